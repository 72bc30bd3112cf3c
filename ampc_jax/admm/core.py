"""The ADMM core protocol, declared once, and its runners, written once.

After jaxopt's ``IterativeSolver`` (a solver is ``init`` and ``update``; the
base class runs them) and optax's ``init`` / ``update`` pair: every
formulation is an :class:`ADMMSolver` and implements the protocol

* ``setup(data, params) -> setup`` -- per control step: costs, rho_j and the
  factorisations, built once (everything the iteration only reads);
* ``init(setup, warm=None) -> state`` -- the cold start of alg:1, or a warm
  start with its iteration count and residuals reset;
* ``step(setup, state) -> state`` -- one iteration of alg:1 (local, global
  and dual updates, and the stopping rule's residuals);
* ``converged(setup, state) -> bool`` -- the stopping rule (eq.Convergence);
* ``result(setup, state) -> SolveResult`` -- the inputs, the status and
  the residuals of the iterate;
* ``point(state) -> x`` and ``at(x, state) -> state`` -- the ADMM map's
  argument as one vector and back, what Anderson acceleration extrapolates;
* ``cold_state(dtype)`` and ``shift(state, steps)`` -- the warm-start story;

with its static options as fields (``topology``, ``max_iter``, ``anderson``,
...). The runners are this class's: :meth:`~ADMMSolver.run` (a ``while_loop``
to the stopping rule, for deployment), :meth:`~ADMMSolver.run_fixed` (a
fixed-length ``scan``, differentiable, for tuning), :meth:`~ADMMSolver.solve`
and :meth:`~ADMMSolver.solve_fixed` (setup, init, run, result) and
:meth:`~ADMMSolver.params`. Anything that iterates a formulation in its own
way (the sweep engine's segmented runner, :mod:`ampc_jax.sweep.engine`) uses
these protocol methods only.
"""

from __future__ import annotations

import abc
import keyword
from dataclasses import dataclass
from typing import Any, ClassVar

from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import SolveResult
from .feasibility import with_certificate
from .params import DEFAULT_TOL, DEFAULT_TOL_REL, SolverParams, solver_params
from .runners import run_fixed, run_while

__all__ = ["RHO_BASES", "RHO_COUNTS", "ADMMSolver", "FormulationInfo"]

RHO_COUNTS = ("objective", "one")
"""How many rho a formulation takes: one rho_j per objective, or one for the problem."""

RHO_BASES = ("opt_ro", "hessian")
"""What ``params.rho`` is a factor on: eq.opt_ro's rho_j* (Local Explicit, the
integrated ADMM), or sqrt(lambda_min lambda_max) of H_j (Ghadimi's penalty for
the consensus constraint U_j - Z_j = 0, Formulations 1 and 2)."""


@dataclass(frozen=True)
class FormulationInfo:
    """What a formulation is, declared once on its class (``info``) and read by
    everything that chooses or describes one (the registry,
    :mod:`ampc_jax.formulations.registry`; the closed loop, sweeps, tuning, the CLI).

    name : the registry name (``"local_explicit"``), an identifier; ``"none"`` is
        the closed loop's "no MPC" and taken.
    title : the paper's name, for messages (``"Local Explicit (Formulation 3)"``).
    label : the short name figure legends print (``"Local Explicit"``).
    rho : ``"objective"`` (one rho_j per objective) or ``"one"`` (one rho for
        the whole problem) (:data:`RHO_COUNTS`).
    rho_basis : what ``params.rho`` multiplies (:data:`RHO_BASES`); it picks the
        example default a closed loop starts from (``rho_scale`` or
        ``consensus_rho_scale``; a one-rho formulation takes
        ``integrated_rho_scale``).
    decomposed : one local problem per objective (True), or the integrated MPC
        solved whole (False: the peer of the time ratio eq.t_ratio, for which
        ``ampc solve --solver`` offers the reference solvers).
    batch_kkt : the ``kkt`` option a batch of single steps is built with (a
        sweep), or None where the formulation has no such option.
    closed_loop : it may run as the controller of a closed loop.
    learned_start : it serves a learned start (:mod:`ampc_jax.admm.learned_start`):
        its iterate is an :class:`~ampc_jax.admm.state.ADMMState` and it
        implements :meth:`ADMMSolver.start_from_inputs`.
    state_file : its iterate is written and read per objective (``local_inputs``,
        ``multipliers``, ``state_of``): ``ampc solve --json``'s ``warm_state``
        and ``--warm-start``.
    """

    name: str
    title: str
    label: str
    rho: str = "objective"
    rho_basis: str = "opt_ro"
    decomposed: bool = True
    batch_kkt: str | None = None
    closed_loop: bool = True
    learned_start: bool = False
    state_file: bool = False

    def __post_init__(self) -> None:
        if not self.name.isidentifier() or keyword.iskeyword(self.name) or self.name == "none":
            raise ValueError(
                f"name: expected an identifier other than 'none' (the closed loop's "
                f"no-MPC choice), got {self.name!r}"
            )
        if self.rho not in RHO_COUNTS:
            raise ValueError(f"rho: expected one of {RHO_COUNTS}, got {self.rho!r}")
        if self.rho_basis not in RHO_BASES:
            raise ValueError(f"rho_basis: expected one of {RHO_BASES}, got {self.rho_basis!r}")

    def n_rho(self, n_objectives: int) -> int:
        """The length of ``params.rho`` for a problem of ``n_objectives`` objectives."""
        return int(n_objectives) if self.rho == "objective" else 1


class ADMMSolver(abc.ABC):
    """An ADMM formulation: the core protocol (abstract) and the runners built on it.

    Subclasses are frozen dataclasses whose fields are the static options;
    they must have ``topology``, ``max_iter`` (the ``while_loop`` runner's cap)
    and ``anderson`` (Anderson memory, 0 for the plain iteration). The numbers
    one tunes are the :class:`~ampc_jax.admm.params.SolverParams` argument, so
    one compiled step serves every parameter point.
    """

    topology: Topology
    max_iter: int
    anderson: int

    #: what the formulation is (:class:`FormulationInfo`); None for a solver that
    #: wraps another (:class:`~ampc_jax.admm.learned_start.LearnedStart`)
    info: ClassVar[FormulationInfo | None] = None

    # -- the protocol ------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def n_rho(self) -> int:
        """Number of rho_j (the length of ``params.rho``)."""

    @abc.abstractmethod
    def setup(self, data: ProblemData, params: SolverParams | None = None) -> Any:
        """Everything the iteration reads, built and factorised once per control step."""

    @abc.abstractmethod
    def init(self, setup: Any, warm: Any = None) -> Any:
        """The cold start, or ``warm`` (checked) with its iteration count and residuals reset."""

    @abc.abstractmethod
    def step(self, setup: Any, state: Any) -> Any:
        """One iteration (alg:1 steps 5-9), with the stopping rule's residuals."""

    @abc.abstractmethod
    def converged(self, setup: Any, state: Any) -> Any:
        """The stopping rule (eq.Convergence) at ``state``: a () bool."""

    @abc.abstractmethod
    def result(self, setup: Any, state: Any) -> SolveResult:
        """The :class:`~ampc_jax.results.SolveResult` of ``state``."""

    @abc.abstractmethod
    def point(self, state: Any) -> Any:
        """The ADMM map's argument at ``state`` as one vector (what Anderson extrapolates)."""

    @abc.abstractmethod
    def at(self, x: Any, state: Any) -> Any:
        """``state`` with its map argument replaced by the vector ``x`` (:meth:`point`'s inverse)."""

    @abc.abstractmethod
    def cold_state(self, dtype: Any = None) -> Any:
        """alg:1's cold start (zeros, residuals inf) in ``dtype``."""

    @abc.abstractmethod
    def shift(self, state: Any, steps: int = 1) -> Any:
        """The MPC warm start: ``state`` moved ``steps`` (0 or 1) along the horizon."""

    def start_from_inputs(self, setup: Any, data: ProblemData, u: Any, like: Any) -> Any:
        """The state at which the inputs ``u`` (N_p x n_u) are a fixed point of the
        iteration on ``setup`` (iteration 0, residuals inf; ``like``: a state of
        the wanted dtype and structure, e.g. :meth:`init`'s). What a learned
        ``"step"`` start builds from its predicted inputs
        (:mod:`ampc_jax.admm.learned_start`). Optional: a formulation declaring
        ``info.learned_start`` implements it."""
        raise NotImplementedError(
            f"{type(self).__name__}: no start from given inputs (it serves no learned start)"
        )

    # -- the runners, once ---------------------------------------------------------------
    def params(
        self,
        rho: Any = 1.0,
        relaxation: Any = 1.0,
        tol_primal: Any = DEFAULT_TOL,
        tol_dual: Any = DEFAULT_TOL,
        dtype: Any = None,
        *,
        tol_rel: Any = DEFAULT_TOL_REL,
    ) -> SolverParams:
        """Validated :class:`SolverParams` with ``n_rho`` rho values
        (:func:`~ampc_jax.admm.params.solver_params`): ``rho`` a factor on the
        formulation's automatic rho_j (rho_j itself with ``rho_method="given"``),
        default 1.0; ``relaxation`` in (0, 2), default 1.0 (the paper);
        absolute tolerances default 1e-6, the relative one ``tol_rel`` 0
        (:class:`~ampc_jax.admm.params.SolverParams`)."""
        return solver_params(
            self.n_rho,
            rho=rho,
            relaxation=relaxation,
            tol_primal=tol_primal,
            tol_dual=tol_dual,
            tol_rel=tol_rel,
            dtype=dtype,
        )

    def setup_from(self, data: ProblemData, params: SolverParams | None, warm: Any) -> Any:
        """:meth:`setup` for a solve starting from ``warm`` (a previous result's
        state or None): a formulation whose setup reuses something the warm
        start carries (Local Explicit's ``rho_method="carried"``) overrides it."""
        return self.setup(data, params)

    def finisher(self, setup: Any) -> Any:
        """The exact finish of an iterate, ``finish(before, after, ran) -> state``
        (:mod:`~.finish`), tried every :attr:`finish_every` iterations by the
        runners; None (default) where the formulation has none or it is off."""
        return None

    finish_every: int = 1
    finish_first: int = 1

    def run(self, setup: Any, state: Any) -> Any:
        """``lax.while_loop`` until :meth:`converged`, ``max_iter`` or a non-finite
        residual (deployment; no reverse-mode derivative); with a finish
        (:meth:`finisher`), in segments of ``finish_every`` iterations, each
        ended by a finish attempt."""
        return run_while(
            lambda st: self.step(setup, st),
            lambda st: self.converged(setup, st),
            state,
            self.max_iter,
            anderson=self.anderson,
            point=self.point,
            at=self.at,
            finish=self.finisher(setup),
            every=self.finish_every,
            first=self.finish_first,
        )

    def run_fixed(self, setup: Any, state: Any, iterations: int) -> Any:
        """Exactly ``iterations`` iterations under ``lax.scan`` (differentiable)."""
        return run_fixed(
            lambda st: self.step(setup, st),
            state,
            iterations,
            anderson=self.anderson,
            point=self.point,
            at=self.at,
        )

    def solve(
        self, data: ProblemData, params: SolverParams | None = None, warm: Any = None
    ) -> SolveResult:
        """One control step to tolerance: setup, init, :meth:`run`, result, and
        the infeasibility search when it did not converge
        (:func:`~ampc_jax.admm.feasibility.with_certificate`).

        ``params``: the :class:`SolverParams` (default :meth:`params` ()), an
        argument of the compiled step; ``warm``: a previous result's ``state``
        (shifted with :meth:`shift`). Pure and jittable; vmap over ``data`` and
        ``params`` together."""
        setup = self.setup_from(data, params, warm)
        res = self.result(setup, self.run(setup, self.init(setup, warm)))
        return with_certificate(res, data)

    def solve_fixed(
        self,
        data: ProblemData,
        iterations: int,
        params: SolverParams | None = None,
        warm: Any = None,
    ) -> SolveResult:
        """One control step with a fixed iteration count (:meth:`run_fixed`): for
        ``jax.grad`` with respect to ``data`` and ``params``."""
        setup = self.setup_from(data, params, warm)
        return self.result(setup, self.run_fixed(setup, self.init(setup, warm), iterations))
