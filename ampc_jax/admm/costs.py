"""Each objective's local cost in the padded layout (eq.F3_primal_1, paper-notes items 8, 18, 19).

Objective j's local cost is ``1/2 U_j' H_j U_j + E_j' U_j`` with
``H_j = 2 (Y_u,j' Qbar_j Y_u,j + I (x) R_(j) / m)`` and
``E_j = 2 Y_u,j' Qbar_j (Y_x,j X^(0) + Y_w,j Wbar - ref_j)``: the tracking cost
of its outputs and its agents' input weights shared out as R_(i) / m_(i). All
objectives are built at once (:func:`padded_costs`); :func:`local_costs` gives
them unpadded, one per objective. Every ADMM formulation starts from these.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..prediction import block_toeplitz, matrix_powers
from ..problem.data import ProblemData
from ..problem.topology import Topology
from . import riccati
from .layout import padded_layout
from .linalg import block_diag, small_cholesky

__all__ = ["PaddedCosts", "local_costs", "padded_costs", "singular_hessians", "unpad_matrix"]


class PaddedCosts(NamedTuple):
    """Objective-stacked, padded cost data (see :func:`padded_costs`).

    Yu : (J, r, n) Y_u,j (r = N_p Y outputs, n = N_p U inputs, padded).
    Q2 : (J, r, r) 2 Qbar_j = 2 I (x) Q_j.   Qh : (J, r, r) a factor, Q2 = Qh Qh',
    I (x) chol(2 Q_j).   BH : (J, U, U) 2 R_j / m (+ identity on padding).
    H : (J, n, n) H_j = Y_u' 2Qbar Y_u + I (x) BH.   E : (J, n) E_j.
    A : (n_x, n_x) the model; Bu : (J, n_x, U) objective j's input columns B_j
    (zero on padding); Qx : (J, n_x, n_x) C_j' 2Q_j C_j: the stage form the
    structured solve (:mod:`~.riccati`) works on.

    Without the condensed form (``condensed=False``) Yu, Q2, Qh and H are None.
    """

    Yu: Any
    Q2: Any
    Qh: Any
    BH: Any
    H: Any
    E: Any
    A: Any = None
    Bu: Any = None
    Qx: Any = None


def padded_costs(
    topology: Topology, data: ProblemData, with_H: bool = True, condensed: bool = True
) -> PaddedCosts:
    """H_j, E_j of every objective in the padded layout, all objectives at once.

    Same formulas as :func:`~ampc_jax.prediction.quadratic_cost` (eq.F3_primal_1,
    paper-notes items 8, 18, 19): H_j = 2 (Y_u,j' Qbar_j Y_u,j + I (x) R_(j) / m),
    E_j = 2 Y_u,j' Qbar_j (Y_x,j X^(0) + Y_w,j Wbar - ref_j). The matrix powers
    and the free response are shared by all objectives; padded inputs get an
    identity block in H, padded outputs zero weight. ``with_H=False`` skips
    forming H (n^2 r work) for the low-rank path, which never needs it;
    ``condensed=False`` skips Y_u too (the structured solve, :mod:`~.riccati`):
    E_j then comes from a forward and an adjoint sweep of the model
    (:func:`~.riccati.linear_cost`).
    """
    T = topology
    lay = padded_layout(T)
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
    Cq = 2.0 * jnp.einsum("jyz,jzx->jyx", Qp, Cp)  # 2 Q_j C_j
    Qx = jnp.einsum("jyx,jyz->jxz", Cp, Cq)  # C_j' 2Q_j C_j
    Qx = 0.5 * (Qx + jnp.swapaxes(Qx, 1, 2))
    if not condensed:
        Cr = jnp.einsum("jyx,jky->jkx", Cq, refp)  # C_j' 2Q_j ref_j,k
        E = riccati.linear_cost(data.A, Bj, Qx, Cr, data.x0, data.w)
        return PaddedCosts(None, None, None, BH, None, E, data.A, Bj, Qx)
    Pw = matrix_powers(data.A, N)  # A^0..A^N
    # free response x^(k+1) = A^(k+1) x0 + sum_{l<=k} A^(k-l) w_l
    xf = Pw[1:] @ data.x0 + (block_toeplitz(Pw[:N], N) @ data.w.reshape(-1)).reshape(N, -1)
    free = (jnp.einsum("jyx,kx->jky", Cp, xf) - refp).reshape(J, N * Y)
    CPB = jnp.einsum("jyx,kxz,jzu->jkyu", Cp, Pw[:N], Bj)  # C_j A^k B_j
    Yu = jax.vmap(block_toeplitz, in_axes=(0, None))(CPB, N)  # (J, N Y, N U)
    eyeN = jnp.eye(N, dtype=dt)
    Q2 = 2.0 * jnp.einsum("kl,jab->jkalb", eyeN, Qp).reshape(J, N * Y, N * Y)
    Qs = small_cholesky(2.0 * Qp)  # 2 Q_j = Qs Qs', Q_j positive semidefinite (validated)
    Qh = jnp.einsum("kl,jab->jkalb", eyeN, Qs).reshape(J, N * Y, N * Y)
    QYu = Q2 @ Yu
    H = None
    if with_H:
        H = jnp.swapaxes(Yu, 1, 2) @ QYu + block_diag(BH, N)
        H = 0.5 * (H + jnp.swapaxes(H, 1, 2))
    E = jnp.einsum("jam,ja->jm", QYu, free)
    return PaddedCosts(Yu, Q2, Qh, BH, H, E, data.A, Bj, Qx)


def unpad_matrix(M: Any, n_u: int, U: int, horizon: int) -> Any:
    M = M.reshape(horizon, U, horizon, U)[:, :n_u, :, :n_u]
    return M.reshape(horizon * n_u, horizon * n_u)


# Jitted (the topology static): eagerly (:func:`singular_hessians`, ``ampc solve``'s
# checks) one compiled program instead of about 60 single operations, each compiled
# alone (2 s of ``ampc solve``'s start, ``bench/bench_compile.py``).
@partial(jax.jit, static_argnums=0)
def local_costs(topology: Topology, data: ProblemData) -> tuple[tuple, tuple]:
    """(H_j, E_j) for every objective (eq.F3_primal_1, paper-notes items 8, 18, 19)."""
    lay = padded_layout(topology)
    U = lay.cols.shape[1]
    N = topology.horizon
    c = padded_costs(topology, data)
    H, E = c.H, c.E
    Hs = tuple(unpad_matrix(H[j], n, U, N) for j, n in enumerate(lay.u_sizes))
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
