"""A learned start of an ADMM solve: a small network's prediction of the iterate
(Z, gamma) and a per-iteration schedule (rho_k, alpha_k), on the core protocol.

After Sambharya, Hall, Amos and Stellato, "Learning to warm-start fixed-point
optimization algorithms" (JMLR 25, 2024): a network h_w maps a case's
parameters theta (here the step's :class:`~ampc_jax.problem.ProblemData`) to
the point the fixed-point iteration starts from, x^0 = h_w(theta), and w is
trained through K unrolled iterations (:mod:`ampc_jax.tuning.warm_start`). After
Sambharya and Stellato, "Learning algorithm hyperparameters for fast
parametric convex optimization" (2024): the first k iterations run with their
own (rho_i, alpha_i), the rest with the steady ones.

Two kinds of network (:data:`KINDS`), both a multilayer perceptron (tanh hidden
layers, a linear output) on standardised inputs:

* ``"step"`` -- the input is the step's data alone (:func:`problem_features`);
  the output is the inputs u (N_p x n_u), as positions in their ranges, and
  the start is built from them so that it is a fixed point when u is the
  optimum::

      u = lb + (ub - lb) clip(m + s y, 0, 1),  Z = max(0, bin - A_in u),  gamma = kkt(u)

  (Z at the fixed point is the rows' slack b - A_in u*; gamma the least-norm
  multipliers that satisfy every local step's stationarity on the rows u
  leaves active, :func:`kkt_multipliers`: their split between objectives is
  not unique, so it is not learned, and an input the network puts beyond
  its bound is exactly at it, its row active). Used for a solve without a previous iterate (``ampc solve``,
  sweeps of single steps) and, in closed loop, in place of it.
* ``"loop"`` -- the input is the step's data and the previous control step's
  iterate (shifted), and the output a correction of that iterate::

      Z = max(0, Z_prev + s_Z y_Z),   gamma = gamma_prev + s_g y_g

  with the last layer initialised at zero, so an untrained network is the
  warm start of today (the previous step's iterate). Used in closed loop.

:class:`LearnedStart` wraps a formulation as an :class:`~ampc_jax.admm.core.ADMMSolver`:
its ``setup`` also factorises the schedule's k matrices K_j(rho_i) (so a
schedule of k values costs k more factorisations per control step, each one
setup's), and its ``init`` predicts the start and runs the k scheduled
iterations (plain ADMM; a pair frozen once it meets eq.Convergence), which
count as iterations. Everything downstream of the protocol (the runners, the
sweep engine, the closed loop, an exported step) then gets the learned start.
The fixed point, and so the solution, is the formulation's own: only the
path changes.

:class:`StartModel` holds the trained numbers as NumPy arrays (static data,
hashed by a digest of every number, so that a compiled step is specialised
on one model and carries its weights as constants); :meth:`StartModel.arrays`
gives them as the :class:`StartArrays` pytree that training differentiates.
"""

from .document import model_document, model_from_document
from .multipliers import ACTIVE_REL, kkt_multipliers
from .network import (
    FEATURE_CLIP,
    KINDS,
    SCHEDULE_MAX,
    StartArrays,
    StartModel,
    box_coordinates,
    input_of,
    mlp,
    n_features,
    problem_features,
)
from .wrapper import LearnedStart, StartSetup, start_state

__all__ = [
    "ACTIVE_REL",
    "FEATURE_CLIP",
    "KINDS",
    "SCHEDULE_MAX",
    "LearnedStart",
    "StartArrays",
    "StartModel",
    "StartSetup",
    "box_coordinates",
    "input_of",
    "kkt_multipliers",
    "mlp",
    "model_document",
    "model_from_document",
    "n_features",
    "problem_features",
    "start_state",
]
