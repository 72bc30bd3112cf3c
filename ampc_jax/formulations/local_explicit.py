"""Formulation 3, Local Explicit (eq.integMPC_F3 to eq.F3_multiplier), in pure JAX.

The integrated MPC is split into one local problem per objective O_j over the
copies U_j of the inputs of its agent group S_j. The constraints become
equalities with a shared non-negative slack Z (eq.integMPC_F3)::

    Abar_j U_j - bbar_j + Z_j = 0,   Z >= 0,

and consensus ADMM iterates, per objective j and constraint row c:

* local update (eq.F3_primal), a closed-form solve with a matrix factorised
  once per control step (the setup stores K_j^-1, formed or as its Woodbury
  factors, and K_j^-1 E_j, so an iteration is a few small matrix-vector
  products)::

      U_j = -(H_j + rho_j Abar_j' Abar_j)^-1 [E_j + Abar_j' (rho_j (Z_j - bbar_j) + gamma_j)]

* global update, the max-projection (eq.F3_dual) in its exact form for
  per-objective rho_j (paper-notes item 14: the rho-weighted average; the printed
  equal-weight average converges to the wrong point when the rho_j differ)::

      v_jc = (-Abar_j U_j - gamma_j / rho_j + bbar_j)_c
      Z_c  = max(0, sum_j rho_j v_jc / sum_j rho_j)       (j over objectives carrying c)

* dual update (eq.F3_multiplier)::

      gamma_j += rho_j (Abar_j U_j - bbar_j + Z_j)

* stopping rule (eq.Convergence, per objective, paper-notes items 6 and 17)::

      ||r_j||^2 = ||Abar_j U_j - bbar_j + Z_j||^2 <= eps_r,
      ||s_j||^2 = ||rho_j (Z_j^q - Z_j^(q-1))||^2 <= eps_s     (``dual_residual="paper"``)
      ||Z_j^q - Z_j^(q-1)||^2 <= eps_s                          (default, ``"slack"``)

Objective j's local cost carries its outputs' tracking cost and the input
weights of its agents shared out as R_(i) / m_(i) (eq.F1_obj with paper-notes item 8).
Objective j carries the constraint rows whose agents all lie in S_j
(:meth:`Topology.group_rows`); a shared agent's box rows are shared by all its
objectives, which is what makes their copies agree (paper-notes item 10).

The default rho_j is eq.opt_ro (:mod:`ampc_jax.admm.rho`), its extreme
eigenvalues estimated by power iteration (``rho_method="eigh"`` for the exact
form), times the factor ``params.rho`` (1: the paper's rho*).

Implementation: the objectives are stacked on a leading axis and padded to
common sizes (:mod:`ampc_jax.admm.layout`), so every per-objective operation
is one batched call; the KKT solve of the local step is a strategy
(:mod:`ampc_jax.admm.kkt`). The numbers one may tune (rho, relaxation,
tolerances) are the :class:`~ampc_jax.admm.params.SolverParams` argument of
:meth:`LocalExplicit.solve`, so one compiled step serves every setting.

Everything here handles one problem; batch with ``jax.vmap`` over
:class:`~ampc_jax.problem.ProblemData` and :class:`SolverParams` together.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..admm import stopping as stop
from ..admm.acceleration import anderson_memory
from ..admm.core import ADMMSolver, FormulationInfo
from ..admm.costs import padded_costs
from ..admm.finish import (
    FINISH_CORRECTIONS,
    FINISH_EVERY,
    attempt,
    default_tol,
    finish_data,
    finish_solve,
    select_finish,
)
from ..admm.kkt import KKT, KKT_SOLVES, select_kkt
from ..admm.layout import padded_layout
from ..admm.learned_start.multipliers import kkt_multipliers
from ..admm.params import SolverParams, as_params
from ..admm.rho import RHO_STEPS, RhoEstimates, eq_opt_ro_exact, eq_opt_ro_power, select_rho
from ..admm.state import ADMMState, cold_state, shift_state, warm_start
from ..admm.stopping import select_dual_residual
from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import SolveResult, SolveStats, Status
from ..validation import check_count

__all__ = ["DUAL_RESIDUALS", "RHO_METHODS", "LocalExplicit", "LocalSetup"]

RHO_METHODS = ("power", "eigh", "given", "carried")
"""How rho_j is found: eq.opt_ro by Lanczos steps or exactly, or carried by the
warm start from the previous step (times ``params.rho``), or ``params.rho`` itself."""

DUAL_RESIDUALS = ("slack", "paper")
"""Forms of the dual stopping test (see :class:`LocalExplicit`)."""


class LocalSetup(NamedTuple):
    """Per-control-step data of Local Explicit, built and factorised once.

    The objectives are stacked on a leading axis j and padded to U inputs per
    step (the largest n_u,j); n = N_p U. Padded inputs carry an identity block
    in K_j and zero columns in A_in,j, so they never move. Constraint rows keep
    the problem's own numbering (all n_c rows for every objective): the rows
    objective j does not carry have zero coefficients and right-hand side and
    are masked out of the global and dual steps. So the global step needs no
    gather: the unpadded iterates are exactly those of the per-objective
    algorithm.

    Ain : (J, n_c, U) per-step rows A_in,j (Abar_j = I_{N_p} (x) A_in,j), zero
        on rows objective j does not carry; or, with the compact row layout
        (many more rows than any objective carries, ``COMPACT_ROWS``), (J, C, U)
        with each objective's own rows gathered and padded with zero rows.
    b : (J, N_p, n_c) bbar_j, step by step (zero on rows not carried); (J, N_p, C)
        in the compact layout.
    rho : (J,) rho_j.
    Kinv : K_j^-1 in the KKT strategy's form (:mod:`ampc_jax.admm.kkt`),
        K_j = H_j + rho_j Abar_j' Abar_j (factorised once).
    KE : (J, n) K_j^-1 E_j.
    inv_den : (n_c,) 1 / sum of rho_j over the objectives carrying each slack row.
    lb, ub : (N_p, n_u) bounds, to project the consensus output.
    relaxation, tol_primal, tol_dual, tol_rel : () from the :class:`SolverParams`.
    E : (J, n) E_j and hessian : H_j in the KKT strategy's form
        (:mod:`ampc_jax.admm.hessian`), for the duality gap of a result.
    b2 : (J,) ||bbar_j||^2, the data part of the relative tolerance's scale.
    rho_star : (J,) eq.opt_ro's rho_j* the rule used (zeros for ``"given"``), what
        the result's state carries to the next step.
    finish : the integrated LQ problem of the exact finish
        (:class:`~ampc_jax.admm.finish.FinishData`), None without a finish.
    """

    Ain: Any
    b: Any
    rho: Any
    Kinv: Any
    KE: Any
    inv_den: Any
    lb: Any
    ub: Any
    relaxation: Any
    tol_primal: Any
    tol_dual: Any
    tol_rel: Any
    E: Any
    hessian: Any
    b2: Any
    rho_star: Any = None
    finish: Any = None


@dataclass(frozen=True)
class LocalExplicit(ADMMSolver):
    """Local Explicit solver for one :class:`Topology`: its static options.

    The static options fix the compiled program; the numbers one may tune are
    the :class:`~ampc_jax.admm.params.SolverParams` argument of :meth:`solve`
    (:meth:`params` builds them). The runners (:meth:`run`, :meth:`run_fixed`,
    :meth:`solve`, :meth:`solve_fixed`) are :class:`~ampc_jax.admm.core.ADMMSolver`'s.

    Parameters
    ----------
    topology : the MACS structure.
    max_iter : iteration cap of the ``while_loop`` runner (default 500).
    anderson : memory m of Anderson acceleration (type II, Walker and Ni 2011)
        of the ADMM map (Z, gamma) -> (Z+, gamma+), 0 to 3; 0 (default) is the
        paper's plain iteration. The closed-loop defaults use 3 (iterations
        p95 17.2 -> 14 on the cruise example, the paper's rho* iteration's
        median 190 -> 43 at N_p = 10, ``bench/bench_local_explicit.py``). An
        accelerated iteration costs more, so with few iterations to save a
        step can take longer. Gradients through an accelerated
        :meth:`solve_fixed` match finite differences while the iterate is still
        above round-off (once converged to machine precision Anderson's least
        squares, and so the map, is no longer smooth).
    kkt : the KKT solve strategy of the local step, one of
        ``"auto"`` (default), ``"dense"``, ``"woodbury"``, ``"woodbury_factored"``,
        ``"riccati"`` (:func:`~ampc_jax.admm.kkt.select_kkt`; each wins at some
        size there).
    rho_method : ``"power"`` (default): rho_j = ``params.rho[j]`` times eq.opt_ro's
        rho_j*, its extreme eigenvalues by ``rho_iterations`` Lanczos steps on
        the pencil (within 10 % of the exact value on the tested problems);
        ``"eigh"``: the same with the exact eigendecomposition (the reference
        the estimate is tested against; several times slower on XLA:CPU);
        ``"given"``: rho_j = ``params.rho[j]`` (no eq.opt_ro; for an objective
        whose H_j is singular, where eq.opt_ro is undefined); ``"carried"``:
        as ``"power"``, but the rho_j* the warm start carries (the previous
        step's, ``ADMMState.rho_star``) is used as it is, so a drive estimates
        it only at its cold start and where a solve asked for a new estimate
        (``rho_refresh``). Objectives with column-rank-deficient rows always
        use the exact form.
    rho_refresh : with ``rho_method="carried"``, a solve that did not converge
        or took more than this many iterations passes no rho_j* on (its
        state's ``rho_star`` is 0), so the next step estimates anew (default
        100).
    rho_iterations : Lanczos steps of ``rho_method="power"`` (default 4,
        :data:`~ampc_jax.admm.rho.RHO_STEPS`; each applies H_j and H_j^-1 once).
    dual_residual : ``"slack"`` (default) tests ||Z_j^q - Z_j^(q-1)||^2 <= eps_s,
        the slack's change in the constraints' own units; ``"paper"`` tests
        ||s_j||^2 = ||rho_j (Z_j^q - Z_j^(q-1))||^2 <= eps_s as printed, to
        reproduce the paper. The printed form scales with rho_j, and eq.opt_ro
        gives rho_j ~ 1e-6 when the weights are per Nm^2 (vehicle examples): a
        fixed eps_s is then met while Z still moves by newtons.
        ``SolveResult.dual_residual`` reports the tested quantity.
    finish : ``"none"`` (default, the paper's iteration) or ``"active_set"``:
        on the start's slack active set (rows with Z_c = 0; a warm start's,
        after ``finish_first`` iterations) and then every ``finish_every``
        iterations where that set did not change in the last iteration, solve
        the integrated problem with those rows as equalities exactly and check
        its KKT conditions, with up to ``finish_corrections`` primal-dual
        active-set steps (:mod:`~ampc_jax.admm.finish`). A verified finish
        replaces the iterate (U_j its inputs, Z its slack, gamma kept) and
        reports its own residuals: ``primal_residual`` the rows' violation
        squared (objective j's rows), ``dual_residual`` 0 (stationarity holds
        exactly); the solve stops when they pass eq.Convergence. A rejected
        finish leaves the iterate as it was. Not for differentiation
        (:meth:`solve_fixed` with a finish is forward only).
    finish_every : iterations between finish attempts (default 8,
        :data:`~ampc_jax.admm.finish.FINISH_EVERY`).
    finish_first : iterations before the first attempt (default 0: the start's
        own active set).
    finish_corrections : primal-dual active-set steps per attempt (default 2,
        :data:`~ampc_jax.admm.finish.FINISH_CORRECTIONS`).

    Use :meth:`solve` for deployment (early stop) and :meth:`solve_fixed` for
    differentiation (fixed iteration count under ``lax.scan``). Both are pure
    and jittable; ``jax.jit(solver.solve)`` compiles one control step, which
    serves every :class:`SolverParams` without recompiling.
    """

    info = FormulationInfo(
        name="local_explicit",
        title="Local Explicit (Formulation 3)",
        label="Local Explicit",
        rho="objective",
        rho_basis="opt_ro",
        decomposed=True,
        batch_kkt="riccati",
        closed_loop=True,
        learned_start=True,
        state_file=True,
    )

    topology: Topology
    max_iter: int = 500
    anderson: int = 0
    kkt: str = "auto"
    rho_method: str = "power"
    rho_iterations: int = RHO_STEPS
    dual_residual: str = "slack"
    rho_refresh: int = 100
    finish: str = "none"
    finish_every: int = FINISH_EVERY
    finish_first: int = 0
    finish_corrections: int = FINISH_CORRECTIONS

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_iter", check_count(self.max_iter, "max_iter"))
        object.__setattr__(self, "anderson", anderson_memory(self.anderson))
        object.__setattr__(
            self, "rho_iterations", check_count(self.rho_iterations, "rho_iterations")
        )
        if self.kkt not in KKT_SOLVES:
            raise ValueError(f"kkt: expected one of {KKT_SOLVES}, got {self.kkt!r}")
        select_rho(self.rho_method, RHO_METHODS)
        object.__setattr__(self, "rho_refresh", check_count(self.rho_refresh, "rho_refresh", 1))
        select_dual_residual(self.dual_residual, DUAL_RESIDUALS)
        object.__setattr__(self, "finish_every", check_count(self.finish_every, "finish_every", 1))
        object.__setattr__(self, "finish_first", check_count(self.finish_first, "finish_first", 0))
        object.__setattr__(
            self,
            "finish_corrections",
            check_count(self.finish_corrections, "finish_corrections", 0),
        )
        select_finish(self.finish, self.finish_every, self.finish_corrections)
        select_kkt(self.topology, self.kkt)  # validates the choice for this topology
        self.topology.check_local_explicit()

    # -- the parameters ---------------------------------------------------------------
    @property
    def n_rho(self) -> int:
        """Number of rho_j (one per objective)."""
        return self.topology.n_objectives

    @property
    def kkt_solve(self) -> KKT:
        """The KKT solve strategy in use (``kkt`` resolved for this topology)."""
        return select_kkt(self.topology, self.kkt)

    @property
    def rho_rule(self) -> Any:
        """How rho_j is chosen (``rho_method`` resolved: :func:`~ampc_jax.admm.rho.select_rho`)."""
        return select_rho(self.rho_method, RHO_METHODS)

    @property
    def finish_rule(self) -> Any:
        """How a solve finishes (``finish`` resolved: :func:`~ampc_jax.admm.finish.select_finish`)."""
        return select_finish(self.finish, self.finish_every, self.finish_corrections)

    @property
    def dual_rule(self) -> Any:
        """The tested dual residual (``dual_residual`` resolved:
        :func:`~ampc_jax.admm.stopping.select_dual_residual`)."""
        return select_dual_residual(self.dual_residual, DUAL_RESIDUALS)

    def _own(self, j: int) -> np.ndarray:
        """Positions of objective j's own rows (``Topology.group_rows(j)`` order)
        among its R rows in the setup and the loop carry, in either row layout."""
        return np.flatnonzero(padded_layout(self.topology).rows[j] < self.topology.n_c)

    def objective_constraints(self, setup: LocalSetup, j: int) -> tuple[Any, Any]:
        """(A_in,j (n_c,j x n_u,j), bbar_j (N_p x n_c,j)): objective j's own rows in
        the order of ``Topology.group_rows(j)``, whatever the setup's row layout."""
        own, u = self._own(j), padded_layout(self.topology).u_sizes[j]
        return setup.Ain[j][own, :u], setup.b[j][:, own]

    # -- per-step setup -----------------------------------------------------------
    def setup_from(
        self, data: ProblemData, params: SolverParams | None, warm: ADMMState | None
    ) -> LocalSetup:
        """:meth:`setup` with the rho_j* ``warm`` carries (``rho_method="carried"``)."""
        carried = None if warm is None else getattr(warm, "rho_star", None)
        return self.setup(data, params, carried=carried)

    def setup(
        self, data: ProblemData, params: SolverParams | None = None, *, carried: Any = None
    ) -> LocalSetup:
        """Build H_j, E_j, rho_j and factorise (once per control step). ``carried``:
        (J,) the rho_j* a warm start carries (``rho_method="carried"``; 0: none)."""
        T = self.topology
        lay = padded_layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        kkt = self.kkt_solve
        dt = data.A.dtype
        p = as_params(self.params(dtype=dt) if params is None else params, J, dt)
        # the formed H_j: for the dense solve, the exact rho and rank-deficient rows
        need_H = kkt.forms_H or self.rho_rule.needs_H or not all(lay.full)
        c = padded_costs(T, data, with_H=need_H, condensed=kkt.condensed or need_H)
        # each objective's R rows (lay.rows; a padded index reads a zero row)
        Aix = jnp.pad(data.Ain, ((0, 1), (0, 1)))  # padded row / column index -> 0
        Ain = Aix[lay.rows[:, :, None], lay.cols[:, None, :]]  # (J, R, U)
        bx = jnp.pad(data.bin, ((0, 0), (0, 1)))
        b = jnp.moveaxis(bx[:, lay.rows], 1, 0)  # (J, N, R)
        AtA = jnp.einsum("jcu,jcv->juv", Ain, Ain)
        own = tuple(self._own(j) for j in range(J))
        hessian = kkt.hessian(c, T)  # H_j and H_j^-1 (+ eps): the power iteration, the gap
        iters = self.rho_iterations

        def estimate_of(args: tuple) -> Any:
            return eq_opt_ro_power(T, *args[:3], own, args[3], iters)

        args = (c, Ain, AtA, hessian)
        rho_star = RhoEstimates(
            estimate=lambda: estimate_of(args),
            exact=lambda: eq_opt_ro_exact(T, c, Ain, AtA, own),
            carried=None if carried is None else jnp.asarray(carried, dt),
            estimate_of=estimate_of,
            args=args,
        )
        star = self.rho_rule.star(rho_star)  # eq.opt_ro's rho_j* (None: rho given)
        rho = p.rho if star is None else p.rho * star
        # K_j = H_j + rho_j I (x) A_in,j'A_in,j, all objectives in one batched
        # factorisation; an iteration then applies it (a few matrix-vector products)
        Kinv = kkt.factor(c, rho[:, None, None] * AtA, N)
        KE = kkt.apply(Kinv, c.E)
        den = rho @ jnp.asarray(lay.carried, dt)
        fd = None
        if self.finish != "none":
            P = jnp.asarray(lay.P, dt)
            tol = default_tol(dt)
            fd = finish_data(c.A, c.Bu, c.Qx, c.BH, c.E, P, data.Ain, data.bin, tol)
        return LocalSetup(
            Ain=Ain,
            b=b,
            rho=rho,
            Kinv=Kinv,
            KE=KE,
            inv_den=1.0 / jnp.where(den > 0, den, 1.0),
            lb=data.lb,
            ub=data.ub,
            relaxation=p.relaxation,
            tol_primal=p.tol_primal,
            tol_dual=p.tol_dual,
            tol_rel=p.tol_rel,
            E=c.E,
            hessian=hessian,
            b2=jnp.sum(b * b, axis=(1, 2)),
            rho_star=jnp.zeros_like(rho) if star is None else star,
            finish=fd,
        )

    # -- states ----------------------------------------------------------------------
    def cold_state(self, dtype: Any = None) -> ADMMState:
        """The cold start of alg:1 (zeros, residuals inf)."""
        return cold_state(self.topology, dtype)

    @staticmethod
    def shift(state: ADMMState, steps: int = 1) -> ADMMState:
        """The MPC warm start from a previous iterate (:func:`~ampc_jax.admm.state.shift_state`)."""
        return shift_state(state, steps)

    def init(self, setup: LocalSetup, warm: ADMMState | None = None) -> ADMMState:
        """Cold start (zeros, as alg:1) or a warm start state (see :meth:`shift`).

        A warm state's U, Z and gamma are kept; its iteration count and
        residuals are reset, so that a previous result's ``.state`` passed as
        it is (not shifted) still iterates on the new data instead of being
        taken as converged.
        """
        return warm_start(
            cold_state(self.topology, setup.rho.dtype),
            warm,
            "an ADMMState (a previous result's .state, shifted)",
            " (ADMMState is in the solver's padded layout; build one from "
            "per-objective arrays with LocalExplicit.state_of)",
        )

    def start_from_inputs(
        self, setup: LocalSetup, data: ProblemData, u: Any, like: ADMMState
    ) -> ADMMState:
        """``like`` with Z = max(0, bbar - A_in u) (the rows' slack at u) and the
        multipliers that make ``u`` a fixed point
        (:func:`~ampc_jax.admm.learned_start.kkt_multipliers`): a learned
        ``"step"`` start from its predicted inputs."""
        Z = jnp.maximum(data.bin - u @ data.Ain.T, 0.0)
        gamma = kkt_multipliers(self.topology, setup.hessian, setup.E, setup.Ain, u, Z, data.bin)
        return like._replace(Z=Z.astype(like.Z.dtype), gamma=gamma.astype(like.gamma.dtype))

    # -- per-objective views of the padded state ------------------------------------
    def local_inputs(self, state: ADMMState) -> tuple:
        """U_j, (N_p, n_u,j) per objective, columns in ``Topology.group_columns(j)`` order."""
        lay = padded_layout(self.topology)
        return tuple(state.U[..., j, :, :u] for j, u in enumerate(lay.u_sizes))

    def multipliers(self, state: ADMMState) -> tuple:
        """gamma_j, (N_p, n_c,j) per objective, rows in ``Topology.group_rows(j)`` order."""
        J = self.topology.n_objectives
        return tuple(state.gamma[..., j, :, :][..., self._own(j)] for j in range(J))

    def state_of(self, U: Any, Z: Any, gamma: Any, dtype: Any = None) -> ADMMState:
        """An :class:`ADMMState` from per-objective arrays (iteration 0, residuals inf).

        U : one (N_p, n_u,j) array per objective; Z : (N_p, n_c);
        gamma : one (N_p, n_c,j) array per objective (``Topology.group_rows(j)`` order).
        """
        T = self.topology
        lay = padded_layout(T)
        J, N = T.n_objectives, T.horizon
        dt = jnp.result_type(float) if dtype is None else dtype
        cold = cold_state(T, dt)
        if len(U) != J or len(gamma) != J:
            raise ValueError(
                f"U, gamma: expected one array per objective ({J}), got {len(U)} and {len(gamma)}"
            )
        Up, gp = cold.U, cold.gamma
        for j in range(J):
            uj = jnp.asarray(U[j], dt)
            gj = jnp.asarray(gamma[j], dt)
            if uj.shape != (N, lay.u_sizes[j]):
                raise ValueError(
                    f"U[{j}]: expected shape {(N, lay.u_sizes[j])} (objective "
                    f"{T.objective_names[j]!r}), got {uj.shape}"
                )
            if gj.shape != (N, lay.c_sizes[j]):
                raise ValueError(
                    f"gamma[{j}]: expected shape {(N, lay.c_sizes[j])} (objective "
                    f"{T.objective_names[j]!r}), got {gj.shape}"
                )
            Up = Up.at[j, :, : lay.u_sizes[j]].set(uj)
            gp = gp.at[j].set(gp[j].at[:, self._own(j)].set(gj))
        Zp = jnp.asarray(Z, dt)
        if Zp.shape != (N, T.n_c):
            raise ValueError(f"Z: expected shape {(N, T.n_c)}, got {Zp.shape}")
        return cold._replace(U=Up, Z=Zp, gamma=gp)

    # -- one iteration --------------------------------------------------------------
    def step(self, setup: LocalSetup, st: ADMMState) -> ADMMState:
        """One ADMM iteration: local, global and dual updates (alg:1 steps 5-9)."""
        T = self.topology
        lay = padded_layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        rho = setup.rho[:, None, None]
        if lay.compact:
            # each objective's own rows, gathered (padded rows read a zero slack)
            def rows_of(Z: Any) -> Any:  # (N, n_c) -> (J, N, C)
                return jnp.moveaxis(jnp.pad(Z, ((0, 0), (0, 1)))[:, lay.rows], 0, 1)

            def mask(x: Any) -> Any:  # padded rows stay zero by construction
                return x

            Z_old = rows_of(st.Z)
        else:
            # all rows in the problem's numbering; rows j does not carry meet zero
            # columns in Ain and are masked out of the global and dual steps
            M = jnp.asarray(lay.carried, setup.rho.dtype)[:, None, :]  # (J, 1, n_c)

            def mask(x: Any) -> Any:
                return M * x

            Z_old = st.Z[None]
        w = rho * (Z_old - setup.b) + st.gamma
        # products with the per-step rows A_in,j (few x U) as broadcast sums, which
        # XLA fuses with the elementwise work around them (a dot would be a call each)
        Ain = setup.Ain[:, None]  # (J, 1, rows, U)
        g = jnp.sum(w[..., None] * Ain, axis=2).reshape(J, N * U)  # Abar_j' w_j
        Uf = -(setup.KE + self.kkt_solve.apply(setup.Kinv, g))  # eq.F3_primal
        AU = jnp.sum(Uf.reshape(J, N, 1, U) * Ain, axis=3)  # Abar_j U_j
        # over-relaxation (Boyd et al. 2011, sec. 3.4.3): alpha AU + (1 - alpha)(b - Z),
        # written as b - Z + alpha (AU - (b - Z)), so that alpha = 1 is the paper's
        # iteration. Rule: no (1 - alpha) term, because that product of a parameter
        # alone is a thunk ready at the program's start, and more than 8 of those
        # move the step onto XLA:CPU's thread pool (bench/bench_thunk_graph.py:
        # the stability step's queue went from 8 to 9, and the step took 18 us longer)
        bz = setup.b - Z_old
        AUr = bz + setup.relaxation * (AU - bz)
        # eq.F3_dual, rho-weighted (paper-notes item 14): Z_c = max(0, sum_j rho_j v_jc / sum_j rho_j)
        rv = mask(rho * (setup.b - AUr) - st.gamma)  # rho_j v_j on the rows j carries
        if lay.compact:
            # sum over the objectives carrying each row: static gathers (a padded zero
            # column for objectives without the row)
            rvx = jnp.pad(rv, ((0, 0), (0, 0), (0, 1)))
            Z = jnp.maximum(sum(rvx[j][:, lay.inv[j]] for j in range(J)) * setup.inv_den, 0.0)
            Zs = rows_of(Z)
        else:
            Z = jnp.maximum(jnp.sum(rv, axis=0) * setup.inv_den, 0.0)
            Zs = Z
        r = mask(AU - setup.b + Zs)
        gamma = st.gamma + rho * mask(AUr - setup.b + Zs)  # eq.F3_multiplier
        dz = self.dual_rule.dual(rho, mask(Zs - Z_old))  # eq.Convergence's s_j
        primal = jnp.sum(r * r, axis=(1, 2))
        dual = jnp.sum(dz * dz, axis=(1, 2))
        return ADMMState(Uf.reshape(J, N, U), Z, gamma, st.iteration + 1, primal, dual, st.rho_star)

    # -- the exact finish -------------------------------------------------------------
    def finisher(self, setup: LocalSetup) -> Any:
        """The exact finish (``finish="active_set"``; None otherwise): ``finish(before,
        after, ran)`` tries the active set of ``after`` where it equals that of
        ``before`` (it did not change in the last iteration), ``after`` ran and has
        not converged; one decision per batch under vmap (:func:`~ampc_jax.admm.finish.attempt`)."""
        if setup.finish is None:
            return None

        def finish(before: ADMMState, after: ADMMState, ran: Any) -> ADMMState:
            active = after.Z <= 0
            stable = jnp.all(active == (before.Z <= 0))
            # a state without an inactive row (the cold start) has no set to try
            due = ran & stable & jnp.any(~active) & ~self.converged(setup, after)
            # only what the finish reads (the factors would be copied into the cond)
            light = setup._replace(Ain=None, b=None, Kinv=None, KE=None, E=None, hessian=None)
            return attempt(due, (light, after), self._finished, lambda a: a[1])

        return finish

    def _finished(self, args: tuple) -> ADMMState:
        """The finish of ``new``'s active set: its state where verified, else ``new``."""
        setup, new = args
        lay = padded_layout(self.topology)
        fd = setup.finish
        dt = new.Z.dtype
        nb = len(self.topology.box_rows)
        u, nu, active, ok = finish_solve(fd, new.Z <= 0, nb, self.finish_corrections)
        Uc = jnp.moveaxis(jnp.pad(u, ((0, 0), (0, 1)))[:, lay.cols], 1, 0)  # (J, N, U) copies
        slack = fd.b - u @ fd.Ain.T
        Z = jnp.where(active, 0.0, jnp.maximum(slack, 0.0))
        r = Z - slack  # A u - b + Z: the violation on violated rows, else 0 (up to round-off)
        primal = jnp.asarray(lay.carried, dt) @ jnp.sum(r * r, axis=0)
        fin = new._replace(U=Uc, Z=Z, primal=primal, dual=jnp.zeros_like(new.dual))
        keep = ok & self.converged(setup, fin)
        return jax.tree.map(lambda a, b: jnp.where(keep, a, b), fin, new)

    def converged(self, setup: LocalSetup, state: ADMMState) -> Any:
        """eq.Convergence for every objective (see ``dual_residual``), with the
        relative tolerance on scale_j^2 = ||Z_j||^2 + ||bbar_j||^2 (the slack and
        the rows' right-hand sides; :func:`~ampc_jax.admm.stopping.converged`)."""
        carried = jnp.asarray(padded_layout(self.topology).carried, state.Z.dtype)
        scale2 = carried @ jnp.sum(state.Z * state.Z, axis=0) + setup.b2
        return stop.converged(
            state.primal,
            state.dual,
            setup.tol_primal,
            setup.tol_dual,
            setup.tol_rel,
            scale2,
            self.dual_rule.scale(setup.rho, scale2),
        )

    # -- the map's argument, for Anderson acceleration ------------------------------
    def point(self, state: ADMMState) -> Any:
        """The ADMM map's argument (Z, gamma), flattened (U is an output only)."""
        return jnp.concatenate([state.Z.ravel(), state.gamma.ravel()])

    def at(self, x: Any, state: ADMMState) -> ADMMState:
        """``state`` with (Z, gamma) from the vector ``x`` (:meth:`point`'s inverse)."""
        nz = state.Z.size
        return state._replace(
            Z=x[:nz].reshape(state.Z.shape), gamma=x[nz:].reshape(state.gamma.shape)
        )

    def result(self, setup: LocalSetup, state: ADMMState) -> SolveResult:
        """Consensus inputs (average of the copies, projected on the bounds), status,
        and the duality gap (``stats.gap``) of the inputs against the dual bound
        of the multipliers: mu_j = Abar_j' gamma_j, lambda = sum_j gamma_j
        (>= 0 after a step: eq.F3_dual's projection; :func:`~ampc_jax.admm.stopping.duality_gap`)."""
        T = self.topology
        lay = padded_layout(T)
        dt = setup.rho.dtype
        P = jnp.asarray(lay.P, dt)
        # sum_j U_j P_j as one broadcast sum (fused; padded columns select nothing)
        total = jnp.sum(state.U[..., None] * P[:, None], axis=(0, 2))
        count = lay.P.sum(axis=(0, 1))
        u = jnp.clip(total / jnp.asarray(count, dt), setup.lb, setup.ub)
        conv = self.converged(setup, state)
        finite = jnp.all(jnp.isfinite(u)) & jnp.all(jnp.isfinite(state.primal))
        status = jnp.where(
            ~finite,
            Status.NUMERICAL_ERROR,
            jnp.where(conv, Status.SOLVED, Status.MAX_ITER_REACHED),
        ).astype(jnp.int32)
        u = jnp.where(finite, u, jnp.zeros_like(u))  # never a NaN out: status 2 says why
        # the rho_j* passed on (rho_method="carried"): none after a slow or failed solve
        fresh = conv & finite & (state.iteration <= self.rho_refresh)
        state = state._replace(rho_star=jnp.where(fresh, setup.rho_star, 0.0))
        J = lay.cols.shape[0]
        Ain = setup.Ain[:, None]  # (J, 1, R, U)
        mu = jnp.sum(state.gamma[..., None] * Ain, axis=2).reshape(J, -1)  # Abar_j' gamma_j
        uj = jnp.moveaxis(jnp.pad(u, ((0, 0), (0, 1)))[:, lay.cols], 1, 0)  # (J, N, U)
        Au = jnp.sum(uj[:, :, None, :] * Ain, axis=3)  # Abar_j u_j
        slack = jnp.sum(state.gamma * (setup.b - Au))  # lambda'(b - Abar u)
        gap = stop.duality_gap(setup.hessian, setup.E, uj.reshape(J, -1), mu, slack)
        return SolveResult(
            u=u,
            iterations=state.iteration,
            converged=conv & finite,
            status=status,
            primal_residual=state.primal,
            dual_residual=state.dual,
            rho=setup.rho,
            state=state,
            stats=SolveStats(gap=jnp.where(finite, gap, jnp.inf)),
        )
