"""Consensus on the inputs: what Formulations 1 and 2 share (alg:1 with eq.F1_primal / eq.F2_primal).

Both formulations give every objective O_j copies U_j of its group's inputs
and a global copy Z of all inputs, with the consensus constraint
U_j - Z_j = 0 (eq.ConsensusADMM; Z_j the group's part of Z). Per iteration:

* local update (eq.F1_primal, eq.F2_primal): for each objective the QP ::

      min_{U_j}  J_j(U_j) + gamma_j' U_j + rho_j / 2 ||U_j - Z_j||^2
      s.t.       A_in,j U_j^(k) + B_in,j U-tilde_j^(k) <= b_in^(k)

  over the rows that involve an agent of S_j, with the other agents' inputs
  U-tilde_j taken from the previous iterate Z (eq.F1_1; the printed
  ``B_in,j = [B_d(i) | i in S_j]`` is read as the rows' coefficients on the
  agents outside S_j, which is what the text around it describes). J_j carries
  the objective's tracking cost, plus (Formulation 1 only) its agents' input
  weights shared out as R_(i) / m_(i) (eq.F1_obj, paper-notes item 8). The QP is
  solved by an inner ADMM on a factorisation cached per control step
  (:mod:`ampc_jax.admm.local_qp`), ``inner_iterations`` inner steps per
  outer iteration, warm-started from the last.
* global update, the exact minimiser of the augmented Lagrangian over Z for
  per-objective rho_j (the multiplier term is gamma_j'(U_j - Z_j), paper-notes
  item 13), per agent i over its objectives S_(i)::

      Formulation 1 (eq.F1_dual):  Z_(i) = sum_j (gamma_j(i) + rho_j U_j(i)) / sum_j rho_j
      Formulation 2 (eq.F2_dual):  Z_(i) = (2 R_(i) + sum_j rho_j I)^-1 sum_j (gamma_j(i) + rho_j U_j(i))

  (paper-notes items 7 and 14: a matrix R_(i), rho-weighted; after the first
  iteration sum_j gamma_j(i) = 0 in Formulation 1, so eq.F1_dual's average is
  the rho-weighted average of the copies.)
* dual update (alg:1 step 9): gamma_j += rho_j (U_j - Z_j).

Over-relaxation (Boyd et al. 2011, sec. 3.4.3): U_j is replaced in the global
and dual updates by Z_j^prev + alpha (U_j - Z_j^prev); alpha = 1 (default) is
the paper's iteration.

Stopping rule (eq.Convergence per objective, with the inner QP's own
residuals added, so that an outer fixed point is only accepted when the local
QPs are solved)::

    ||r_j||^2 = ||U_j - Z_j||^2 + ||Abar_j U_j - b_j + s_j||^2          <= eps_r
    ||s_j||^2 = ||Z_j - Z_j^prev||^2 + ||s_j - s_j^prev||^2            <= eps_s

(``dual_residual="paper"`` scales the first term by rho_j, as printed).

The fixed point. With box rows only (every row acting on one agent), the
fixed point is the integrated optimum: summing the local KKT conditions over
the objectives gives the integrated ones, with a box row's multiplier the sum
of the objectives' multipliers on it. The same holds for every constraint row
whose agents all lie in each group it touches. A row that couples an agent of
S_j with one outside S_j is different: objective j enforces it with the
outside agent held at Z, with a multiplier of its own, and at the fixed point
the integrated KKT conditions need all objectives touching the row to agree
on one multiplier, which nothing enforces. The fixed point is then a feasible
point at which no objective can improve its own part alone (a generalised
Nash equilibrium of the objectives), not in general the optimum
(``docs/formulations.md``; the gap is pinned by a test).

rho: by default rho_j = ``params.rho[j]`` times sqrt(lambda_min lambda_max) of
objective j's Hessian with its input weights (Formulation 1's H_j, for both
formulations, since Formulation 2's may be singular): Ghadimi et al.'s
optimal penalty for the constraint U_j - Z_j = 0, the analogue of eq.opt_ro,
with the extreme eigenvalues by power iteration. The paper tunes rho by hand
for these two formulations; ``rho_method="given"`` takes ``params.rho`` as
rho_j itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from ..admm import stopping as stop
from ..admm.acceleration import anderson_memory
from ..admm.core import ADMMSolver
from ..admm.costs import padded_costs
from ..admm.hessian import DenseHessian
from ..admm.layout import padded_layout
from ..admm.linalg import block_diag, spd_inverse_dense
from ..admm.local_qp import InnerState, LocalQP, factor, inner_rho, iterate
from ..admm.params import SolverParams, as_params
from ..admm.rho import RhoEstimates, extreme_eigenvalues, select_rho
from ..admm.state import shift_horizon, warm_start
from ..admm.stopping import select_dual_residual
from ..problem.data import ProblemData
from ..problem.errors import ProblemError
from ..problem.topology import Topology
from ..results import SolveResult, SolveStats, Status
from ..validation import check_count

__all__ = [
    "CONSENSUS_DUAL_RESIDUALS",
    "CONSENSUS_RHO_METHODS",
    "ConsensusADMM",
    "ConsensusSetup",
    "ConsensusState",
]

CONSENSUS_RHO_METHODS = ("power", "given")
"""rho_j as a factor on sqrt(lambda_min lambda_max) of H_j (power iteration), or given."""

CONSENSUS_DUAL_RESIDUALS = ("change", "paper")
"""The dual test on the change of Z_j, as is (default) or times rho_j (as printed)."""


class ConsensusState(NamedTuple):
    """Iterate of Formulations 1 and 2 (objectives stacked and padded to U inputs).

    U : (J, N_p, U) local copies U_j (columns ``Topology.group_columns(j)``, padding zero).
    Z : (N_p, n_u) the global inputs.
    gamma : (J, N_p, U) consensus multipliers gamma_j.
    s, y : (J, N_p, n_c) the local QPs' slack and multipliers (inner ADMM state).
    iteration : () int32;  primal, dual : (J,) the stopping rule's squared residuals.
    """

    U: Any
    Z: Any
    gamma: Any
    s: Any
    y: Any
    iteration: Any
    primal: Any
    dual: Any


class ConsensusSetup(NamedTuple):
    """Per-control-step data, built and factorised once.

    qp : the local QPs' rows and cached inverse (:class:`~ampc_jax.admm.local_qp.LocalQP`).
    E : (J, n) linear terms of the local costs.  rho : (J,) rho_j.
    b : (J, N_p, n_c) right-hand sides on the rows touching S_j (zero elsewhere).
    Aout : (J, n_c, n_u) those rows' coefficients on agents outside S_j (U-tilde_j).
    Zmap : (n_u, n_u) the global step's linear map (diag(1 / sum rho) or
        (2R + diag(sum rho))^-1).
    lb, ub : (N_p, n_u) bounds, to project the output.
    relaxation, tol_primal, tol_dual, tol_rel : () from the :class:`SolverParams`.
    hessian : H_j with the input weights (Formulation 1's), formed and inverted
        (:class:`~ampc_jax.admm.hessian.DenseHessian`), for the duality gap.
    R2 : (J, U, U) 2 R_j / m per step (the input weights' share in H_j).
    b2 : (J,) ||b_j||^2, the data part of the relative tolerance's scale.
    """

    qp: LocalQP
    E: Any
    rho: Any
    b: Any
    Aout: Any
    Zmap: Any
    lb: Any
    ub: Any
    relaxation: Any
    tol_primal: Any
    tol_dual: Any
    tol_rel: Any
    hessian: Any
    R2: Any
    b2: Any


@dataclass(frozen=True)
class ConsensusADMM(ADMMSolver):
    """Shared machinery of :class:`FullyDistributed` and :class:`VirtualCenter`;
    the runners are :class:`~ampc_jax.admm.core.ADMMSolver`'s.

    Parameters
    ----------
    topology : the MACS structure (every agent must lie in some group S_j).
    max_iter : outer iteration cap of the ``while_loop`` runner (default 500).
    inner_iterations : inner ADMM iterations per outer iteration on the local
        QPs (default 5). Rule: the most inner iterations that cost no r_time;
        reason: up to 5 the vehicle manoeuvres' r_time is unchanged within
        noise while e_sub p95 and the outer iterations fall about threefold
        (``docs/formulations.md``, "Inner iterations", which gives its
        command).
    anderson : Anderson memory (0 to 3) on the map (Z, gamma, s, y) -> next;
        0 (default) is the plain iteration.
    rho_method : ``"power"`` (default) or ``"given"`` (:data:`CONSENSUS_RHO_METHODS`).
    rho_iterations : power-iteration steps (default 8).
    dual_residual : ``"change"`` (default) or ``"paper"`` (:data:`CONSENSUS_DUAL_RESIDUALS`).
    """

    topology: Topology
    max_iter: int = 500
    inner_iterations: int = 5
    anderson: int = 0
    rho_method: str = "power"
    rho_iterations: int = 8
    dual_residual: str = "change"

    #: Formulation 2 (the input weights in the global step) when True.
    center = False

    @property
    def title(self) -> str:
        """The paper's name of the formulation, for messages (``info.title``)."""
        return "consensus ADMM" if self.info is None else self.info.title

    def __post_init__(self) -> None:
        for name in ("max_iter", "inner_iterations", "rho_iterations"):
            object.__setattr__(self, name, check_count(getattr(self, name), name))
        object.__setattr__(self, "anderson", anderson_memory(self.anderson))
        select_rho(self.rho_method, CONSENSUS_RHO_METHODS)
        select_dual_residual(self.dual_residual, CONSENSUS_DUAL_RESIDUALS)
        T = self.topology
        for i, m in enumerate(T.multiplicity):
            if m == 0:
                raise ProblemError(
                    f"agents[{i}] ({T.agent_names[i]}): in no objective's group; "
                    f"{self.title} needs every agent in some group S_j (give the objective "
                    f"it acts on an 'agents' list that includes it)"
                )

    # -- static structure ------------------------------------------------------------
    @property
    def n_rho(self) -> int:
        """Number of rho_j (one per objective)."""
        return self.topology.n_objectives

    @property
    def rho_rule(self) -> Any:
        """How rho_j is chosen (``rho_method`` resolved: :func:`~ampc_jax.admm.rho.select_rho`)."""
        return select_rho(self.rho_method, CONSENSUS_RHO_METHODS)

    @property
    def dual_rule(self) -> Any:
        """The tested dual residual (``dual_residual`` resolved:
        :func:`~ampc_jax.admm.stopping.select_dual_residual`)."""
        return select_dual_residual(self.dual_residual, CONSENSUS_DUAL_RESIDUALS)

    def _touched(self) -> np.ndarray:
        """(J, n_c) 1 where constraint row c involves an agent of S_j."""
        T = self.topology
        out = np.zeros((T.n_objectives, T.n_c))
        for j, g in enumerate(T.groups):
            for c in range(T.n_c):
                out[j, c] = float(bool(set(T.row_agents(c)) & set(g)))
        return out

    def _outside(self) -> np.ndarray:
        """(J, n_u) 1 on the inputs of agents outside S_j."""
        T = self.topology
        out = np.ones((T.n_objectives, T.n_u))
        for j in range(T.n_objectives):
            out[j, list(T.group_columns(j))] = 0.0
        return out

    # -- per-step setup -----------------------------------------------------------------
    def setup(self, data: ProblemData, params: SolverParams | None = None) -> ConsensusSetup:
        """Local costs, rho_j, the local QPs' factorisation and the global map."""
        T = self.topology
        lay = padded_layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        dt = data.A.dtype
        p = as_params(self.params(dtype=dt) if params is None else params, J, dt)
        c = padded_costs(T, data)
        mask = jnp.asarray(np.tile(lay.umask, (1, N)), dt)
        # H_j with the input weights (Formulation 1's), for rho* in both formulations;
        # the shift keeps its inverse finite when some direction costs nothing
        n = N * U
        tr = jnp.einsum("jaa->j", c.H * mask[:, :, None]) / jnp.sum(mask, axis=1)
        delta = (jnp.finfo(dt).eps * tr)[:, None, None] * jnp.eye(n, dtype=dt)
        Hinv = spd_inverse_dense(c.H + delta)
        lam_min, lam_max = extreme_eigenvalues(c.H, Hinv, mask, self.rho_iterations)
        # Ghadimi's optimal penalty for U_j - Z_j = 0, times params.rho (or given)
        rho = self.rho_rule.rho(p.rho, RhoEstimates(lambda: jnp.sqrt(lam_min * lam_max)))
        Rj = 0.5 * (c.BH - jnp.asarray(np.eye(U)[None] * (1.0 - lay.umask)[:, :, None], dt))
        if self.center:  # Formulation 2: no input weights in the local cost
            H = c.H - block_diag(2.0 * Rj, N)
            lam_min_l, lam_max_l = lam_min * 0.0, lam_max  # a lower bound of H's spectrum
        else:
            H = c.H
            lam_min_l, lam_max_l = lam_min, lam_max
        eye = jnp.eye(n, dtype=dt)
        P = H + rho[:, None, None] * eye
        # the rows touching S_j, on S_j's columns and (for U-tilde_j) on the others
        touched = jnp.asarray(self._touched(), dt)
        Aix = jnp.pad(data.Ain, ((0, 0), (0, 1)))  # padded column index -> 0
        A = jnp.moveaxis(Aix[:, lay.cols], 1, 0) * touched[:, :, None]  # (J, n_c, U)
        Aout = data.Ain[None] * touched[:, :, None] * jnp.asarray(self._outside(), dt)[:, None, :]
        b = data.bin[None] * touched[:, None, :]
        sigma = inner_rho(lam_min_l + rho, lam_max_l + rho, A)
        qp = factor(P, A, sigma, N)
        # global step: Z^(k) = Zmap sum_j P_j'(gamma_j + rho_j U_j)^(k)
        Psel = jnp.asarray(lay.P, dt)  # (J, U, n_u)
        den = jnp.einsum("j,jun->n", rho, Psel)
        if self.center:
            Zmap = spd_inverse_dense((2.0 * data.R + jnp.diag(den))[None])[0]
        else:
            Zmap = jnp.diag(1.0 / jnp.where(den > 0, den, 1.0))
        return ConsensusSetup(
            qp=qp,
            E=c.E,
            rho=rho,
            b=b,
            Aout=Aout,
            Zmap=Zmap,
            lb=data.lb,
            ub=data.ub,
            relaxation=p.relaxation,
            tol_primal=p.tol_primal,
            tol_dual=p.tol_dual,
            tol_rel=p.tol_rel,
            hessian=DenseHessian(c.H, Hinv),
            R2=2.0 * Rj,
            b2=jnp.sum(b * b, axis=(1, 2)),
        )

    # -- states -----------------------------------------------------------------------
    def cold_state(self, dtype: Any = None) -> ConsensusState:
        """alg:1's cold start: zeros, residuals inf."""
        dt = jnp.result_type(float) if dtype is None else dtype
        T = self.topology
        J, U = padded_layout(T).cols.shape
        N = T.horizon
        return ConsensusState(
            U=jnp.zeros((J, N, U), dt),
            Z=jnp.zeros((N, T.n_u), dt),
            gamma=jnp.zeros((J, N, U), dt),
            s=jnp.zeros((J, N, T.n_c), dt),
            y=jnp.zeros((J, N, T.n_c), dt),
            iteration=jnp.zeros((), jnp.int32),
            primal=jnp.full((J,), jnp.inf, dt),
            dual=jnp.full((J,), jnp.inf, dt),
        )

    @staticmethod
    def shift(state: ConsensusState, steps: int = 1) -> ConsensusState:
        """The MPC warm start: the iterate moved ``steps`` (0 or 1) along the horizon."""
        inf = jnp.full_like(state.primal, jnp.inf)
        return ConsensusState(
            U=shift_horizon(state.U, steps, axis=1),
            Z=shift_horizon(state.Z, steps),
            gamma=shift_horizon(state.gamma, steps, axis=1),
            s=shift_horizon(state.s, steps, axis=1),
            y=shift_horizon(state.y, steps, axis=1),
            iteration=jnp.zeros((), jnp.int32),
            primal=inf,
            dual=inf,
        )

    def init(self, setup: ConsensusSetup, warm: ConsensusState | None = None) -> ConsensusState:
        """Cold start, or ``warm`` with its iteration count and residuals reset."""
        return warm_start(
            self.cold_state(setup.rho.dtype),
            warm,
            f"a ConsensusState (a previous {self.title} result's .state)",
        )

    def local_inputs(self, state: ConsensusState) -> tuple:
        """U_j, (N_p, n_u,j) per objective, columns in ``Topology.group_columns(j)`` order."""
        lay = padded_layout(self.topology)
        return tuple(state.U[..., j, :, :u] for j, u in enumerate(lay.u_sizes))

    # -- one iteration ------------------------------------------------------------------
    def step(self, setup: ConsensusSetup, st: ConsensusState) -> ConsensusState:
        """One outer iteration: local QPs, global and dual updates (alg:1 steps 5-9)."""
        T = self.topology
        lay = padded_layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        dt = setup.rho.dtype
        Psel = jnp.asarray(lay.P, dt)
        rho = setup.rho[:, None, None]
        Zj = jnp.einsum("jun,kn->jku", Psel, st.Z)  # Z_j, (J, N, U)
        q = setup.E + (st.gamma - rho * Zj).reshape(J, N * U)
        b = setup.b - jnp.einsum("jcn,kn->jkc", setup.Aout, st.Z)  # eq.F1_1's U-tilde_j
        u, inner, ip, idl = iterate(setup.qp, q, b, InnerState(st.s, st.y), self.inner_iterations)
        Uj = u.reshape(J, N, U)
        Ur = Zj + setup.relaxation * (Uj - Zj)
        num = jnp.einsum("jun,jku->kn", Psel, st.gamma + rho * Ur)
        Z = num @ setup.Zmap  # eq.F1_dual / eq.F2_dual (Zmap symmetric)
        Zn = jnp.einsum("jun,kn->jku", Psel, Z)
        gamma = st.gamma + rho * (Ur - Zn)
        r = Uj - Zn
        dz = self.dual_rule.dual(rho, Zn - Zj)
        primal = jnp.sum(r * r, axis=(1, 2)) + ip
        dual = jnp.sum(dz * dz, axis=(1, 2)) + idl
        return ConsensusState(Uj, Z, gamma, inner.s, inner.y, st.iteration + 1, primal, dual)

    def converged(self, setup: ConsensusSetup, state: ConsensusState) -> Any:
        """eq.Convergence for every objective, with the local QPs' residuals, and
        the relative tolerance on scale_j^2 = ||Z_j||^2 + ||b_j||^2: the sizes of
        the consensus target and of the local rows' right-hand sides
        (:func:`~ampc_jax.admm.stopping.converged`)."""
        cols = jnp.asarray(padded_layout(self.topology).P.sum(axis=1), state.Z.dtype)  # (J, n_u)
        scale2 = cols @ jnp.sum(state.Z * state.Z, axis=0) + setup.b2
        return stop.converged(
            state.primal,
            state.dual,
            setup.tol_primal,
            setup.tol_dual,
            setup.tol_rel,
            scale2,
            self.dual_rule.scale(setup.rho, scale2),
        )

    # -- the map's argument, for Anderson acceleration ---------------------------------
    def point(self, state: ConsensusState) -> Any:
        """The ADMM map's argument (Z, gamma, s, y), flattened (U is an output only)."""
        return jnp.concatenate(
            [state.Z.ravel(), state.gamma.ravel(), state.s.ravel(), state.y.ravel()]
        )

    def at(self, x: Any, state: ConsensusState) -> ConsensusState:
        """``state`` with (Z, gamma, s, y) from the vector ``x`` (:meth:`point`'s inverse)."""
        out, o = [], 0
        for a in (state.Z, state.gamma, state.s, state.y):
            out.append(x[o : o + a.size].reshape(a.shape))
            o += a.size
        return state._replace(Z=out[0], gamma=out[1], s=out[2], y=out[3])

    def result(self, setup: ConsensusSetup, state: ConsensusState) -> SolveResult:
        """The global inputs Z projected on the bounds, the status, and the duality
        gap (``stats.gap``; :func:`~ampc_jax.admm.stopping.duality_gap`).

        The dual point: lambda = sum_j y_j (the local QPs' row multipliers, >= 0)
        and mu_j = gamma_j + A_j' y_j (Formulation 2: minus 2 R_j / m Z_j, the
        input weights its local cost leaves to the global step), corrected by
        an equal share per copy so that sum_j P_j' mu_j = Abar' lambda holds
        exactly (it holds at the fixed point; the correction also covers rows
        that couple agents of different groups)."""
        u = jnp.clip(state.Z, setup.lb, setup.ub)
        conv = self.converged(setup, state)
        finite = jnp.all(jnp.isfinite(u)) & jnp.all(jnp.isfinite(state.primal))
        status = jnp.where(
            ~finite,
            Status.NUMERICAL_ERROR,
            jnp.where(conv, Status.SOLVED, Status.MAX_ITER_REACHED),
        ).astype(jnp.int32)
        u = jnp.where(finite, u, jnp.zeros_like(u))
        gap = jnp.where(finite, self._gap(setup, state, u), jnp.inf)
        return SolveResult(
            u=u,
            iterations=state.iteration,
            converged=conv & finite,
            status=status,
            primal_residual=state.primal,
            dual_residual=state.dual,
            rho=setup.rho,
            state=state,
            stats=SolveStats(gap=gap),
        )

    def _gap(self, setup: ConsensusSetup, state: ConsensusState, u: Any) -> Any:
        lay = padded_layout(self.topology)
        J = lay.cols.shape[0]
        dt = u.dtype
        Psel = jnp.asarray(lay.P, dt)  # (J, U, n_u)
        count = jnp.asarray(lay.P.sum(axis=(0, 1)), dt)  # copies of each input, m_(i)
        A, y = setup.qp.A, state.y
        Ay = jnp.einsum("jcu,jkc->jku", A, y)  # A_j' y_j on S_j's columns
        mu = state.gamma + Ay
        if self.center:
            Zj = jnp.einsum("jun,kn->jku", Psel, state.Z)
            mu = mu - jnp.einsum("juv,jkv->jku", setup.R2, Zj)
        # sum_j P_j' mu_j = Abar' lambda, lambda = sum_j y_j: the rows' full coefficients
        # are A_j on S_j and Aout_j outside
        full = jnp.einsum("jun,jku->kn", Psel, Ay) + jnp.einsum("jcn,jkc->kn", setup.Aout, y)
        miss = (full - jnp.einsum("jun,jku->kn", Psel, mu)) / jnp.where(count > 0, count, 1.0)
        mu = mu + jnp.einsum("jun,kn->jku", Psel, miss)
        uj = jnp.einsum("jun,kn->jku", Psel, u)
        Au = jnp.einsum("jcu,jku->jkc", A, uj) + jnp.einsum("jcn,kn->jkc", setup.Aout, u)
        slack = jnp.sum(y * (setup.b - Au))  # lambda'(b - Abar u)
        return stop.duality_gap(setup.hessian, setup.E, uj.reshape(J, -1), mu.reshape(J, -1), slack)
