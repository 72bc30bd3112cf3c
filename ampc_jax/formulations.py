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

The default rho_j is eq.opt_ro (:func:`optimal_rho`), its extreme eigenvalues
estimated by power iteration (:func:`_power_rho`; ``rho_method="eigh"`` for the
exact form), optionally scaled (``rho_scale``).

Implementation: the objectives are stacked on a leading axis and padded to
common sizes, so every per-objective operation is one batched call (one
factorisation, one matrix-vector product per iteration for all objectives).
When every objective has at most half as many outputs as inputs per step
(the cruise example: one output, three or four inputs), K_j^-1 comes from the
Woodbury identity through the N_p n_y,j outputs (:func:`_lowrank_parts`) instead of an
N_p n_u,j Cholesky factorisation.

Everything here handles one problem; batch with ``jax.vmap`` over
:class:`~ampc_jax.topology.ProblemData`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .prediction import _block_toeplitz, matrix_powers
from .results import SolveResult
from .topology import ProblemData, Topology

__all__ = [
    "ADMMState",
    "LocalExplicit",
    "LocalSetup",
    "cold_state",
    "local_costs",
    "optimal_rho",
    "shift_horizon",
    "shift_state",
    "singular_hessians",
]


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
        (many more rows than any objective carries, ``_COMPACT_ROWS``), (J, C, U)
        with each objective's own rows gathered and padded with zero rows.
    b : (J, N_p, n_c) bbar_j, step by step (zero on rows not carried); (J, N_p, C)
        in the compact layout.
    rho : (J,) rho_j.
    Kinv : (J, n, n) K_j^-1, K_j = H_j + rho_j Abar_j' Abar_j (factorised once);
        or, when the solver's ``inverse`` is factored, the Woodbury parts
        (B^-1 (J, U, U), W (J, r, n), P W (J, r, n)) with K_j^-1 = I (x) B^-1 - W'PW
        (:func:`_lowrank_parts`), applied without forming it.
    KE : (J, n) K_j^-1 E_j.
    inv_den : (n_c,) 1 / sum of rho_j over the objectives carrying each slack row.
    lb, ub : (N_p, n_u) bounds, to project the consensus output.
    """

    Ain: Any
    b: Any
    rho: Any
    Kinv: Any
    KE: Any
    inv_den: Any
    lb: Any
    ub: Any


class _Layout(NamedTuple):
    """Static index maps of the padded, objective-stacked layout."""

    cols: np.ndarray  # (J, U) input index of each padded column; n_u for padding
    umask: np.ndarray  # (J, U) 1 for a real input
    carried: np.ndarray  # (J, n_c) 1 where objective j carries constraint row c
    compact: bool  # rows gathered per objective (see _COMPACT_ROWS) instead of all n_c
    rows: np.ndarray  # (J, R) constraint row behind each of objective j's R rows; n_c (a
    # zero row) for padding or a row j does not carry. Compact: R = C, j's own rows
    # first; otherwise R = n_c in the problem's numbering.
    inv: np.ndarray  # (J, n_c) compact: padded row of objective j carrying row c; C if none
    P: np.ndarray  # (J, U, n_u) 0/1 selection: padded column -> input
    scale: np.ndarray  # (J, U) 1 / m_(i) of each column's agent (0 for padding)
    u_sizes: tuple  # n_u,j
    c_sizes: tuple  # n_c,j
    y_sizes: tuple  # n_y,j
    full: tuple  # A_in,j has full column rank (eq.opt_ro without a threshold)


@functools.lru_cache(maxsize=64)
def _layout(topology: Topology) -> _Layout:
    T = topology
    J = T.n_objectives
    u_sizes = tuple(len(T.group_columns(j)) for j in range(J))
    c_sizes = tuple(len(T.group_rows(j)) for j in range(J))
    U = max(u_sizes)
    cols = np.full((J, U), T.n_u, np.int32)
    carried = np.zeros((J, T.n_c))
    C = max(1, max(c_sizes))
    rows = np.full((J, C), T.n_c, np.int32)
    inv = np.full((J, T.n_c), C, np.int32)
    P = np.zeros((J, U, T.n_u))
    scale = np.zeros((J, U))
    mult = T.multiplicity
    for j in range(J):
        cj = T.group_columns(j)
        cols[j, : len(cj)] = cj
        for a, k in enumerate(cj):
            P[j, a, k] = 1.0
            scale[j, a] = 1.0 / mult[T.agent_of_input(k)]
        rj = list(T.group_rows(j))
        carried[j, rj] = 1.0
        rows[j, : len(rj)] = rj
        inv[j, rj] = np.arange(len(rj))
    compact = T.n_c > _COMPACT_ROWS * C
    if not compact:
        rows = np.where(carried > 0, np.arange(T.n_c), T.n_c).astype(np.int32)
    umask = (cols < T.n_u).astype(np.float64)
    full = tuple(T.group_rank[j] == u_sizes[j] for j in range(J))
    return _Layout(
        cols,
        umask,
        carried,
        compact,
        rows,
        inv,
        P,
        scale,
        u_sizes,
        c_sizes,
        tuple(T.output_sizes),
        full,
    )


# Row layout of the iteration. When some objective carries every constraint row
# (C = n_c; the cruise benchmark, the integrated problem), every objective works
# on all n_c rows in the problem's numbering, those it does not carry masked:
# the global step then needs no gather (batched at N_p = 10, 0.90 against
# 1.13 us per iteration gathered). Otherwise (n_c > _COMPACT_ROWS * C) each
# objective's own rows are gathered into C padded rows: with all rows, generated
# chains of J objectives (N_p = 10, one problem, K^-1 formed or factored) cost
# 1.1x to 1.2x per iteration at J = 2, 1.8x to 2.1x at J = 8 and 3.3x to 3.8x
# at J = 16, and the closed-loop cruise step (n_c = 8, C = 6) about 1 us more.
_COMPACT_ROWS = 1.0


class ADMMState(NamedTuple):
    """Iterate of Local Explicit, in the solver's padded, objective-stacked layout.

    The loop carries this state as it is, so a warm start goes in and the
    final iterate comes out without any regrouping (a control step costs no
    more array arguments with more objectives). J objectives, each padded to
    U = max_j n_u,j input columns and R constraint rows:

    U : (J, N_p, U) local inputs U_j; column a of objective j is input
        ``Topology.group_columns(j)[a]``, padded columns are ignored.
    Z : (N_p, n_c) global slack.
    gamma : (J, N_p, R) multipliers gamma_j, zero on the rows objective j does
        not carry and on padding. R is n_c (rows in the problem's numbering)
        or, when no objective carries every row, max_j n_c,j (objective j's own
        rows first, in ``Topology.group_rows(j)`` order).
    iteration : () int32.
    primal, dual : (J,) ||r_j||^2 and ||s_j||^2 of the last iteration.

    Per-objective views: :meth:`LocalExplicit.local_inputs`,
    :meth:`LocalExplicit.multipliers`; from per-objective arrays:
    :meth:`LocalExplicit.state_of`; cold start: :func:`cold_state`.
    """

    U: Any
    Z: Any
    gamma: Any
    iteration: Any
    primal: Any
    dual: Any


def _eye_like(n: int, dtype: Any, batch: int) -> Any:
    return jnp.broadcast_to(jnp.eye(n, dtype=dtype), (batch, n, n))


def _lapack_spd_inverse(M: Any) -> Any:
    """Inverse of a batch (..., n, n) of SPD matrices through LAPACK.

    M = L L' (Cholesky), M^-1 = L^-T L^-1: one triangular solve and one product,
    half the triangular work of ``cho_solve`` with an identity right-hand side.
    """
    L = jnp.linalg.cholesky(M)
    eye = jnp.broadcast_to(jnp.eye(M.shape[-1], dtype=M.dtype), M.shape)
    Li = jax.lax.linalg.triangular_solve(L, eye, left_side=True, lower=True)
    return jnp.einsum("...ka,...kb->...ab", Li, Li)


def _sweep_inverse(M: Any) -> Any:
    """Inverse of a batch (..., n, n) of SPD matrices by n symmetric sweeps, pure JAX.

    Sweeping pivot k (Gauss-Jordan elimination without pivoting, stable for
    SPD matrices: the pivots are the positive Schur complements) maps A to
    B with B_kk = -1/d, B_ik = B_ki = A_ik/d and B_ij = A_ij - A_ik A_kj/d,
    d = A_kk; after all n pivots B = -M^-1. Each sweep is one elementwise
    pass, vectorised over the batch; no LAPACK call (see :func:`_spd_inverse`).
    """
    n = M.shape[-1]
    eye = jnp.eye(n, dtype=M.dtype)

    def sweep(k: Any, A: Any) -> Any:
        col = jax.lax.dynamic_index_in_dim(A, k, axis=-1, keepdims=False)  # A[..., :, k]
        e = jax.lax.dynamic_index_in_dim(eye, k, axis=0, keepdims=False)
        d = jnp.sum(col * e, axis=-1, keepdims=True)
        v = col / d
        new = v - e * (1.0 + 1.0 / d)  # column k of B
        B = A - d[..., None] * v[..., :, None] * v[..., None, :]
        B = jnp.where(e[:, None] > 0.5, new[..., None, :], B)  # row k
        return jnp.where(e[None, :] > 0.5, new[..., :, None], B)  # column k

    return -jax.lax.fori_loop(0, n, sweep, M)


# Up to this size the sweeps are used for one (unbatched) problem too: faster
# than LAPACK for small blocks. Larger sizes were measured twice: before the
# single-kernel loop flag, 12 made the N_p = 10 cruise step slower (189 to 201
# us against 151 to 153 us). With the flag (2026-11-30, one core) 12 made most
# steps 3 to 5 us faster, but with Anderson acceleration at N_p = 10 the step
# went onto XLA:CPU's thread pool (jax.profiler: "ThunkExecutor::Execute (wait
# for completion)"; the sweeps of the Woodbury path's 10 x 10 matrices were
# parallel branches) and took 102 against 78 us. So: the Woodbury path's
# matrices up to 4 x 4 (``_SWEEP_MAX``); the dense path's H_j + delta I (for
# eq.opt_ro) and K_j, which follow one another, up to 12 x 12
# (``_SWEEP_MAX_DENSE``; the stability closed loop's 9 x 9 and 12 x 12: both
# solvers 4 to 5 us faster per step).
_SWEEP_MAX = 4
_SWEEP_MAX_DENSE = 12


def _make_spd_inverse(sweep_max: int) -> Any:
    """:func:`_spd_inverse` with sweeps up to ``sweep_max`` x ``sweep_max``."""

    @jax.custom_batching.custom_vmap
    def impl(M: Any) -> Any:
        if M.shape[-1] <= sweep_max:
            return _sweep_inverse(M)
        return _lapack_spd_inverse(M)

    @impl.def_vmap
    def batched(axis_size: int, in_batched: Any, M: Any) -> tuple[Any, bool]:
        # Batched (vmap over scenarios): always the sweeps. XLA:CPU's batched LAPACK
        # kernels fan their batch out into the intra-op thread pool they run on and
        # wait for it, which deadlocks once every pool thread runs such a kernel
        # (two CPU devices sharding a batch on two cores: ampc_jax.batch).
        (is_batched,) = in_batched
        if not is_batched:
            return impl(M), False
        return _sweep_inverse(M), True

    # A JVP rule (not a VJP one), so that forward mode (jvp, jacfwd, hessian)
    # works too; reverse mode transposes the rule, which is linear in dM.
    @jax.custom_jvp
    def inverse(M: Any) -> Any:
        return impl(M)

    @inverse.defjvp
    def inverse_jvp(primals: tuple, tangents: tuple) -> tuple[Any, Any]:
        (M,), (dM,) = primals, tangents
        X = inverse(M)  # not impl: so that the rule itself differentiates (hessian)
        return X, -(X @ dM @ X)

    return inverse


_spd_inverse = _make_spd_inverse(_SWEEP_MAX)
"""Inverse of a batch (..., n, n) of symmetric positive definite matrices.

Small matrices (n <= 4, ``_SWEEP_MAX``) and every vmapped batch use symmetric
sweeps in pure JAX (:func:`_sweep_inverse`); a single larger problem uses
LAPACK (:func:`_lapack_spd_inverse`). Derivative (forward and reverse mode)
d(M^-1) = -M^-1 dM M^-1."""

_spd_inverse_dense = _make_spd_inverse(_SWEEP_MAX_DENSE)
""":func:`_spd_inverse` for the dense path's H_j and K_j (sweeps up to ``_SWEEP_MAX_DENSE``)."""


def _small_cholesky(A: Any) -> Any:
    """Lower factor L, L L' = A, of a batch (..., m, m) of small positive
    semidefinite matrices (m static and small), unrolled in pure JAX.

    A zero pivot (a semidefinite A, e.g. a padded output with zero weight)
    gives a zero column instead of a division by zero.
    """
    m = A.shape[-1]
    cols = []
    for k in range(m):
        a = A[..., :, k]
        for c in cols:
            a = a - c * c[..., k : k + 1]
        piv = a[..., k : k + 1]
        pos = piv > 0
        # the inner where keeps sqrt's derivative finite at a zero pivot (a NaN
        # there would leak into gradients through the outer where)
        d = jnp.where(pos, jnp.sqrt(jnp.where(pos, piv, 1.0)), 0.0)
        safe = jnp.where(d > 0, d, 1.0)
        mask = jnp.asarray(np.arange(m) >= k, A.dtype)
        cols.append(jnp.where(d > 0, a / safe, 0.0) * mask)
    return jnp.stack(cols, axis=-1)


class _Costs(NamedTuple):
    """Objective-stacked, padded cost data (see :func:`_padded_costs`).

    Yu : (J, r, n) Y_u,j (r = N_p Y outputs, n = N_p U inputs, padded).
    Q2 : (J, r, r) 2 Qbar_j = 2 I (x) Q_j.   Qh : (J, r, r) a factor, Q2 = Qh Qh',
    I (x) chol(2 Q_j).   BH : (J, U, U) 2 R_j / m (+ identity on padding).
    H : (J, n, n) H_j = Y_u' 2Qbar Y_u + I (x) BH.   E : (J, n) E_j.
    """

    Yu: Any
    Q2: Any
    Qh: Any
    BH: Any
    H: Any
    E: Any


def _padded_costs(topology: Topology, data: ProblemData, with_H: bool = True) -> _Costs:
    """H_j, E_j of every objective in the padded layout, all objectives at once.

    Same formulas as :func:`~ampc_jax.prediction.quadratic_cost` (eq.F3_primal_1,
    NOTES items 8, 18, 19): H_j = 2 (Y_u,j' Qbar_j Y_u,j + I (x) R_(j) / m),
    E_j = 2 Y_u,j' Qbar_j (Y_x,j X^(0) + Y_w,j Wbar - ref_j). The matrix powers
    and the free response are shared by all objectives; padded inputs get an
    identity block in H, padded outputs zero weight. ``with_H=False`` skips
    forming H (n^2 r work) for the low-rank path, which never needs it.
    """
    T = topology
    lay = _layout(T)
    J, U = lay.cols.shape
    N = T.horizon
    dt = data.A.dtype
    Y = max(lay.y_sizes)
    Cp = jnp.stack([jnp.pad(c, ((0, Y - c.shape[0]), (0, 0))) for c in data.C])
    Qp = jnp.stack([jnp.pad(q, ((0, Y - q.shape[0]), (0, Y - q.shape[0]))) for q in data.Q])
    refp = jnp.stack([jnp.pad(r, ((0, 0), (0, Y - r.shape[1]))) for r in data.ref])
    Bx = jnp.concatenate([data.B, jnp.zeros((T.n_x, 1), dt)], axis=1)
    Bj = jnp.moveaxis(Bx[:, lay.cols], 1, 0)  # (J, n_x, U)
    Rx = jnp.pad(data.R, ((0, 1), (0, 1)))
    Rj = Rx[lay.cols[:, :, None], lay.cols[:, None, :]] * jnp.asarray(lay.scale, dt)[:, :, None]
    BH = 2.0 * Rj + jnp.asarray(np.eye(U)[None] * (1.0 - lay.umask)[:, :, None], dt)
    Pw = matrix_powers(data.A, N)  # A^0..A^N
    # free response x^(k+1) = A^(k+1) x0 + sum_{l<=k} A^(k-l) w_l
    xf = Pw[1:] @ data.x0 + (_block_toeplitz(Pw[:N], N) @ data.w.reshape(-1)).reshape(N, -1)
    free = (jnp.einsum("jyx,kx->jky", Cp, xf) - refp).reshape(J, N * Y)
    CPB = jnp.einsum("jyx,kxz,jzu->jkyu", Cp, Pw[:N], Bj)  # C_j A^k B_j
    Yu = jax.vmap(_block_toeplitz, in_axes=(0, None))(CPB, N)  # (J, N Y, N U)
    eyeN = jnp.eye(N, dtype=dt)
    Q2 = 2.0 * jnp.einsum("kl,jab->jkalb", eyeN, Qp).reshape(J, N * Y, N * Y)
    Qs = _small_cholesky(2.0 * Qp)  # 2 Q_j = Qs Qs', Q_j positive semidefinite (validated)
    Qh = jnp.einsum("kl,jab->jkalb", eyeN, Qs).reshape(J, N * Y, N * Y)
    QYu = Q2 @ Yu
    H = None
    if with_H:
        H = jnp.swapaxes(Yu, 1, 2) @ QYu + _block_diag(BH, N)
        H = 0.5 * (H + jnp.swapaxes(H, 1, 2))
    E = jnp.einsum("jam,ja->jm", QYu, free)
    return _Costs(Yu, Q2, Qh, BH, H, E)


def _block_diag(B: Any, horizon: int) -> Any:
    """I_{N_p} (x) B_j for a batch (J, U, U) -> (J, N_p U, N_p U)."""
    J, U, _ = B.shape
    eye = jnp.eye(horizon, dtype=B.dtype)
    return jnp.einsum("kl,jab->jkalb", eye, B).reshape(J, horizon * U, horizon * U)


def _lowrank_parts(Yu: Any, Qh: Any, B: Any, horizon: int) -> tuple[Any, Any, Any]:
    """(B^-1, W, P) of the Woodbury identity for (D + Y_u' Q2 Y_u)^-1, D = I (x) B.

    With Q2 = Qh Qh' (a Cholesky factor), W = Y_u D^-1 and M = W Y_u'
    (r x r, positive semidefinite)::

        (D + Y_u' Q2 Y_u)^-1 = D^-1 - W' P W,   P = Qh (I + Qh' M Qh)^-1 Qh'

    (valid for any positive semidefinite Q2, singular included). Only U x U and
    r x r symmetric positive definite systems are factorised (Cholesky, no
    pivoting), against n x n for the dense path: cheaper whenever an objective
    has few outputs against its inputs (r << n).
    """
    J, r, n = Yu.shape
    U = B.shape[-1]
    Binv = _spd_inverse(B)
    W = jnp.einsum("jskv,jvu->jsku", Yu.reshape(J, r, horizon, U), Binv).reshape(J, r, n)
    M = W @ jnp.swapaxes(Yu, 1, 2)
    QhT = jnp.swapaxes(Qh, 1, 2)
    S = jnp.eye(r, dtype=B.dtype) + QhT @ M @ Qh
    P = Qh @ _spd_inverse(0.5 * (S + jnp.swapaxes(S, 1, 2))) @ QhT
    return Binv, W, 0.5 * (P + jnp.swapaxes(P, 1, 2))


def _lowrank_inverse(c: _Costs, B: Any, horizon: int) -> Any:
    """(Y_u' 2Qbar Y_u + I (x) B)^-1 by the Woodbury identity (:func:`_lowrank_parts`)."""
    Binv, W, P = _lowrank_parts(c.Yu, c.Qh, B, horizon)
    inv = _block_diag(Binv, horizon) - jnp.swapaxes(W, 1, 2) @ P @ W
    return 0.5 * (inv + jnp.swapaxes(inv, 1, 2))


def _apply_inverse(Kinv: Any, x: Any) -> Any:
    """K^-1 x for x (J, n): Kinv is (J, n, n), or the Woodbury parts
    (B^-1, W, PW = P W) of :func:`_lowrank_parts`, K^-1 = I (x) B^-1 - W' P W.

    Factored: two (r x n) products and the per-step U x U block product as a
    broadcast sum (which XLA fuses with the work around it; measured batched
    at N_p = 10, 0.52 -> 0.49 us per iteration against a dot for it).
    """
    if not isinstance(Kinv, tuple):
        return jnp.einsum("jab,jb->ja", Kinv, x)
    Binv, W, PW = Kinv
    J, n = x.shape
    U = Binv.shape[-1]
    low = jnp.matmul(jnp.swapaxes(W, 1, 2), jnp.matmul(PW, x[..., None]))[..., 0]
    blk = jnp.sum(Binv[:, None] * x.reshape(J, n // U, 1, U), axis=-1).reshape(J, n)
    return blk - low


def _unpad_matrix(M: Any, n_u: int, U: int, horizon: int) -> Any:
    M = M.reshape(horizon, U, horizon, U)[:, :n_u, :, :n_u]
    return M.reshape(horizon * n_u, horizon * n_u)


def local_costs(topology: Topology, data: ProblemData) -> tuple[tuple, tuple]:
    """(H_j, E_j) for every objective (eq.F3_primal_1, NOTES items 8, 18, 19)."""
    lay = _layout(topology)
    U = lay.cols.shape[1]
    N = topology.horizon
    c = _padded_costs(topology, data)
    H, E = c.H, c.E
    Hs = tuple(_unpad_matrix(H[j], n, U, N) for j, n in enumerate(lay.u_sizes))
    Es = tuple(E[j].reshape(N, U)[:, :n].reshape(-1) for j, n in enumerate(lay.u_sizes))
    return Hs, Es


def singular_hessians(
    topology: Topology, data: ProblemData, rtol: float = 1e-12
) -> tuple[tuple[int, float, float], ...]:
    """Objectives whose H_j is singular: ``(j, smallest, largest eigenvalue)``.

    eq.opt_ro's rho* = 1/sqrt(lambda_1 lambda_n) of Abar H_j^-1 Abar' needs
    H_j^-1, which does not exist when some input direction costs nothing in
    objective j (R_(i) singular and Q_j blind to it; both are allowed). Such
    an objective needs a given rho. Not jittable (NumPy eigenvalues of the
    H_j of ``data``); smallest <= ``rtol`` * largest counts as singular.
    """
    Hs, _ = local_costs(topology, data)
    out = []
    for j, H in enumerate(Hs):
        ev = np.linalg.eigvalsh(np.asarray(H, dtype=float))
        if ev[0] <= rtol * max(ev[-1], np.finfo(float).tiny):
            out.append((j, float(ev[0]), float(ev[-1])))
    return tuple(out)


def optimal_rho(H: Any, Ain: Any, horizon: int, rank: int | None = None) -> Any:
    """eq.opt_ro, exactly: rho* = 1 / sqrt(lambda_1 lambda_n) of M = Abar H^-1 Abar'.

    lambda_1 and lambda_n are the smallest non-zero and the largest eigenvalue
    of M. The non-zero eigenvalues of M are those of H^-1 Abar'Abar (same
    non-zero spectrum of XY and YX).

    * Full column rank A_in,j (every bounded input; ``rank is None``): all of
      H^-1 Abar'Abar's eigenvalues are non-zero. With Abar'Abar = L L' (block
      diagonal, L = I (x) chol(A_in,j' A_in,j)) they are 1/mu for mu the
      eigenvalues of G = L^-1 H L^-T, so rho* = sqrt(mu_min mu_max): no
      threshold, so float32 does not pick rounding noise (jax-facts). For
      two-sided boxes this is sqrt(lambda_min(H) lambda_max(H)) / 2 (NOTES 16).
    * Otherwise ``rank`` = rank(A_in,j) per step gives the number of non-zero
      eigenvalues, N_p * rank, of L_H^-1 Abar'Abar L_H^-T (L_H = chol(H)):
      the known rank replaces a numerical threshold.

    This is the exact (eigendecomposition) form, ``rho_method="eigh"`` of
    :class:`LocalExplicit`; the default estimates mu_min and mu_max by power
    iteration (:func:`_power_rho`), which is much cheaper on XLA:CPU.
    """
    n = H.shape[0]
    AtA = Ain.T @ Ain
    if rank is None:
        G = _scaled_hessian(H, AtA, horizon)
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


def _scaled_hessian(H: Any, AtA: Any, horizon: int) -> Any:
    """L^-1 H L^-T with L = I (x) chol(A_in' A_in) (see :func:`optimal_rho`).

    Works on one (n, n) H with (U, U) A_in'A_in, or a batch (J, n, n), (J, U, U).
    """
    batched = H.ndim == 3
    Hb = H if batched else H[None]
    Ab = AtA if batched else AtA[None]
    J, n = Hb.shape[0], Hb.shape[1]
    nu = n // horizon
    La = jnp.linalg.cholesky(Ab)
    Li = jsl.solve_triangular(La, _eye_like(nu, H.dtype, J), lower=True)
    G = jnp.einsum("jab,jkblc,jdc->jkald", Li, Hb.reshape(J, horizon, nu, horizon, nu), Li)
    G = G.reshape(J, n, n)
    return G if batched else G[0]


def _rho_from_quotients(rq: Any) -> Any:
    """sqrt(mu_min mu_max) from the two chains' Rayleigh quotients (J, 2), mu_min
    floored at eps mu_max (a singular H_j)."""
    mu_max = jnp.maximum(rq[:, 0], rq[:, 1])
    mu_min = jnp.maximum(jnp.minimum(rq[:, 0], rq[:, 1]), jnp.finfo(rq.dtype).eps * mu_max)
    return jnp.sqrt(mu_min * mu_max)


def _power_start(mask: Any, dtype: Any) -> Any:
    """The two chains' fixed start (J, 2, n): positive entries on real inputs."""
    J, n = mask.shape
    v0 = np.random.default_rng(12345).uniform(0.5, 1.5, n)
    return jnp.broadcast_to((jnp.asarray(v0, dtype) * mask)[:, None, :], (J, 2, n))


def _blocks(B: Any, x: Any) -> Any:
    """(I (x) B_j) x for B (J, U, U) and x (J, p, n)."""
    J, p, n = x.shape
    U = B.shape[-1]
    return jnp.einsum("juv,jpkv->jpku", B, x.reshape(J, p, n // U, U)).reshape(J, p, n)


def _power_rho(H: Any, Hinv: Any, LamB: Any, mask: Any, iterations: int) -> Any:
    """eq.opt_ro with mu_min, mu_max estimated by power iteration.

    mu are the eigenvalues of the pencil H x = mu Lambda x, Lambda = Abar'Abar
    (= I (x) A_in,j'A_in,j, positive definite for full column rank rows): the
    same as those of G = L^-1 H L^-T of :func:`optimal_rho`, without forming
    L. mu_max comes from iterating x <- Lambda^-1 H x, mu_min from
    x <- H^-1 Lambda x; each estimate is the Rayleigh quotient
    x'Hx / x'Lambda x, which lies inside [mu_min, mu_max], so mu_max is under-
    and mu_min over-estimated. rho only sets the convergence rate (the
    solution does not depend on it): ``rho_iterations`` = 8 gave rho within
    10 % of the exact eigendecomposition on the generated problems (worst
    8.7 %, ``test_power_rho_close_to_exact``) and within 1 % on the shipped
    cruise example (``examples/cruise_control.json``: 0.95 % and 0.06 %).

    H, Hinv : (J, n, n); LamB : (J, U, U) the per-step block of Lambda;
    mask : (J, n) 1 on real entries. The two operators are formed (for one
    problem at the stability example's n = 9 that was 4 us faster than
    applying H and H^-1 in every iteration).
    """
    # the two operators, formed once (n^2 U work: block-diagonal factors); with H,
    # H^-1 and Lambda symmetric, (I (x) B) applied to the rows of M is M (I (x) B)
    LiH = jnp.swapaxes(_blocks(_spd_inverse(LamB), H), 1, 2)  # Lambda^-1 H
    HiL = _blocks(LamB, Hinv)  # H^-1 Lambda
    ops = jnp.stack([LiH, HiL], axis=1)  # (J, 2, n, n): one chain each
    v = _power_start(mask, H.dtype)

    def body(_: Any, v: Any) -> Any:
        v = jnp.einsum("jpab,jpb->jpa", ops, v)
        return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))

    v = jax.lax.fori_loop(0, iterations, body, v)
    num = jnp.einsum("jpa,jab,jpb->jp", v, H, v)
    return _rho_from_quotients(num / jnp.sum(v * _blocks(LamB, v), -1))


def _power_rho_lowrank(
    c: _Costs, BH: Any, LamB: Any, mask: Any, iterations: int, horizon: int
) -> Any:
    """:func:`_power_rho` with H = Y_u' Q2 Y_u + I (x) BH and H^-1 from the Woodbury form.

    No n x n matrix is formed or factorised: each iteration applies
    (:func:`_lowrank_parts`)::

        Lambda^-1 H x = (I (x) Lambda_B^-1) [(I (x) BH) x + Y_u'(Q2 (Y_u x))]
        H^-1 Lambda x = (I (x) BH^-1) Lambda x - W'(P (W Lambda x))

    which is O(n r) per product against the O(n^2 r) of forming the two
    operators. Measured on the cruise example at N_p = 10 (n = 40): setup
    26 against 42 us per case batched over 32 cases, and 56 against 62 us
    for one problem (it was the other way round before the factorisations
    became pure JAX, 2026-11-29).
    """
    Binv, W, P = _lowrank_parts(c.Yu, c.Qh, BH, horizon)
    Laminv = _spd_inverse(LamB)

    def lowrank(L: Any, Mid: Any, R: Any, x: Any) -> Any:
        y = jnp.einsum("jsn,jpn->jps", R, x)
        y = jnp.einsum("jst,jpt->jps", Mid, y)
        return jnp.einsum("jsn,jps->jpn", L, y)

    def Hx(x: Any) -> Any:
        return _blocks(BH, x) + lowrank(c.Yu, c.Q2, c.Yu, x)

    def body(_: Any, v: Any) -> Any:
        up = _blocks(Laminv, Hx(v[:, :1]))  # Lambda^-1 H v
        lx = _blocks(LamB, v[:, 1:])
        down = _blocks(Binv, lx) - lowrank(W, P, W, lx)  # H^-1 Lambda v
        v = jnp.concatenate([up, down], axis=1)
        return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))

    v = _power_start(mask, c.Yu.dtype)
    v = jax.lax.fori_loop(0, iterations, body, v)
    rq = jnp.sum(v * Hx(v), -1) / jnp.sum(v * _blocks(LamB, v), -1)
    return _rho_from_quotients(rq)


_ANDERSON_MAX = 3
"""Largest Anderson memory (its m x m least-squares system is solved in closed form)."""
_ANDERSON_REG = 1e-8
"""Tikhonov weight of the Anderson least squares, relative to trace(dF dF')
(at least 1e3 machine epsilons, so float32 stays well conditioned)."""
_ANDERSON_SAFEGUARD = 2.0
"""An extrapolated point whose fixed-point residual exceeds this factor times
the previous one is dropped: the history restarts from the last accepted image."""


def _check_rho(rho: Any, n_objectives: int) -> None:
    """A given rho (a float or one per objective): positive and finite, or a
    ValueError naming ``rho``. Traced values (inside ``jit``) are not checked."""
    if isinstance(rho, jax.core.Tracer):
        return
    r = np.asarray(rho, dtype=float)
    if r.ndim > 1 or (r.ndim == 1 and r.size not in (1, n_objectives)):
        raise ValueError(
            f"rho: expected a float or {n_objectives} values (one per objective), got shape {r.shape}"
        )
    if not np.all(np.isfinite(r) & (r > 0)):
        raise ValueError(f"rho: expected positive finite values, got {rho!r}")


def _anderson_memory(value: Any) -> int:
    """``value`` as an Anderson memory (an integer in 0..``_ANDERSON_MAX``), or a
    ValueError naming the field (``LocalExplicit.anderson``, ``SimConfig.anderson``)."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not 0 <= int(value) <= _ANDERSON_MAX
    ):
        raise ValueError(
            f"anderson: expected an integer memory in 0..{_ANDERSON_MAX} "
            f"(0 = plain ADMM), got {value!r}"
        )
    return int(value)


class _Anderson(NamedTuple):
    """Anderson acceleration's carry (x: the iterate (Z, gamma) flattened).

    The m past points and their images sit in a ring of separate vectors, not
    stacked, and are overwritten in place. On the cruise example (40 iterate
    entries) a stacked (m + 1, n) history, a buffer over 512 bytes, made
    XLA:CPU run the whole step on its thread pool instead of inline (seen with
    ``jax.profiler``; XLA prefers inline execution when every buffer is that
    small): a step took 113 us instead of 76 us.
    """

    x: Any  # (n,) where the ADMM map is evaluated next
    X: tuple  # m past points (n,), a ring
    G: tuple  # their images under the ADMM map
    valid: Any  # (m,) which ring slots hold a point
    pos: Any  # () the slot the next accepted point overwrites
    fprev: Any  # () ||g - x|| at the last accepted point (inf after a restart)


def _solve_small(A: Any, b: Any) -> Any:
    """x with A x = b for one (m, m) A, m <= 3, by Cramer's rule.

    Elementwise formulas, which XLA fuses into one kernel (an unrolled
    factorisation was a dozen kernels per iteration on XLA:CPU). A is the
    regularised Gram matrix of :func:`_anderson_step`, so det(A) > 0.
    """
    m = A.shape[-1]
    if m == 1:
        return b / A[0]
    if m == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return jnp.stack([A[1, 1] * b[0] - A[0, 1] * b[1], A[0, 0] * b[1] - A[1, 0] * b[0]]) / det
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    adj = jnp.stack(
        [
            jnp.stack(
                [c00, A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2], A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]]
            ),
            jnp.stack(
                [c01, A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0], A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]]
            ),
            jnp.stack(
                [c02, A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1], A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]]
            ),
        ]
    )
    return jnp.sum(adj * b[None, :], axis=1) / det


def _anderson_init(x: Any, m: int) -> _Anderson:
    z = tuple(x for _ in range(m))  # empty slots (valid = 0); masked out until written
    return _Anderson(
        x, z, z, jnp.zeros((m,), x.dtype), jnp.zeros((), jnp.int32), jnp.asarray(jnp.inf, x.dtype)
    )


def _anderson_step(a: _Anderson, g: Any) -> _Anderson:
    """Next point of type-II Anderson acceleration, given g = T(a.x).

    With f = g - x and the differences to the m last accepted points and
    images, dF_i = f - (g_i - x_i), dG_i = g - g_i::

        theta = argmin ||f - sum_i theta_i dF_i||^2 + lambda ||theta||^2,
        x_next = g - sum_i theta_i dG_i

    (Walker and Ni 2011; lambda = ``_ANDERSON_REG`` trace(dF dF')). Safeguard:
    when ||f|| > ``_ANDERSON_SAFEGUARD`` times the last accepted residual, the
    point is dropped and the iteration restarts, plainly, from the last
    accepted image. All inner products come from one Gram matrix of (dF, f).
    """
    m = len(a.X)
    dt = g.dtype
    f = g - a.x
    dF = [(f - a.G[i] + a.X[i]) * a.valid[i] for i in range(m)]
    dG = [(g - a.G[i]) * a.valid[i] for i in range(m)]
    V = dF + [f]
    pairs = [(i, j) for i in range(m + 1) for j in range(i, m + 1)]
    # one variadic reduction over all the products, which XLA fuses with them
    # into one kernel (a stacked V or stacked products would be buffers of
    # their own, and separate sums a kernel each)
    dots = jax.lax.reduce(
        tuple(V[i] * V[j] for i, j in pairs),
        tuple(jnp.zeros((), dt) for _ in pairs),
        lambda u, w: tuple(p + q for p, q in zip(u, w, strict=True)),
        (0,),
    )
    at = {p: k for k, p in enumerate(pairs)}
    gram = jnp.stack(
        [jnp.stack([dots[at[min(i, j), max(i, j)]] for j in range(m + 1)]) for i in range(m + 1)]
    )  # (m + 1, m + 1)
    A, b = gram[:m, :m], gram[:m, m]
    fn = jnp.sqrt(jnp.maximum(gram[m, m], jnp.finfo(dt).tiny))  # finite gradient at f = 0
    reject = jnp.any(a.valid > 0) & (fn > _ANDERSON_SAFEGUARD * a.fprev)
    reg = max(_ANDERSON_REG, 1e3 * float(jnp.finfo(dt).eps))
    A = A + jnp.diag(1.0 - a.valid + reg * jnp.trace(A) + jnp.finfo(dt).tiny)
    theta = _solve_small(A, b)
    theta = jnp.where(jnp.all(jnp.isfinite(theta)), theta, 0.0)
    x_aa = g - sum(theta[i] * dG[i] for i in range(m))
    slot = jnp.arange(m) == a.pos
    last = jnp.arange(m) == (a.pos - 1) % m
    write = slot & ~reject
    return _Anderson(
        x=jnp.where(reject, sum(a.G[i] * last[i] for i in range(m)), x_aa),
        X=tuple(jnp.where(write[i], a.x, a.X[i]) for i in range(m)),
        G=tuple(jnp.where(write[i], g, a.G[i]) for i in range(m)),
        valid=jnp.where(reject, last, slot | (a.valid > 0)).astype(dt),
        pos=jnp.where(reject, a.pos, (a.pos + 1) % m).astype(jnp.int32),
        fprev=jnp.where(reject, jnp.inf, fn).astype(dt),
    )


def shift_horizon(x: Any, steps: int = 1, axis: int = 0) -> Any:
    """x moved one step along its horizon axis ``axis``, the last step repeated
    (``steps=1``), or unchanged (``steps=0``): the MPC warm start."""
    if steps not in (0, 1):
        raise ValueError(f"steps: expected 0 (hold) or 1 (shift), got {steps!r}")
    if not steps:
        return x
    n = x.shape[axis]
    head = jax.lax.slice_in_dim(x, 1, n, axis=axis)
    return jnp.concatenate([head, jax.lax.slice_in_dim(x, n - 1, n, axis=axis)], axis=axis)


def shift_state(state: ADMMState, steps: int = 1) -> ADMMState:
    """Warm start: the previous step's iterate shifted along the horizon.

    ``steps=1`` (default): step k+1 becomes step k and the last step is
    repeated, the usual MPC warm start. ``steps=0`` holds the previous iterate
    as it is (only the iteration count and residuals are reset): on the
    vehicle examples' short horizons (N_p = 2 to 3) that needed fewer
    iterations in the stability example (``docs/results.md``).
    """
    inf = jnp.full_like(state.primal, jnp.inf)
    return ADMMState(
        U=shift_horizon(state.U, steps, axis=1),
        Z=shift_horizon(state.Z, steps),
        gamma=shift_horizon(state.gamma, steps, axis=1),
        iteration=jnp.zeros((), jnp.int32),
        primal=inf,
        dual=inf,
    )


def cold_state(topology: Topology, dtype: Any = None) -> ADMMState:
    """The cold start of alg:1 for ``topology``: zeros, residuals inf (``dtype``:
    default JAX's float, float64 with ``jax_enable_x64``)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    lay = _layout(topology)
    J, U = lay.cols.shape
    N = topology.horizon
    return ADMMState(
        U=jnp.zeros((J, N, U), dtype),
        Z=jnp.zeros((N, topology.n_c), dtype),
        gamma=jnp.zeros((J, N, lay.rows.shape[1]), dtype),
        iteration=jnp.zeros((), jnp.int32),
        primal=jnp.full((J,), jnp.inf, dtype),
        dual=jnp.full((J,), jnp.inf, dtype),
    )


@dataclass(frozen=True)
class LocalExplicit:
    """Local Explicit solver for one :class:`Topology` (static, hashable).

    Parameters
    ----------
    topology : the MACS structure.
    max_iter : iteration cap of the ``while_loop`` runner.
    tol_primal, tol_dual : eps_r and eps_s of eq.Convergence (squared norms).
        Absolute, as in the paper, in the constraint rows' units squared: scale
        them with the problem (inputs of order 1e-6 meet the 1e-6 default after
        one iteration, far from the optimum). Only the first step U^(0) is
        pinned tightly by the stopping rule in practice; later steps of ``u``
        can be less accurate at the same tolerance.
    dual_residual : ``"slack"`` (default) tests ||Z_j^q - Z_j^(q-1)||^2 <= eps_s,
        the slack's change in the constraints' own units; ``"paper"`` tests
        ||s_j||^2 = ||rho_j (Z_j^q - Z_j^(q-1))||^2 <= eps_s as printed. The
        printed form scales with rho_j, and eq.opt_ro gives rho_j ~ 1e-6 when
        the weights are per Nm^2 (vehicle examples): a fixed eps_s is then met
        while Z still moves by newtons, and the solver stops far from the
        optimum. ``SolveResult.dual_residual`` reports the tested quantity.
    rho_method : how eq.opt_ro's extreme eigenvalues are found when rho is not
        given. ``"power"`` (default): power iteration on the pencil
        (H_j, Abar_j'Abar_j) and its inverse (``rho_iterations`` steps, see
        :func:`_power_rho`, :func:`_power_rho_lowrank`); ``"eigh"``: the
        exact eigendecomposition (:func:`optimal_rho`), several times slower on
        XLA:CPU (LAPACK eigensolvers dominate a small step). Objectives whose
        rows A_in,j are column-rank deficient always use the exact form.
    rho_iterations : power-iteration steps of ``rho_method="power"``.
    rho_scale : factor(s) on eq.opt_ro's rho_j (a float, or one per objective),
        used when no rho is given. eq.opt_ro minimises a bound on the linear
        convergence rate, not the iteration count; on the cruise example the
        fewest iterations come at about (1, 0.1) x rho* (``python
        bench/bench_local_explicit.py --tune`` sweeps it; the closed loop's own
        choices are in ``simulation.CONTROLLER_DEFAULTS``). Scaling rho* keeps
        it following the operating point.
    relaxation : over-relaxation factor alpha of the global and dual steps
        (Boyd et al. 2011, sec. 3.4.3): Abar_j U_j is replaced there by
        alpha Abar_j U_j + (1 - alpha)(bbar_j - Z_j^(q-1)). 1.0 (default) is
        the paper's iteration; 1.5 to 1.8 usually needs fewer iterations. The
        stopping rule still tests the unrelaxed residual r_j.
    factorisation : how K_j^-1 (and H_j^-1 for rho) are formed: ``"dense"``
        (Cholesky of the N_p n_u,j square matrix), ``"lowrank"`` (Woodbury
        identity through the N_p n_y,j outputs, :func:`_lowrank_inverse`) or
        ``"auto"`` (low-rank when every objective has at most half as many
        outputs as inputs per step, see :attr:`lowrank`).
    inverse : how the low-rank K_j^-1 is applied in an iteration: ``"formed"``
        (formed once per step, one n x n matrix-vector product per iteration),
        ``"factored"`` (the Woodbury parts, O(n r) per iteration and no O(n^2 r)
        forming) or ``"auto"`` (factored when every objective has fewer than
        half as many outputs as inputs per step, see :attr:`factored`). The
        dense factorisation is always formed.
    anderson : memory m of Anderson acceleration (type II, Walker and Ni 2011)
        of the ADMM map (Z, gamma) -> (Z+, gamma+), at most 3; 0 (default) is the paper's
        plain iteration. Each iteration still evaluates the map once (the
        iteration count is the number of local solves); the next point is the
        combination of the last m + 1 images that minimises the linearised
        fixed-point residual (:func:`_anderson_step`), with a safeguard that
        falls back to the plain step when the residual grows. The fixed points,
        and so the solution, are ADMM's. On the vehicle examples m = 3 cut the
        warm-started iteration count's 95th percentile from 17.2 to 14 (cruise)
        and the paper's rho* iteration's median from 190 to 43 (benchmark,
        N_p = 10). An accelerated iteration costs more (the history's inner
        products and updates), so with few iterations to save a step can take
        longer (README, "Speed"). ``run`` and ``run_fixed`` both accelerate;
        gradients through an accelerated ``run_fixed`` match finite
        differences while the iterate is still above round-off (once it has
        converged to machine precision Anderson's least squares, and so the
        map, is no longer smooth: differentiate fewer iterations, or plain ADMM).

    Use :meth:`solve` for deployment (early stop) and :meth:`solve_fixed` for
    differentiation (fixed iteration count under ``lax.scan``). Both are pure
    and jittable; ``jax.jit(solver.solve)`` compiles one control step.
    """

    topology: Topology
    max_iter: int = 500
    tol_primal: float = 1e-6
    tol_dual: float = 1e-6
    dual_residual: str = "slack"
    rho_method: str = "power"
    rho_iterations: int = 8
    rho_scale: float | tuple = 1.0
    relaxation: float = 1.0
    factorisation: str = "auto"
    inverse: str = "auto"
    anderson: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.max_iter, bool) or not isinstance(self.max_iter, (int, np.integer)):
            raise ValueError(f"max_iter: expected an integer >= 1, got {self.max_iter!r}")
        if self.max_iter < 1:
            raise ValueError(f"max_iter: expected an integer >= 1, got {self.max_iter}")
        for name in ("tol_primal", "tol_dual"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating, np.integer)) and 0 <= v < np.inf):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        if self.dual_residual not in ("slack", "paper"):
            raise ValueError(
                f"dual_residual: expected 'slack' or 'paper', got {self.dual_residual!r}"
            )
        if self.rho_method not in ("power", "eigh"):
            raise ValueError(f"rho_method: expected 'power' or 'eigh', got {self.rho_method!r}")
        if int(self.rho_iterations) < 1:
            raise ValueError(f"rho_iterations: expected >= 1, got {self.rho_iterations}")
        scale = np.atleast_1d(np.asarray(self.rho_scale, dtype=float))
        if scale.size > 1:  # hashable (the solver is a static jit argument)
            object.__setattr__(self, "rho_scale", tuple(float(x) for x in scale))
        if scale.size not in (1, self.topology.n_objectives):
            raise ValueError(
                f"rho_scale: expected a float or {self.topology.n_objectives} values "
                f"(one per objective), got {scale.size}"
            )
        if not np.all(np.isfinite(scale) & (scale > 0)):
            raise ValueError(f"rho_scale: expected positive finite values, got {self.rho_scale}")
        if self.factorisation not in ("auto", "dense", "lowrank"):
            raise ValueError(
                f"factorisation: expected 'auto', 'dense' or 'lowrank', got {self.factorisation!r}"
            )
        if self.inverse not in ("auto", "formed", "factored"):
            raise ValueError(
                f"inverse: expected 'auto', 'formed' or 'factored', got {self.inverse!r}"
            )
        if self.factorisation == "lowrank" and self.topology.singular_r:
            names = [self.topology.agent_names[i] for i in self.topology.singular_r]
            raise ValueError(
                f"factorisation: 'lowrank' needs every R_(i) positive definite; singular "
                f"for {names} (use 'dense' or 'auto')"
            )
        if self.inverse == "factored" and not self.lowrank:
            raise ValueError(
                "inverse: 'factored' needs the low-rank factorisation "
                "(factorisation='lowrank', or 'auto' with few outputs)"
            )
        if not 0.0 < float(self.relaxation) < 2.0:
            raise ValueError(f"relaxation: expected a value in (0, 2), got {self.relaxation}")
        object.__setattr__(self, "anderson", _anderson_memory(self.anderson))
        self.topology.check_local_explicit()

    def _own(self, j: int) -> np.ndarray:
        """Positions of objective j's own rows (``Topology.group_rows(j)`` order)
        among its R rows in the setup and the loop carry, in either row layout."""
        return np.flatnonzero(_layout(self.topology).rows[j] < self.topology.n_c)

    def objective_constraints(self, setup: LocalSetup, j: int) -> tuple[Any, Any]:
        """(A_in,j (n_c,j x n_u,j), bbar_j (N_p x n_c,j)): objective j's own rows in
        the order of ``Topology.group_rows(j)``, whatever the setup's row layout."""
        own, u = self._own(j), _layout(self.topology).u_sizes[j]
        return setup.Ain[j][own, :u], setup.b[j][:, own]

    # -- per-step setup -----------------------------------------------------------
    @property
    def lowrank(self) -> bool:
        """Whether K_j^-1 comes from the Woodbury identity (:func:`_lowrank_inverse`).

        ``factorisation="auto"``: when every objective (padded) has at most half
        as many outputs as inputs per step (r <= n / 2). The Woodbury form
        factorises r x r instead of n x n but needs more (small) operations, so
        near r = n the dense form is cheaper; measured on the vehicle examples
        (N_p = 2 to 20): one output against three or four inputs favours the
        low-rank form, two outputs against three inputs the dense one. Not when
        some R_(i) is singular (``Topology.singular_r``): the Woodbury form
        inverts the per-step block 2 R_j / m + rho_j A_in,j' A_in,j, which is then
        singular whenever the rows leave a null direction of R_j free, although
        K_j itself is positive definite.
        """
        if self.factorisation != "auto":
            return self.factorisation == "lowrank"
        lay = _layout(self.topology)
        return 2 * max(lay.y_sizes) <= lay.cols.shape[1] and not self.topology.singular_r

    @property
    def factored(self) -> bool:
        """Whether the low-rank K_j^-1 is applied in factored form (see ``inverse``).

        ``inverse="auto"``: when every objective has fewer than half as many
        outputs as inputs per step (r < n / 2). Measured on the cruise
        benchmark problem (one output, four inputs; setup plus one iteration,
        then each further iteration, formed -> factored): batched over 32
        cases, N_p = 10: 23.1 -> 19.3 us and 0.82 -> 0.51 us per case; N_p = 20:
        109.6 -> 91.7 and 2.13 -> 1.15 us. One problem, N_p = 10: 56.5 -> 53.6
        and 1.15 -> 0.89 us; N_p = 20: 120 -> 106 and 2.4 -> 1.5 us. The closed
        loop's cruise step (N_p = 2) got about 4 us faster. The merged cruise
        problem (two outputs, four inputs, r = n / 2) was 1 us slower
        factored, so it stays formed.
        """
        if not self.lowrank:
            return False
        if self.inverse != "auto":
            return self.inverse == "factored"
        lay = _layout(self.topology)
        return 2 * max(lay.y_sizes) < lay.cols.shape[1]

    def setup(self, data: ProblemData, rho: Any = None) -> LocalSetup:
        """Build H_j, E_j, rho_j and factorise (once per control step).

        ``rho``: ``None`` for eq.opt_ro per objective (times ``rho_scale``), a
        scalar, or (n_obj,).
        """
        T = self.topology
        lay = _layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        need_H = not self.lowrank or self.rho_method == "eigh" or not all(lay.full)
        c = _padded_costs(T, data, with_H=need_H)
        dt = c.E.dtype
        # each objective's R rows (lay.rows; a padded index reads a zero row)
        Aix = jnp.pad(data.Ain, ((0, 1), (0, 1)))  # padded row / column index -> 0
        Ain = Aix[lay.rows[:, :, None], lay.cols[:, None, :]]  # (J, R, U)
        bx = jnp.pad(data.bin, ((0, 0), (0, 1)))
        b = jnp.moveaxis(bx[:, lay.rows], 1, 0)  # (J, N, R)
        AtA = jnp.einsum("jcu,jcv->juv", Ain, Ain)
        if rho is None:
            scale = np.broadcast_to(np.asarray(self.rho_scale, dtype=float), (J,))
            rho_arr = self._optimal_rhos(c, Ain, AtA) * jnp.asarray(scale, dt)
        else:
            _check_rho(rho, J)
            rho_arr = jnp.broadcast_to(jnp.asarray(rho, dt), (J,))
        # K_j = H_j + rho_j I (x) A_in,j'A_in,j, all objectives in one batched
        # factorisation; its inverse, formed or kept factored (``inverse``), makes an
        # iteration a few matrix-vector products.
        BK = c.BH + rho_arr[:, None, None] * AtA
        if self.lowrank:
            if self.factored:
                Binv_K, W_K, P_K = _lowrank_parts(c.Yu, c.Qh, BK, N)
                Kinv = (Binv_K, W_K, P_K @ W_K)  # applied in factored form
            else:
                Kinv = _lowrank_inverse(c, BK, N)
        else:
            Kinv = _spd_inverse_dense(c.H + _block_diag(rho_arr[:, None, None] * AtA, N))
        KE = _apply_inverse(Kinv, c.E)
        den = rho_arr @ jnp.asarray(lay.carried, dt)
        return LocalSetup(
            Ain=Ain,
            b=b,
            rho=rho_arr,
            Kinv=Kinv,
            KE=KE,
            inv_den=1.0 / jnp.where(den > 0, den, 1.0),
            lb=data.lb,
            ub=data.ub,
        )

    def _optimal_rhos(self, c: _Costs, Ain: Any, AtA: Any) -> Any:
        """eq.opt_ro for every objective (see ``rho_method``)."""
        T = self.topology
        lay = _layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        H = c.H
        dt = c.E.dtype
        full = np.asarray(lay.full)
        out = [None] * J
        if full.any():
            # Padded inputs: identity in A_in'A_in and in H, decoupled from the real
            # entries. Rank-deficient objectives get an identity here and the exact
            # form below.
            eyeU = jnp.asarray(np.eye(U)[None] * (1.0 - lay.umask)[:, :, None], dt)
            fixed = jnp.asarray((~full)[:, None, None] * np.eye(U), dt)
            LamB = AtA * jnp.asarray(full[:, None, None], dt) + eyeU + fixed
            mask = jnp.asarray(np.tile(lay.umask, (1, N)), dt)
            if self.rho_method == "power":
                # H may be singular (R_j = 0): a shift of eps * mean(diag H) keeps
                # its inverse finite and mu_min at about the eps * mu_max floor
                nj = jnp.asarray([N * u for u in lay.u_sizes], dt)
                um = jnp.asarray(lay.umask, dt)
                tr = jnp.sum(c.Yu * (c.Q2 @ c.Yu), axis=(1, 2)) + N * jnp.einsum(
                    "jaa,ja->j", c.BH, um
                )
                delta = (jnp.finfo(dt).eps * tr / nj)[:, None, None]
                if self.lowrank:
                    BHd = c.BH + delta * jnp.eye(U, dtype=dt)
                    rho_full = _power_rho_lowrank(c, BHd, LamB, mask, self.rho_iterations, N)
                else:
                    Hinv = _spd_inverse_dense(H + delta * jnp.eye(N * U, dtype=dt))
                    rho_full = _power_rho(H, Hinv, LamB, mask, self.rho_iterations)
            else:
                # exact: G = L^-1 H L^-T padded with the mean real eigenvalue
                # (trace / n_j), which lies between the extreme ones and so leaves
                # mu_min, mu_max unchanged
                G = _scaled_hessian(H, LamB, N)
                G = 0.5 * (G + jnp.swapaxes(G, 1, 2))
                nj = jnp.asarray([N * u for u in lay.u_sizes], dt)
                mean = jnp.einsum("jaa->j", G * mask[:, :, None]) / nj
                G = G * (mask[:, :, None] * mask[:, None, :]) + (1 - mask)[:, :, None] * (
                    mean[:, None, None] * jnp.eye(N * U, dtype=dt)
                )
                mu = jnp.linalg.eigvalsh(G)
                eps = jnp.finfo(dt).eps
                rho_full = jnp.sqrt(jnp.maximum(mu[:, 0], eps * mu[:, -1]) * mu[:, -1])
            for j in range(J):
                if full[j]:
                    out[j] = rho_full[j]
        for j in range(J):
            if not full[j]:
                u = lay.u_sizes[j]
                Hj = _unpad_matrix(H[j], u, U, N)
                Aj = Ain[j][self._own(j), :u]
                out[j] = optimal_rho(Hj, Aj, N, T.group_rank[j])
        return jnp.stack(out)

    def init(self, setup: LocalSetup, warm: ADMMState | None = None) -> ADMMState:
        """Cold start (zeros, as alg:1) or a warm start state (see :func:`shift_state`).

        A warm state's U, Z and gamma are kept; its iteration count and
        residuals are reset, so that a previous result's ``.state`` passed as
        it is (not shifted) still iterates on the new data instead of being
        taken as converged.
        """
        cold = cold_state(self.topology, setup.rho.dtype)
        if warm is None:
            return cold
        if not isinstance(warm, ADMMState):
            raise TypeError(
                f"warm: expected an ADMMState (a previous result's .state, shifted), "
                f"got {type(warm).__name__}"
            )
        for name, want, got in zip(ADMMState._fields, cold, warm, strict=True):
            if jnp.shape(got) != want.shape:
                raise ValueError(
                    f"warm.{name}: expected shape {want.shape} for this topology "
                    f"(ADMMState is in the solver's padded layout; build one from "
                    f"per-objective arrays with LocalExplicit.state_of), got {jnp.shape(got)}"
                )
        return warm._replace(iteration=cold.iteration, primal=cold.primal, dual=cold.dual)

    # -- per-objective views of the padded state ------------------------------------
    def local_inputs(self, state: ADMMState) -> tuple:
        """U_j, (N_p, n_u,j) per objective, columns in ``Topology.group_columns(j)`` order."""
        lay = _layout(self.topology)
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
        lay = _layout(T)
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
        lay = _layout(T)
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
        Uf = -(setup.KE + _apply_inverse(setup.Kinv, g))  # eq.F3_primal
        AU = jnp.sum(Uf.reshape(J, N, 1, U) * Ain, axis=3)  # Abar_j U_j
        # eq.F3_dual, rho-weighted (NOTES 14): Z_c = max(0, sum_j rho_j v_jc / sum_j rho_j)
        if self.relaxation != 1.0:  # over-relaxation (Boyd et al. 2011, sec. 3.4.3)
            a = self.relaxation
            AUr = a * AU + (1.0 - a) * (setup.b - Z_old)
        else:
            AUr = AU
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
        dz = mask(Zs - Z_old)
        if self.dual_residual == "paper":
            dz = rho * dz  # s_j = rho_j (Z_j - Z_j_prev), eq.Convergence
        primal = jnp.sum(r * r, axis=(1, 2))
        dual = jnp.sum(dz * dz, axis=(1, 2))
        return ADMMState(Uf.reshape(J, N, U), Z, gamma, st.iteration + 1, primal, dual)

    def converged(self, state: ADMMState) -> Any:
        """eq.Convergence for every objective (see ``dual_residual``)."""
        return jnp.all((state.primal <= self.tol_primal) & (state.dual <= self.tol_dual))

    # -- runners ---------------------------------------------------------------------
    def run(self, setup: LocalSetup, state: ADMMState) -> ADMMState:
        """``lax.while_loop`` until eq.Convergence or ``max_iter`` (deployment)."""

        def cond(st: ADMMState) -> Any:
            finite = jnp.all(jnp.isfinite(st.primal) | (st.iteration == 0))
            return (st.iteration < self.max_iter) & ~self.converged(st) & finite

        carry, body, iterate_of = self._loop(setup, state)
        return iterate_of(jax.lax.while_loop(lambda c: cond(iterate_of(c)), body, carry))

    def run_fixed(self, setup: LocalSetup, state: ADMMState, iterations: int) -> ADMMState:
        """Exactly ``iterations`` iterations under ``lax.scan`` (differentiable)."""
        if (
            isinstance(iterations, bool)
            or not isinstance(iterations, (int, np.integer))
            or iterations < 1
        ):
            raise ValueError(f"iterations: expected an integer >= 1, got {iterations!r}")
        carry, body, iterate_of = self._loop(setup, state)
        out, _ = jax.lax.scan(lambda c, _: (body(c), None), carry, None, length=iterations)
        return iterate_of(out)

    def _loop(self, setup: LocalSetup, state: ADMMState) -> tuple[Any, Any, Any]:
        """Both runners' loop: its initial carry, one iteration, and the iterate
        in the carry (the carry is the iterate itself, or with ``anderson`` the
        iterate and the acceleration's history)."""
        if not self.anderson:
            return state, lambda st: self.step(setup, st), lambda st: st
        carry = (state, _anderson_init(self._point(state), self.anderson))
        return carry, lambda c: self._accelerated(setup, c), lambda c: c[0]

    # -- Anderson acceleration (``anderson`` > 0) ------------------------------------
    @staticmethod
    def _point(st: ADMMState) -> Any:
        """The ADMM map's argument (Z, gamma), flattened (U is an output only)."""
        return jnp.concatenate([st.Z.ravel(), st.gamma.ravel()])

    @staticmethod
    def _at(x: Any, st: ADMMState) -> ADMMState:
        nz = st.Z.size
        return st._replace(Z=x[:nz].reshape(st.Z.shape), gamma=x[nz:].reshape(st.gamma.shape))

    def _accelerated(self, setup: LocalSetup, carry: tuple) -> tuple:
        """One ADMM map evaluation at the Anderson point, then the next point."""
        st, a = carry
        out = self.step(setup, self._at(a.x, st))
        return out, _anderson_step(a, self._point(out))

    def result(self, setup: LocalSetup, state: ADMMState) -> SolveResult:
        """Consensus inputs (average of the copies, projected on the bounds) and status."""
        T = self.topology
        lay = _layout(T)
        dt = setup.rho.dtype
        P = jnp.asarray(lay.P, dt)
        # sum_j U_j P_j as one broadcast sum (fused; padded columns select nothing)
        total = jnp.sum(state.U[..., None] * P[:, None], axis=(0, 2))
        count = lay.P.sum(axis=(0, 1))
        u = jnp.clip(total / jnp.asarray(count, dt), setup.lb, setup.ub)
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
