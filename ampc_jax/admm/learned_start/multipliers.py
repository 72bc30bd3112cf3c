"""The multipliers that make given inputs a fixed point of Local Explicit's iteration
(what a learned ``"step"`` start builds its multipliers from, so that they need
not be learned)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ...problem.topology import Topology
from ..layout import padded_layout

__all__ = ["ACTIVE_REL", "kkt_multipliers"]

ACTIVE_REL = 1e-6
"""A row whose slack is within this fraction of (1 + |b_c|) is active for
:func:`kkt_multipliers` (an optimum meets its bounds to round-off)."""


def kkt_multipliers(
    topology: Topology, hessian: Any, E: Any, Ain: Any, u: Any, Z: Any, b: Any
) -> Any:
    """gamma (J, N_p, R): the multipliers that make ``u`` (N_p x n_u) a fixed point.

    At a fixed point every copy is U_j = P_j u, Z = b - Abar u on the rows, and
    each local step's stationarity (eq.F3_primal) reads Abar_j' gamma_j =
    -(H_j U_j + E_j); the consensus on the slack (eq.F3_dual) gives sum_j
    gamma_jc = 0 on every row c with Z_c > 0, while on an active row the sum,
    the integrated problem's multiplier lambda_c, is free (a row is active
    when Z_c <= :data:`ACTIVE_REL` (1 + |b_c|): an input clipped to its bound
    is exactly). These conditions leave the split of lambda_c between the
    objectives free, so the least-norm solution is taken, step by step (Abar_j
    = I_(N_p) (x) A_in,j), by regularised normal equations: a start at the
    optimum's u is a fixed point, whatever split the iterates would reach, and
    nothing about the multipliers has to be learned.

    ``hessian``: H_j as an operator (:mod:`ampc_jax.admm.hessian`); ``E``: (J, n)
    E_j; ``Ain``: (J, R, U) the per-step rows A_in,j in the padded layout
    (:mod:`ampc_jax.admm.layout`), as Local Explicit's setup holds them;
    ``Z``, ``b``: (N_p, n_c).
    """
    T = topology
    lay = padded_layout(T)
    J, U = lay.cols.shape
    N, n_c = T.horizon, T.n_c
    R = lay.rows.shape[1]
    dt = u.dtype
    uj = jnp.moveaxis(jnp.pad(u, ((0, 0), (0, 1)))[:, lay.cols], 1, 0)  # (J, N, U)
    g = hessian.apply(uj.reshape(J, -1)[:, None])[:, 0] + E
    g = jnp.moveaxis(g.reshape(J, N, U), 1, 0)  # (N, J, U)
    exists = jnp.asarray(lay.rows < n_c, dt)  # (J, R)
    Ain = Ain * exists[..., None]  # (J, R, U)
    A1 = jnp.einsum("jk,jra->jakr", jnp.eye(J, dtype=dt), Ain).reshape(J * U, J * R)
    S = jnp.asarray(lay.rows[None] == np.arange(n_c)[:, None, None], dt).reshape(n_c, J * R)
    reg = 1e3 * float(jnp.finfo(dt).eps)
    inactive = (Z > ACTIVE_REL * (1.0 + jnp.abs(b))).astype(dt)

    def one(gk: Any, ik: Any) -> Any:
        M = jnp.concatenate([A1, ik[:, None] * S])
        rhs = jnp.concatenate([-gk.ravel(), jnp.zeros((n_c,), dt)])
        MM = M @ M.T
        lam = reg * (jnp.trace(MM) / MM.shape[0] + jnp.finfo(dt).tiny)
        x = M.T @ jnp.linalg.solve(MM + lam * jnp.eye(MM.shape[0], dtype=dt), rhs)
        return x.reshape(J, R) * exists

    return jnp.moveaxis(jax.vmap(one)(g, inactive), 0, 1)
