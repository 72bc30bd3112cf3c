"""Small dense linear-algebra kernels of the ADMM setup, pure JAX where batched.

Rule: every factorisation inside a ``vmap`` is pure JAX (symmetric sweeps),
never XLA:CPU's batched LAPACK kernels. Those split their batch into tasks on
the intra-op thread pool they themselves run on and wait for them, which
deadlocks once every pool thread runs such a kernel (two CPU devices sharding
a batch on two cores; ``tests/batch/test_batch.py`` pins both the absence of
LAPACK calls and the reproducer). A single (unbatched) problem uses LAPACK
above a small size, where it is faster.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "bmm",
    "bmtm",
    "bmtv",
    "bmv",
    "SWEEP_MAX",
    "SWEEP_MAX_DENSE",
    "apply_blocks",
    "block_diag",
    "eye_like",
    "lapack_spd_inverse",
    "small_cholesky",
    "spd_inverse",
    "spd_inverse_dense",
    "sweep_inverse",
    "woodbury_inverse",
    "woodbury_parts",
]


def eye_like(n: int, dtype: Any, batch: int) -> Any:
    return jnp.broadcast_to(jnp.eye(n, dtype=dtype), (batch, n, n))


def lapack_spd_inverse(M: Any) -> Any:
    """Inverse of a batch (..., n, n) of SPD matrices through LAPACK.

    M = L L' (Cholesky), M^-1 = L^-T L^-1: one triangular solve and one product,
    half the triangular work of ``cho_solve`` with an identity right-hand side.
    """
    L = jnp.linalg.cholesky(M)
    eye = jnp.broadcast_to(jnp.eye(M.shape[-1], dtype=M.dtype), M.shape)
    Li = jax.lax.linalg.triangular_solve(L, eye, left_side=True, lower=True)
    return jnp.einsum("...ka,...kb->...ab", Li, Li)


def sweep_inverse(M: Any) -> Any:
    """Inverse of a batch (..., n, n) of SPD matrices by n symmetric sweeps, pure JAX.

    Sweeping pivot k (Gauss-Jordan elimination without pivoting, stable for
    SPD matrices: the pivots are the positive Schur complements) maps A to
    B with B_kk = -1/d, B_ik = B_ki = A_ik/d and B_ij = A_ij - A_ik A_kj/d,
    d = A_kk; after all n pivots B = -M^-1. Each sweep is one elementwise
    pass, vectorised over the batch; no LAPACK call (see :func:`spd_inverse`).
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


# Largest matrix a single (unbatched) problem inverts by sweeps rather than
# LAPACK. Rule: sweeps while they are cheaper and do not turn the step's thunk
# graph parallel. The Woodbury path keeps its matrices up to 4 x 4: its two
# 10 x 10 sweeps at N_p = 10 are independent branches, which made XLA:CPU run
# the accelerated step on its thread pool (``bench/bench_thunk_graph.py`` shows
# the ready queue; ``bench/bench_local_explicit.py --only latency`` the cost).
# The dense path's H_j + delta I and K_j follow one another, so up to 12 x 12
# (the stability closed loop's 9 x 9 and 12 x 12 are faster by sweeps,
# ``bench/bench_call_overhead.py``).
SWEEP_MAX = 4
SWEEP_MAX_DENSE = 12


def _make_spd_inverse(sweep_max: int) -> Any:
    """:func:`spd_inverse` with sweeps up to ``sweep_max`` x ``sweep_max``."""

    @jax.custom_batching.custom_vmap
    def impl(M: Any) -> Any:
        if M.shape[-1] <= sweep_max:
            return sweep_inverse(M)
        return lapack_spd_inverse(M)

    @impl.def_vmap
    def batched(axis_size: int, in_batched: Any, M: Any) -> tuple[Any, bool]:
        # Batched (vmap over scenarios): always the sweeps. XLA:CPU's batched LAPACK
        # kernels fan their batch out into the intra-op thread pool they run on and
        # wait for it, which deadlocks once every pool thread runs such a kernel
        # (two CPU devices sharding a batch on two cores: ampc_jax.batch).
        (is_batched,) = in_batched
        if not is_batched:
            return impl(M), False
        return sweep_inverse(M), True

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


spd_inverse = _make_spd_inverse(SWEEP_MAX)
"""Inverse of a batch (..., n, n) of symmetric positive definite matrices.

Small matrices (n <= 4, ``SWEEP_MAX``) and every vmapped batch use symmetric
sweeps in pure JAX (:func:`sweep_inverse`); a single larger problem uses
LAPACK (:func:`lapack_spd_inverse`). Derivative (forward and reverse mode)
d(M^-1) = -M^-1 dM M^-1."""

spd_inverse_dense = _make_spd_inverse(SWEEP_MAX_DENSE)
""":func:`spd_inverse` for the dense path's H_j and K_j (sweeps up to ``SWEEP_MAX_DENSE``)."""


def small_cholesky(A: Any) -> Any:
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


def block_diag(B: Any, horizon: int) -> Any:
    """I_{N_p} (x) B_j for a batch (J, U, U) -> (J, N_p U, N_p U)."""
    J, U, _ = B.shape
    eye = jnp.eye(horizon, dtype=B.dtype)
    return jnp.einsum("kl,jab->jkalb", eye, B).reshape(J, horizon * U, horizon * U)


def apply_blocks(B: Any, x: Any) -> Any:
    """(I (x) B_j) x for B (J, U, U) and x (J, p, n)."""
    J, p, n = x.shape
    U = B.shape[-1]
    return jnp.einsum("juv,jpkv->jpku", B, x.reshape(J, p, n // U, U)).reshape(J, p, n)


def woodbury_parts(Yu: Any, Qh: Any, B: Any, horizon: int) -> tuple[Any, Any, Any]:
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
    Binv = spd_inverse(B)
    W = jnp.einsum("jskv,jvu->jsku", Yu.reshape(J, r, horizon, U), Binv).reshape(J, r, n)
    M = W @ jnp.swapaxes(Yu, 1, 2)
    QhT = jnp.swapaxes(Qh, 1, 2)
    S = jnp.eye(r, dtype=B.dtype) + QhT @ M @ Qh
    P = Qh @ spd_inverse(0.5 * (S + jnp.swapaxes(S, 1, 2))) @ QhT
    return Binv, W, 0.5 * (P + jnp.swapaxes(P, 1, 2))


def woodbury_inverse(Yu: Any, Qh: Any, B: Any, horizon: int) -> Any:
    """(Y_u' Q2 Y_u + I (x) B)^-1 formed, by the Woodbury identity (:func:`woodbury_parts`)."""
    Binv, W, P = woodbury_parts(Yu, Qh, B, horizon)
    inv = block_diag(Binv, horizon) - jnp.swapaxes(W, 1, 2) @ P @ W
    return 0.5 * (inv + jnp.swapaxes(inv, 1, 2))


# Batched small products as fused broadcast sums (XLA:CPU fuses them with the
# work around them, where a dot is a kernel of its own): the Riccati sweeps'
# and the exact finish's.
def bmv(M: Any, x: Any) -> Any:
    """M x for M (..., a, b), x (..., b): a fused broadcast sum."""
    return jnp.sum(M * x[..., None, :], axis=-1)


def bmtv(M: Any, x: Any) -> Any:
    """M' x for M (..., a, b), x (..., a)."""
    return jnp.sum(M * x[..., :, None], axis=-2)


def bmm(M: Any, N: Any) -> Any:
    """M N for M (..., a, b), N (..., b, c)."""
    return jnp.sum(M[..., :, :, None] * N[..., None, :, :], axis=-2)


def bmtm(M: Any, N: Any) -> Any:
    """M' N for M (..., b, a), N (..., b, c)."""
    return jnp.sum(M[..., :, :, None] * N[..., :, None, :], axis=-3)
