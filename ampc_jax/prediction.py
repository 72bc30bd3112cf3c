"""Prediction matrices and condensed quadratic costs (eq.F3_primal_1, eq.F3_primal_1_1).

All functions are pure and jittable: the model data are traced arrays, only
sizes are static, so a time-varying model is rebuilt inside one compiled step.

Stacking convention: inputs are stacked step by step,
``Ubar = [U^(0); U^(1); ...; U^(N_p-1)]`` (paper-notes item 5), outputs
``Ybar = [C X^(1); ...; C X^(N_p)]`` and the disturbance
``Wbar = [W_d^(0); ...; W_d^(N_p-1)]`` (paper-notes item 18: W is not multiplied by C
again). With ``X^(k+1) = A X^(k) + B U^(k) + W^(k)``,

    Ybar = Y_x X^(0) + Y_u Ubar + Y_w Wbar,
    Y_x[k]    = C A^(k+1),
    Y_u[k, l] = C A^(k-l) B   (l <= k),   Y_w[k, l] = C A^(k-l)   (l <= k).

The local cost of eq.ConsensusADMM_F3 then reads ``1/2 U' H U + E' U + const``
with ``H = 2 (Y_u' Qbar Y_u + Rbar)`` and
``E = 2 Y_u' Qbar (Y_x X^(0) + Y_w Wbar - Xbar_ref)`` (eq.F3_primal_1), where the
reference belongs to the predicted steps 1..N_p (paper-notes item 19).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = ["Prediction", "matrix_powers", "block_toeplitz", "prediction_matrices", "quadratic_cost"]


class Prediction(NamedTuple):
    """Prediction matrices of one output map C over the horizon.

    Y_u : (N_p * n_y, N_p * n_b);  Y_x : (N_p * n_y, n_x);  Y_w : (N_p * n_y, N_p * n_x).
    """

    Y_u: Any
    Y_x: Any
    Y_w: Any


def matrix_powers(A: Any, n: int) -> Any:
    """(n + 1, n_x, n_x) stack of A^0 .. A^n."""

    # Unrolled (n is a static horizon): a loop of tiny matrix products costs
    # more in loop overhead than in arithmetic on XLA:CPU.
    out = [jnp.eye(A.shape[0], dtype=A.dtype)]
    for _ in range(n):
        out.append(A @ out[-1])
    return jnp.stack(out)


def block_toeplitz(blocks: Any, horizon: int) -> Any:
    """Lower block-Toeplitz matrix with ``blocks[d]`` on block diagonal d >= 0.

    blocks : (N_p, p, q) -> (N_p * p, N_p * q).
    """
    k = np.arange(horizon)
    sel = (k[:, None, None] - k[None, :, None] == k[None, None, :]).astype(np.float64)
    full = jnp.einsum("kld,dpq->kplq", jnp.asarray(sel, blocks.dtype), blocks)
    p, q = blocks.shape[1:]
    return full.reshape(horizon * p, horizon * q)


def prediction_matrices(A: Any, B: Any, C: Any, horizon: int) -> Prediction:
    """Y_u, Y_x, Y_w of eq.F3_primal_1 for outputs C X and inputs entering through B.

    Parameters
    ----------
    A : (n_x, n_x) A_d.   B : (n_x, n_b) input columns (B_d,j).   C : (n_y, n_x) C_j.
    horizon : N_p (static).
    """
    P = matrix_powers(A, horizon)  # A^0..A^Np
    CP = jnp.einsum("yx,kxz->kyz", C, P)  # C A^k
    ny, nx = C.shape
    Y_x = CP[1:].reshape(horizon * ny, nx)
    Y_w = block_toeplitz(CP[:horizon], horizon)
    Y_u = block_toeplitz(jnp.einsum("kyx,xb->kyb", CP[:horizon], B), horizon)
    return Prediction(Y_u=Y_u, Y_x=Y_x, Y_w=Y_w)


def quadratic_cost(
    pred: Prediction, Q: Any, R_step: Any, x0: Any, w: Any, ref: Any
) -> tuple[Any, Any]:
    """H and E of eq.F3_primal_1 for one objective.

    Parameters
    ----------
    pred : prediction matrices of the objective's outputs.
    Q : (n_y, n_y) Q_j.  R_step : (n_b, n_b) per-step input weight (Rbar_j = I (x) R_step).
    x0 : (n_x,).  w : (N_p, n_x) W_d^(k).  ref : (N_p, n_y) reference of C X^(k+1).

    Returns
    -------
    H : (N_p n_b, N_p n_b) = 2 (Y_u' Qbar Y_u + Rbar);  E : (N_p n_b,).
    """
    horizon, ny = ref.shape
    Yu = pred.Y_u.reshape(horizon, ny, -1)
    QYu = jnp.einsum("ij,kjb->kib", Q, Yu).reshape(horizon * ny, -1)
    free = pred.Y_x @ x0 + pred.Y_w @ w.reshape(-1) - ref.reshape(-1)
    Rbar = jnp.kron(jnp.eye(horizon, dtype=R_step.dtype), R_step)
    H = 2.0 * (pred.Y_u.T @ QYu + Rbar)
    H = 0.5 * (H + H.T)
    E = 2.0 * (QYu.T @ free)
    return H, E
