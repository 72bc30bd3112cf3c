"""Formulation 3, Local Explicit (eq.integMPC_F3 to eq.F3_multiplier), in pure JAX.

The integrated MPC is split into one local problem per objective O_j over the
copies U_j of the inputs of its agent group S_j. The constraints become
equalities with a shared non-negative slack Z (eq.integMPC_F3)::

    Abar_j U_j - bbar_j + Z_j = 0,   Z >= 0,

and consensus ADMM iterates, per objective j and constraint row c:

* local update (eq.F3_primal), a closed-form solve with a matrix factorised
  once per control step (the setup stores K_j^-1 E_j and K_j^-1 Abar_j', so an
  iteration is a few small matrix-vector products)::

      U_j = -(H_j + rho_j Abar_j' Abar_j)^-1 [E_j + Abar_j' (rho_j (Z_j - bbar_j) + gamma_j)]

* global update, the max-projection (eq.F3_dual) in its exact form for
  per-objective rho_j (NOTES item 14: the rho-weighted average; the printed
  equal-weight average converges to the wrong point when the rho_j differ)::

      v_jc = (-Abar_j U_j - gamma_j / rho_j + bbar_j)_c
      Z_c  = max(0, sum_j rho_j v_jc / sum_j rho_j)       (j over objectives carrying c)

* dual update (eq.F3_multiplier)::

      gamma_j += rho_j (Abar_j U_j - bbar_j + Z_j)

* stopping rule (eq.Convergence, per objective, NOTES items 6 and 17)::

      ||r_j||^2 = ||Abar_j U_j - bbar_j + Z_j||^2 <= eps_r,
      ||s_j||^2 = ||rho_j (Z_j^q - Z_j^(q-1))||^2 <= eps_s     (``dual_residual="paper"``)
      ||Z_j^q - Z_j^(q-1)||^2 <= eps_s                          (default, ``"slack"``)

Objective j's local cost carries its outputs' tracking cost and the input
weights of its agents shared out as R_(i) / m_(i) (eq.F1_obj with NOTES item 8).
Objective j carries the constraint rows whose agents all lie in S_j
(:meth:`Topology.group_rows`); a shared agent's box rows are shared by all its
objectives, which is what makes their copies agree (NOTES item 10).

The default rho_j is eq.opt_ro (:func:`optimal_rho`).

Everything here handles one problem; batch with ``jax.vmap`` over
:class:`~ampc_jax.topology.ProblemData` (see :mod:`ampc_jax.batch`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .prediction import prediction_matrices, quadratic_cost
from .results import SolveResult
from .topology import ProblemData, Topology

__all__ = [
    "ADMMState",
    "LocalExplicit",
    "LocalSetup",
    "local_costs",
    "optimal_rho",
    "shift_state",
]


class LocalSetup(NamedTuple):
    """Per-control-step data of Local Explicit, built and factorised once.

    Tuples run over objectives j; n_j = N_p n_u,j and m_j = N_p n_cj (rows of
    Abar_j). The iteration works on the objectives stacked: n = sum n_j,
    m = sum m_j.

    H : tuple of (n_j, n_j) H_j.   E : tuple of (n_j,) E_j.
    Ain : tuple of (n_cj, n_uj) per-step rows A_in,j (Abar_j = I_{N_p} (x) A_in,j).
    bin : tuple of (N_p, n_cj) bbar_j, step by step.
    rho : (n_obj,) rho_j.
    KE : (n,) stacked K_j^-1 E_j, K_j = H_j + rho_j Abar_j' Abar_j (factorised once).
    KA : (n, m) block-diagonal K_j^-1 Abar_j'.
    Abar : (m, n) block-diagonal Abar_j.
    b : (m,) stacked bbar_j.   rho_rows : (m,) rho_j of each stacked row.
    inv_den : (N_p n_c,) 1 / sum of rho_j over the objectives carrying each slack.
    lb, ub : (N_p, n_u) bounds, to project the consensus output.
    """

    H: tuple
    E: tuple
    Ain: tuple
    bin: tuple
    rho: Any
    KE: Any
    KA: Any
    Abar: Any
    b: Any
    rho_rows: Any
    inv_den: Any
    lb: Any
    ub: Any


class _Layout(NamedTuple):
    """Static index maps between Z (N_p n_c,) and the stacked rows (m,)."""

    gather: np.ndarray  # (m,) index into Z.ravel() of each stacked row
    scatter: np.ndarray  # (N_p n_c, max m_(c)) positions in the padded (m+1,) row vector
    segment: np.ndarray  # (n_obj, m) 0/1: which objective a stacked row belongs to
    u_sizes: tuple  # n_j
    r_sizes: tuple  # m_j


@functools.lru_cache(maxsize=64)
def _layout(topology: Topology) -> _Layout:
    T = topology
    N, nc = T.horizon, T.n_c
    gather, owner = [], []
    for j in range(T.n_objectives):
        rows = T.group_rows(j)
        for k in range(N):
            for c in rows:
                gather.append(k * nc + c)
                owner.append(j)
    gather = np.asarray(gather, np.int32)
    m = gather.size
    lists: list[list[int]] = [[] for _ in range(N * nc)]
    for pos, e in enumerate(gather):
        lists[e].append(pos)
    width = max(1, max(len(x) for x in lists))
    scatter = np.full((N * nc, width), m, np.int32)  # index m = the appended zero
    for e, x in enumerate(lists):
        scatter[e, : len(x)] = x
    segment = np.zeros((T.n_objectives, m))
    segment[np.asarray(owner), np.arange(m)] = 1.0
    u_sizes = tuple(N * len(T.group_columns(j)) for j in range(T.n_objectives))
    r_sizes = tuple(N * len(T.group_rows(j)) for j in range(T.n_objectives))
    return _Layout(gather, scatter, segment, u_sizes, r_sizes)


class _Flat(NamedTuple):
    """The iterate stacked over objectives (the loop carry)."""

    Z: Any  # (N_p n_c,)
    gamma: Any  # (m,)
    U: Any  # (n,)
    iteration: Any
    primal: Any
    dual: Any


def _split(x: Any, sizes: tuple, horizon: int) -> tuple:
    out, o = [], 0
    for n in sizes:
        out.append(x[o : o + n].reshape(horizon, -1))
        o += n
    return tuple(out)


class ADMMState(NamedTuple):
    """Iterate of Local Explicit.

    U : tuple over objectives of (N_p, n_uj) local inputs U_j.
    Z : (N_p, n_c) global slack.
    gamma : tuple over objectives of (N_p, n_cj) multipliers gamma_j.
    iteration : () int32.
    primal, dual : (n_obj,) ||r_j||^2 and ||s_j||^2 of the last iteration.
    """

    U: tuple
    Z: Any
    gamma: tuple
    iteration: Any
    primal: Any
    dual: Any


def local_costs(topology: Topology, data: ProblemData) -> tuple[tuple, tuple]:
    """(H_j, E_j) for every objective (eq.F3_primal_1, NOTES items 8, 18, 19)."""
    T = topology
    mult = T.multiplicity
    H, E = [], []
    for j in range(T.n_objectives):
        cols = np.asarray(T.group_columns(j))
        scale = np.concatenate([np.full(T.agent_sizes[i], 1.0 / mult[i]) for i in T.groups[j]])
        R_j = data.R[np.ix_(cols, cols)] * jnp.asarray(scale, data.R.dtype)[:, None]
        pred = prediction_matrices(data.A, data.B[:, cols], data.C[j], T.horizon)
        Hj, Ej = quadratic_cost(pred, data.Q[j], R_j, data.x0, data.w, data.ref[j])
        H.append(Hj)
        E.append(Ej)
    return tuple(H), tuple(E)


def optimal_rho(H: Any, Ain: Any, horizon: int, rank: int | None = None) -> Any:
    """eq.opt_ro: rho* = 1 / sqrt(lambda_1 lambda_n) of M = Abar H^-1 Abar'.

    lambda_1 and lambda_n are the smallest non-zero and the largest eigenvalue
    of M. The non-zero eigenvalues of M are those of H^-1 Abar'Abar (same
    non-zero spectrum of XY and YX).

    * Full column rank A_in,j (every bounded input; ``rank is None``): all of
      H^-1 Abar'Abar's eigenvalues are non-zero. With Abar'Abar = L L' (block
      diagonal, L = I (x) chol(A_in,j' A_in,j)) they are 1/mu for mu the
      eigenvalues of L^-1 H L^-T, so rho* = sqrt(mu_min mu_max): no
      threshold, so float32 does not pick rounding noise (jax-facts). For
      two-sided boxes this is sqrt(lambda_min(H) lambda_max(H)) / 2 (NOTES 16).
    * Otherwise ``rank`` = rank(A_in,j) per step gives the number of non-zero
      eigenvalues, N_p * rank, of L_H^-1 Abar'Abar L_H^-T (L_H = chol(H)):
      the known rank replaces a numerical threshold.
    """
    n = H.shape[0]
    AtA = Ain.T @ Ain
    if rank is None:
        G = _scaled_hessian(H, Ain, horizon)
        mu = jnp.linalg.eigvalsh(0.5 * (G + G.T))
        mu_min = jnp.maximum(mu[0], jnp.finfo(H.dtype).eps * mu[-1])
        return jnp.sqrt(mu_min * mu[-1])
    LH = jnp.linalg.cholesky(H)
    M = jnp.kron(jnp.eye(horizon, dtype=H.dtype), AtA)
    X = jsl.solve_triangular(LH, M, lower=True)
    G = jsl.solve_triangular(LH, X.T, lower=True)
    lam = jnp.linalg.eigvalsh(0.5 * (G + G.T))
    nonzero = horizon * rank
    return 1.0 / jnp.sqrt(lam[n - nonzero] * lam[-1])


def _scaled_hessian(H: Any, Ain: Any, horizon: int) -> Any:
    """L^-1 H L^-T with L = I (x) chol(A_in' A_in) (see :func:`optimal_rho`)."""
    n = H.shape[0]
    nu = n // horizon
    La = jnp.linalg.cholesky(Ain.T @ Ain)
    Li = jsl.solve_triangular(La, jnp.eye(nu, dtype=H.dtype), lower=True)
    Hb = H.reshape(horizon, nu, horizon, nu)
    return jnp.einsum("ab,kbld,cd->kalc", Li, Hb, Li).reshape(n, n)


def _pad_identity(K: Any, n: int) -> Any:
    p = n - K.shape[0]
    if p == 0:
        return K
    return jnp.pad(K, ((0, p), (0, p))) + jnp.diag(
        jnp.concatenate([jnp.zeros(K.shape[0], K.dtype), jnp.ones(p, K.dtype)])
    )


def _pad_mean(G: Any, n: int) -> Any:
    p = n - G.shape[0]
    if p == 0:
        return G
    mean = jnp.trace(G) / G.shape[0]
    return jnp.pad(G, ((0, p), (0, p))) + jnp.diag(
        jnp.concatenate([jnp.zeros(G.shape[0], G.dtype), jnp.full((p,), mean, G.dtype)])
    )


def shift_state(state: ADMMState) -> ADMMState:
    """Warm start: the previous step's iterate shifted one step along the horizon.

    Step k+1 becomes step k; the last step is repeated.
    """

    def sh(x: Any) -> Any:
        return jnp.concatenate([x[1:], x[-1:]], axis=0)

    inf = jnp.full_like(state.primal, jnp.inf)
    return ADMMState(
        U=tuple(sh(u) for u in state.U),
        Z=sh(state.Z),
        gamma=tuple(sh(g) for g in state.gamma),
        iteration=jnp.zeros((), jnp.int32),
        primal=inf,
        dual=inf,
    )


@dataclass(frozen=True)
class LocalExplicit:
    """Local Explicit solver for one :class:`Topology` (static, hashable).

    Parameters
    ----------
    topology : the MACS structure.
    max_iter : iteration cap of the ``while_loop`` runner.
    tol_primal, tol_dual : eps_r and eps_s of eq.Convergence (squared norms).
    dual_residual : ``"slack"`` (default) tests ||Z_j^q - Z_j^(q-1)||^2 <= eps_s,
        the slack's change in the constraints' own units; ``"paper"`` tests
        ||s_j||^2 = ||rho_j (Z_j^q - Z_j^(q-1))||^2 <= eps_s as printed. The
        printed form scales with rho_j, and eq.opt_ro gives rho_j ~ 1e-6 when
        the weights are per Nm^2 (vehicle examples): a fixed eps_s is then met
        while Z still moves by newtons, and the solver stops far from the
        optimum. ``SolveResult.dual_residual`` reports the tested quantity.

    Use :meth:`solve` for deployment (early stop) and :meth:`solve_fixed` for
    differentiation (fixed iteration count under ``lax.scan``). Both are pure
    and jittable; ``jax.jit(solver.solve)`` compiles one control step.
    """

    topology: Topology
    max_iter: int = 500
    tol_primal: float = 1e-6
    tol_dual: float = 1e-6
    dual_residual: str = "slack"

    def __post_init__(self) -> None:
        if self.dual_residual not in ("slack", "paper"):
            raise ValueError(
                f"dual_residual: expected 'slack' or 'paper', got {self.dual_residual!r}"
            )
        self.topology.check_local_explicit()

    def _rows(self, j: int) -> np.ndarray:
        return np.asarray(self.topology.group_rows(j), dtype=np.int32)

    # -- per-step setup -----------------------------------------------------------
    def setup(self, data: ProblemData, rho: Any = None) -> LocalSetup:
        """Build H_j, E_j, rho_j and factorise (once per control step).

        ``rho``: ``None`` for eq.opt_ro per objective, a scalar, or (n_obj,).
        """
        T = self.topology
        H, E = local_costs(T, data)
        Ains, bins = [], []
        for j in range(T.n_objectives):
            rows = self._rows(j)
            cols = np.asarray(T.group_columns(j))
            Ains.append(data.Ain[np.ix_(rows, cols)])
            bins.append(data.bin[:, rows])
        if rho is None:
            rho_arr = self._optimal_rhos(H, Ains)
        else:
            rho_arr = jnp.broadcast_to(jnp.asarray(rho, H[0].dtype), (T.n_objectives,))
        # Factorise every K_j = H_j + rho_j Abar_j'Abar_j in one batched call
        # (padded to a common size with an identity block and zero right-hand
        # sides, which leaves each K_j^-1 [E_j, Abar_j'] unchanged).
        Abars, Ks, rhss = [], [], []
        for j in range(T.n_objectives):
            Abar = jnp.kron(jnp.eye(T.horizon, dtype=H[j].dtype), Ains[j])
            Abars.append(Abar)
            Ks.append(H[j] + rho_arr[j] * Abar.T @ Abar)
            rhss.append(jnp.concatenate([E[j][:, None], Abar.T], axis=1))
        n_max = max(k.shape[0] for k in Ks)
        c_max = max(r.shape[1] for r in rhss)
        K_b = jnp.stack([_pad_identity(k, n_max) for k in Ks])
        rhs_b = jnp.stack(
            [jnp.pad(r, ((0, n_max - r.shape[0]), (0, c_max - r.shape[1]))) for r in rhss]
        )
        sol_b = jsl.cho_solve((jnp.linalg.cholesky(K_b), True), rhs_b)
        KE, KA = [], []
        for j in range(T.n_objectives):
            n_j, c_j = rhss[j].shape
            KE.append(sol_b[j, :n_j, 0])
            KA.append(sol_b[j, :n_j, 1:c_j])
        lay = _layout(T)
        seg = jnp.asarray(lay.segment, rho_arr.dtype)
        rho_rows = rho_arr @ seg
        den = jnp.zeros((T.horizon * T.n_c,), rho_arr.dtype).at[lay.gather].add(rho_rows)
        return LocalSetup(
            H=tuple(H),
            E=tuple(E),
            Ain=tuple(Ains),
            bin=tuple(bins),
            rho=rho_arr,
            KE=jnp.concatenate(KE),
            KA=jsl.block_diag(*KA),
            Abar=jsl.block_diag(*Abars),
            b=jnp.concatenate([x.reshape(-1) for x in bins]),
            rho_rows=rho_rows,
            inv_den=1.0 / den,
            lb=data.lb,
            ub=data.ub,
        )

    def _optimal_rhos(self, H: tuple, Ains: tuple) -> Any:
        """eq.opt_ro for every objective, eigenvalues in one batched call.

        For an objective with only box rows (the common case) A_in,j'A_in,j is
        diagonal, so L^-1 H L^-T of :func:`optimal_rho` is a diagonal scaling
        of H_j. The matrices are padded to a common size with their mean
        eigenvalue (trace / n), which lies between the extreme eigenvalues and
        so leaves mu_min and mu_max unchanged.
        """
        T = self.topology
        nb = len(T.box_rows)
        Gs, general = [], {}
        for j in range(T.n_objectives):
            full = T.group_rank[j] == len(T.group_columns(j))
            if not full:
                general[j] = optimal_rho(H[j], Ains[j], T.horizon, T.group_rank[j])
                Gs.append(None)
            elif all(c < nb for c in T.group_rows(j)):
                dh = jnp.tile(1.0 / jnp.sqrt(jnp.sum(Ains[j] ** 2, axis=0)), T.horizon)
                Gs.append(H[j] * dh[:, None] * dh[None, :])
            else:
                Gs.append(_scaled_hessian(H[j], Ains[j], T.horizon))
        sizes = [g.shape[0] for g in Gs if g is not None]
        if sizes:
            n_max = max(sizes)
            G_b = jnp.stack(
                [_pad_mean(0.5 * (g + g.T), n_max) for g in Gs if g is not None]
            )
            mu = jnp.linalg.eigvalsh(G_b)
            eps = jnp.finfo(mu.dtype).eps
            rho_sym = jnp.sqrt(jnp.maximum(mu[:, 0], eps * mu[:, -1]) * mu[:, -1])
        out, k = [], 0
        for j in range(T.n_objectives):
            if Gs[j] is None:
                out.append(general[j])
            else:
                out.append(rho_sym[k])
                k += 1
        return jnp.stack(out)

    def init(self, setup: LocalSetup, warm: ADMMState | None = None) -> ADMMState:
        """Cold start (zeros, as alg:1) or a warm start state (see :func:`shift_state`)."""
        if warm is not None:
            return warm
        T = self.topology
        dt = setup.rho.dtype
        inf = jnp.full((T.n_objectives,), jnp.inf, dt)
        return ADMMState(
            U=tuple(jnp.zeros((T.horizon, a.shape[1]), dt) for a in setup.Ain),
            Z=jnp.zeros((T.horizon, T.n_c), dt),
            gamma=tuple(jnp.zeros((T.horizon, a.shape[0]), dt) for a in setup.Ain),
            iteration=jnp.zeros((), jnp.int32),
            primal=inf,
            dual=inf,
        )

    # -- one iteration --------------------------------------------------------------
    def _flat(self, state: ADMMState) -> _Flat:
        return _Flat(
            Z=state.Z.reshape(-1),
            gamma=jnp.concatenate([g.reshape(-1) for g in state.gamma]),
            U=jnp.concatenate([u.reshape(-1) for u in state.U]),
            iteration=state.iteration,
            primal=state.primal,
            dual=state.dual,
        )

    def _unflat(self, flat: _Flat) -> ADMMState:
        T = self.topology
        lay = _layout(T)
        return ADMMState(
            U=_split(flat.U, lay.u_sizes, T.horizon),
            Z=flat.Z.reshape(T.horizon, T.n_c),
            gamma=_split(flat.gamma, lay.r_sizes, T.horizon),
            iteration=flat.iteration,
            primal=flat.primal,
            dual=flat.dual,
        )

    def _step_flat(self, setup: LocalSetup, st: _Flat) -> _Flat:
        lay = _layout(self.topology)
        rho = setup.rho_rows
        Zs_old = st.Z[lay.gather]
        w = rho * (Zs_old - setup.b) + st.gamma
        U = -(setup.KE + setup.KA @ w)  # eq.F3_primal, all objectives at once
        AU = setup.Abar @ U
        v = -AU - st.gamma / rho + setup.b
        padded = jnp.concatenate([rho * v, jnp.zeros((1,), v.dtype)])
        num = padded[lay.scatter].sum(axis=1)  # sum_j rho_j v_jc per slack
        Z = jnp.maximum(num * setup.inv_den, 0.0)  # eq.F3_dual, rho-weighted (NOTES 14)
        Zs = Z[lay.gather]
        r = AU - setup.b + Zs
        dz = Zs - Zs_old
        gamma = st.gamma + rho * r  # eq.F3_multiplier
        if self.dual_residual == "paper":
            dz = rho * dz  # s_j = rho_j (Z_j - Z_j_prev), eq.Convergence
        norms = jnp.asarray(lay.segment, r.dtype) @ jnp.stack([r * r, dz * dz], axis=1)
        return _Flat(Z, gamma, U, st.iteration + 1, norms[:, 0], norms[:, 1])

    def step(self, setup: LocalSetup, state: ADMMState) -> ADMMState:
        """One ADMM iteration: local, global and dual updates (alg:1 steps 5-9)."""
        return self._unflat(self._step_flat(setup, self._flat(state)))

    def converged(self, state: ADMMState) -> Any:
        """eq.Convergence for every objective (see ``dual_residual``)."""
        return jnp.all((state.primal <= self.tol_primal) & (state.dual <= self.tol_dual))

    # -- runners ---------------------------------------------------------------------
    def run(self, setup: LocalSetup, state: ADMMState) -> ADMMState:
        """``lax.while_loop`` until eq.Convergence or ``max_iter`` (deployment)."""

        def cond(st: _Flat) -> Any:
            finite = jnp.all(jnp.isfinite(st.primal) | (st.iteration == 0))
            return (st.iteration < self.max_iter) & ~self.converged(st) & finite

        flat = jax.lax.while_loop(cond, lambda st: self._step_flat(setup, st), self._flat(state))
        return self._unflat(flat)

    def run_fixed(self, setup: LocalSetup, state: ADMMState, iterations: int) -> ADMMState:
        """Exactly ``iterations`` iterations under ``lax.scan`` (differentiable)."""

        def body(st: _Flat, _: Any) -> tuple[_Flat, None]:
            return self._step_flat(setup, st), None

        flat, _ = jax.lax.scan(body, self._flat(state), None, length=iterations)
        return self._unflat(flat)

    def result(self, setup: LocalSetup, state: ADMMState) -> SolveResult:
        """Consensus inputs (average of the copies, projected on the bounds) and status."""
        T = self.topology
        total = jnp.zeros((T.horizon, T.n_u), setup.rho.dtype)
        count = np.zeros(T.n_u)
        for j in range(T.n_objectives):
            cols = np.asarray(T.group_columns(j))
            total = total.at[:, cols].add(state.U[j])
            count[cols] += 1
        u = jnp.clip(total / jnp.asarray(count, total.dtype), setup.lb, setup.ub)
        conv = self.converged(state)
        finite = jnp.all(jnp.isfinite(u)) & jnp.all(jnp.isfinite(state.primal))
        status = jnp.where(~finite, 2, jnp.where(conv, 0, 1)).astype(jnp.int32)
        return SolveResult(
            u=u,
            iterations=state.iteration,
            converged=conv & finite,
            status=status,
            primal_residual=state.primal,
            dual_residual=state.dual,
            rho=setup.rho,
            state=state,
        )

    def solve(
        self, data: ProblemData, rho: Any = None, warm: ADMMState | None = None
    ) -> SolveResult:
        """Full control step: setup, factorise, rho, iterate to tolerance."""
        setup = self.setup(data, rho)
        return self.result(setup, self.run(setup, self.init(setup, warm)))

    def solve_fixed(
        self,
        data: ProblemData,
        iterations: int,
        rho: Any = None,
        warm: ADMMState | None = None,
    ) -> SolveResult:
        """Full control step with a fixed iteration count (for ``jax.grad``)."""
        setup = self.setup(data, rho)
        return self.result(setup, self.run_fixed(setup, self.init(setup, warm), iterations))
