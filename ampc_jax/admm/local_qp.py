"""The inequality-constrained local QPs of Formulations 1 and 2 (eq.F1_primal, eq.F2_primal).

Objective j's local update is the QP, over its padded horizon inputs u (n = N_p U)::

    min 1/2 u' P_j u + q_j' u    s.t.   A_in,j u^(k) <= b_j^(k),  k = 0..N_p-1

with P_j fixed for a control step (the local Hessian plus rho_j I) and q_j,
b_j changing every outer iteration (the multiplier, the consensus target and
the other agents' previous inputs U-tilde of eq.F1_1). It is solved by an
inner ADMM with a slack s >= 0 on the rows (the same splitting as Local
Explicit's, for one objective)::

    u = -M_j^-1 [q_j + Abar_j' (sigma_j (s - b_j) + y)],   M_j = P_j + sigma_j Abar_j'Abar_j
    s = max(0, b_j - Abar_j u - y / sigma_j)
    y = y + sigma_j (Abar_j u - b_j + s)

M_j does not depend on q_j or b_j, so it is inverted once per control step
(:func:`factor`) and every inner iteration is two small matrix-vector
products and elementwise work: all objectives and, under ``vmap``, all
scenarios at once, with no host call and no data-dependent shape. The inner
state (s, y) is carried from one outer iteration to the next, so a fixed,
small number of inner iterations per outer iteration suffices (an inexact
ADMM: at the outer fixed point the inner data stop changing, and the inner
fixed point is the exact local solution).

Why this and not a packaged QP solver (qpax's interior point, jaxopt's
OSQP): an interior-point method refactorises its KKT matrix at every one of
its iterations and cannot use the previous outer iteration's answer, while
here the factorisation is shared by every inner and outer iteration of a
control step (``docs/formulations.md`` gives the measurement that decided it,
``bench/bench_local_qp.py``).

sigma_j is Ghadimi et al.'s choice for this splitting (eq.opt_ro with
A = Abar_j): for rows that are boxes it is sqrt(lambda_min(P_j)
lambda_max(P_j)) / 2 (paper-notes item 16); for general rows the box form is
scaled by the largest diagonal entry of A_in,j'A_in,j instead of 2
(:func:`inner_rho`). It only sets the inner convergence rate.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .linalg import block_diag, spd_inverse_dense

__all__ = ["InnerState", "LocalQP", "factor", "inner_rho", "iterate"]


class LocalQP(NamedTuple):
    """The per-control-step part of the local QPs (stacked over objectives j).

    A : (J, R, U) per-step rows A_in,j (zero rows and columns where j has none).
    Minv : (J, n, n) M_j^-1 = (P_j + sigma_j Abar_j'Abar_j)^-1.
    sigma : (J,) the inner penalty sigma_j.
    """

    A: Any
    Minv: Any
    sigma: Any


class InnerState(NamedTuple):
    """The inner ADMM's carried iterate: slack s and multiplier y, (J, N_p, R) each."""

    s: Any
    y: Any


def inner_rho(lam_min: Any, lam_max: Any, A: Any) -> Any:
    """(J,) sigma_j = sqrt(lambda_min lambda_max of P_j) / a_j, a_j the largest
    diagonal entry of A_in,j'A_in,j (2 for two-sided boxes: paper-notes item 16)."""
    a = jnp.max(jnp.sum(A * A, axis=1), axis=-1)
    return jnp.sqrt(lam_min * lam_max) / jnp.where(a > 0, a, 1.0)


def factor(P: Any, A: Any, sigma: Any, horizon: int) -> LocalQP:
    """Invert M_j = P_j + sigma_j I (x) A_in,j'A_in,j for every objective, once."""
    AtA = jnp.einsum("jcu,jcv->juv", A, A)
    M = P + block_diag(sigma[:, None, None] * AtA, horizon)
    return LocalQP(A=A, Minv=spd_inverse_dense(0.5 * (M + jnp.swapaxes(M, 1, 2))), sigma=sigma)


def iterate(
    qp: LocalQP, q: Any, b: Any, state: InnerState, iterations: int
) -> tuple[Any, InnerState, Any, Any]:
    """``iterations`` inner ADMM iterations from ``state`` on the data (q, b).

    q : (J, n) linear terms; b : (J, N_p, R) right-hand sides (zero on the rows
    an objective does not carry, whose coefficients are zero too).
    Returns u (J, n), the new state, and per objective the squared inner
    residuals ||Abar_j u - b_j + s||^2 (primal) and ||s - s_prev||^2 (dual,
    in the rows' units) of the last iteration.
    """
    J, N, R = b.shape
    U = qp.A.shape[-1]
    sig = qp.sigma[:, None, None]
    A = qp.A[:, None]  # (J, 1, R, U)

    def one(carry: tuple) -> tuple:
        s, y, _, _, _ = carry
        w = sig * (s - b) + y
        g = jnp.sum(w[..., None] * A, axis=2).reshape(J, N * U)  # Abar' w
        u = -jnp.einsum("jab,jb->ja", qp.Minv, q + g)
        Au = jnp.sum(u.reshape(J, N, 1, U) * A, axis=3)
        s_new = jnp.maximum(b - Au - y / sig, 0.0)
        r = Au - b + s_new
        return s_new, y + sig * r, u, r, s_new - s

    zeros = jnp.zeros_like(b)
    carry = (state.s, state.y, jnp.zeros_like(q), zeros, zeros)
    carry = jax.lax.fori_loop(0, iterations, lambda _, c: one(c), carry)
    s, y, u, r, ds = carry
    return u, InnerState(s, y), jnp.sum(r * r, axis=(1, 2)), jnp.sum(ds * ds, axis=(1, 2))
