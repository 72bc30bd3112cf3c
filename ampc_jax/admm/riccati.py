"""Objective j's local step as a linear-quadratic problem over the horizon: a Riccati recursion.

The local update of Local Explicit (eq.F3_primal) solves ``K_j U_j = v_j`` with
``K_j = Y_u,j' 2Qbar_j Y_u,j + I (x) B_j``, ``B_j = 2 R_j / m + rho_j A_in,j'A_in,j``
(the rows act step by step: every box and every general row of the problem
file). That system is the stationarity condition of the LQ problem::

    min  sum_{k=1..N_p} 1/2 x_k' Qx_j x_k + sum_{k=0..N_p-1} (1/2 u_k' B_j u_k - v_k' u_k)
    s.t. x_{k+1} = A x_k + Bu_j u_k,   x_0 = 0,            Qx_j = C_j' 2Q_j C_j

so ``K_j^-1 v`` needs no condensed matrix: a backward Riccati recursion (the
factorisation, once per control step, :func:`factor`)::

    P_N = Qx;  G_k = B_j + Bu' P_{k+1} Bu,  L_k = G_k^-1 Bu' P_{k+1} A,
    P_k = Qx + A' P_{k+1} A - A' P_{k+1} Bu L_k

and per right-hand side a backward and a forward sweep (:func:`solve`)::

    p_N = 0;  e_k = Bu' p_{k+1} - v_k,  d_k = G_k^-1 e_k,  p_k = A' p_{k+1} - L_k' e_k
    x_0 = 0;  u_k = -L_k x_k - d_k,  x_{k+1} = A x_k + Bu u_k

O(N_p (n_x^3 + U^3)) to factorise and O(N_p (n_x^2 + n_x U + U^2)) to apply,
against O((N_p U)^3) and O((N_p U)^2) for the condensed dense form
(:class:`~ampc_jax.admm.kkt.DenseKKT`, kept as the check). The linear cost
E_j = Y_u,j' 2Qbar_j (free response - ref) and the product H_j x (for the
power iteration of eq.opt_ro, :func:`power_rho`) come from the same sweeps
over the model, so the structured path never forms Y_u,j.

Every product is written as a broadcast multiply and a sum over the small
trailing axes (n_x, U <= a few), which XLA fuses with the elementwise work
around it, and the horizon loop is unrolled (N_p static): no ``dot`` call, no
inner ``while`` loop per step. The G_k are inverted by unrolled symmetric
sweeps (pure JAX; no LAPACK, so batches never meet the XLA:CPU thread-pool
deadlock of :mod:`~.linalg`).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .linalg import bmm as _mm
from .linalg import bmtm as _mtm
from .linalg import bmtv as _mtv
from .linalg import bmv as _mv

__all__ = [
    "RiccatiFactor",
    "factor",
    "hessian_apply",
    "linear_cost",
    "solve",
    "trace_gram",
    "unrolled_spd_inverse",
]


class RiccatiFactor(NamedTuple):
    """K_j's factorisation by the backward Riccati recursion (stacked over j).

    A : (n_x, n_x) the model; Bu : (J, n_x, U) objective j's input columns
    (zero on padding). Ginv : (N_p, J, U, U) G_k^-1; L : (N_p, J, U, n_x) the
    gains L_k (L_0 is never used: x_0 = 0).
    """

    A: Any
    Bu: Any
    Ginv: Any
    L: Any


def _sym(M: Any) -> Any:
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def unrolled_spd_inverse(M: Any) -> Any:
    """Inverse of a batch (..., m, m) of SPD matrices by m symmetric sweeps, unrolled.

    The same Gauss-Jordan sweeps as :func:`~.linalg.sweep_inverse` (stable
    without pivoting for SPD matrices) with the pivot index static, so each
    sweep is plain elementwise work XLA fuses (no ``while`` loop; m is small).
    """
    m = M.shape[-1]
    A = M
    for k in range(m):
        d = A[..., k : k + 1, k : k + 1]
        v = A[..., :, k : k + 1] / d  # (..., m, 1)
        e = jnp.zeros((m, 1), M.dtype).at[k, 0].set(1.0)
        new = v - e * (1.0 + 1.0 / d)  # column k of the swept matrix
        B = A - d * v * jnp.swapaxes(v, -1, -2)
        row = jnp.swapaxes(new, -1, -2)
        sel_r = jnp.zeros((m, 1), bool).at[k, 0].set(True)
        sel_c = jnp.zeros((1, m), bool).at[0, k].set(True)
        B = jnp.where(sel_r, row, B)
        A = jnp.where(sel_c, new, B)
    return -A


def factor(A: Any, Bu: Any, Qx: Any, Bk: Any, horizon: int) -> RiccatiFactor:
    """The backward Riccati recursion for K_j = Y_u' 2Qbar Y_u + I (x) Bk_j, every j.

    A : (n_x, n_x); Bu : (J, n_x, U); Qx : (J, n_x, n_x) C_j' 2Q_j C_j;
    Bk : (J, U, U) the per-step input block (positive definite).
    """

    def back(P: Any, _: Any) -> tuple[Any, tuple[Any, Any]]:
        PB = _mm(P, Bu)  # (J, n_x, U)
        Gi = unrolled_spd_inverse(_sym(Bk + _mtm(Bu, PB)))
        APB = _mtm(A, PB)  # A' P B  (J, n_x, U)
        Lk = _mm(Gi, jnp.swapaxes(APB, -1, -2))  # G^-1 B' P A  (J, U, n_x)
        return _sym(Qx + _mtm(A, _mm(P, A)) - _mm(APB, Lk)), (Gi, Lk)

    _, (Ginv, L) = _scan(back, Qx, None, horizon, reverse=True)
    return RiccatiFactor(A=A, Bu=Bu, Ginv=Ginv, L=L)


def _scan(body: Any, carry: Any, xs: Any, length: int, reverse: bool = False) -> Any:
    """``lax.scan`` over the horizon. Rule: the horizon is rolled, not unrolled;
    reason: a rolled sweep compiles once whatever N_p (an unrolled one was
    4 N_p small kernels per sweep, and a batch-1 step whose loop XLA:CPU
    compiles into one function took 88 s to compile at N_p = 10,
    ``bench/bench_compile.py``), and a sweep's loop is small enough for
    XLA:CPU to run it as one kernel (``ampc_jax`` sets the threshold)."""
    return jax.lax.scan(body, carry, xs, length=length, reverse=reverse)


def solve(f: RiccatiFactor, v: Any) -> Any:
    """K_j^-1 v_j for v (J, N_p U) (or (J, p, N_p U): p right-hand sides)."""
    N, J, U, nx = f.L.shape
    lead = v.shape[1:-1]
    ones = (1,) * len(lead)
    vk = jnp.moveaxis(v.reshape(J, *lead, N, U), -2, 0)  # (N, J, *lead, U)
    bu = f.Bu.reshape(J, *ones, nx, U)
    Ginv = f.Ginv.reshape(N, J, *ones, U, U)
    L = f.L.reshape(N, J, *ones, U, nx)
    zero = jnp.zeros((J, *lead, nx), v.dtype)

    def back(p: Any, x: tuple) -> tuple[Any, Any]:
        Gk, Lk, vk = x
        e = _mtv(bu, p) - vk
        return _mtv(f.A, p) - _mtv(Lk, e), _mv(Gk, e)

    _, d = _scan(back, zero, (Ginv, L, vk), N, reverse=True)

    def fwd(x: Any, y: tuple) -> tuple[Any, Any]:
        Lk, dk = y
        uk = -(_mv(Lk, x) + dk)
        return _mv(f.A, x) + _mv(bu, uk), uk

    _, u = _scan(fwd, zero, (L, d), N)
    return jnp.moveaxis(u, 0, -2).reshape(v.shape)


def linear_cost(A: Any, Bu: Any, Qx: Any, Cr: Any, x0: Any, w: Any) -> Any:
    """E_j = Y_u,j' 2Qbar_j (Y_x,j x0 + Y_w,j Wbar - ref_j) by one forward sweep (the
    free response) and one adjoint sweep (eq.F3_primal_1; paper-notes items 18, 19:
    the reference belongs to the predicted steps 1..N_p).

    A : (n_x, n_x); Bu : (J, n_x, U); Qx : (J, n_x, n_x) C_j' 2Q_j C_j;
    Cr : (J, N_p, n_x) C_j' 2Q_j ref_j,k; x0 : (n_x,); w : (N_p, n_x).
    Returns (J, N_p U).
    """
    N = w.shape[0]

    def fwd(x: Any, y: tuple) -> tuple[Any, Any]:
        wk, crk = y
        x = _mv(A, x) + wk  # free response x^(k+1), shared by every objective
        return x, _mv(Qx, x) - crk  # C' 2Q (C x^(k+1) - ref_k)

    _, g = _scan(fwd, x0, (w, jnp.moveaxis(Cr, 1, 0)), N)
    return _adjoint(A, Bu, g)


def _adjoint(A: Any, Bu: Any, g: Any) -> Any:
    """(Y_u' applied) E_l = Bu' mu_l, mu_l = g_l + A' mu_(l+1), mu_N = 0; g (N, ..., n_x)
    stacked over the horizon; returns (..., N U)."""
    N = g.shape[0]

    def back(mu: Any, gk: Any) -> tuple[Any, Any]:
        mu = gk + _mtv(A, mu)
        return mu, _mtv(Bu, mu)

    _, out = _scan(back, jnp.zeros_like(g[0]), g, N, reverse=True)
    return jnp.moveaxis(out, 0, -2).reshape(*out.shape[1:-1], -1)


def hessian_apply(A: Any, Bu: Any, Qx: Any, Bh: Any, u: Any) -> Any:
    """H_j u = Y_u' 2Qbar Y_u u + (I (x) Bh) u for u (J, p, N_p U) (p vectors each):
    a forward sweep of the model from x_0 = 0 and an adjoint sweep back."""
    J, P, n = u.shape
    nx, U = Bu.shape[-2:]
    N = n // U
    uk = u.reshape(J, P, N, U)
    bu = Bu[:, None]
    qx = Qx[:, None]

    def fwd(x: Any, ukk: Any) -> tuple[Any, Any]:
        x = _mv(A, x) + _mv(bu, ukk)  # x_{k+1}
        return x, _mv(qx, x)

    _, g = _scan(fwd, jnp.zeros((J, P, nx), u.dtype), jnp.moveaxis(uk, 2, 0), N)
    return _adjoint(A, bu, g) + _mv(Bh[:, None, None], uk).reshape(J, P, n)


def trace_gram(A: Any, Bu: Any, Qx: Any, horizon: int) -> Any:
    """(J,) trace(Y_u' 2Qbar Y_u) = sum_l trace(Bu' S_(N-1-l) Bu), S_m = sum_(i<=m) A'^i Qx A^i."""

    def body(S: Any, _: Any) -> tuple[Any, Any]:
        return Qx + _mtm(A, _mm(S, A)), jnp.sum(Bu * _mm(S, Bu), axis=(-2, -1))

    _, tr = _scan(body, Qx, None, horizon)
    return jnp.sum(tr, axis=0)
