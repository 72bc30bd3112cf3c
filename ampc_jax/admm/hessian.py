"""Each objective's local Hessian H_j as an operator: applied, and inverted.

H_j = Y_u,j' 2Qbar_j Y_u,j + I (x) BH_j (:mod:`~.costs`) is needed beyond the
KKT solve of the local step: eq.opt_ro's power iteration applies H_j and
H_j^-1 (:mod:`~.rho`), and the duality gap of a result evaluates the local
costs and their conjugates (:mod:`~.stopping`). Three forms behind one
interface (``apply``, ``solve``, ``pencil_rho``), each made once per control
step by its KKT strategy (:meth:`~.kkt.DenseKKT.hessian`, ...), so a formulation
never branches on how H_j is held:

* :class:`DenseHessian` -- H_j formed and inverted (n x n);
* :class:`WoodburyHessian` -- the low-rank form: H_j applied as
  ``I (x) BH + Y_u' Q2 Y_u``, H_j^-1 by the Woodbury identity, O(n r);
* :class:`RiccatiHessian` -- no condensed matrix: H_j applied by sweeps of the
  model, H_j^-1 by the Riccati recursion (:mod:`~.riccati`).

H_j may be singular (R_j = 0 and Q_j blind to some input direction): every
form inverts H_j + delta I with delta = eps * trace(H_j) / n_j, which keeps the
inverse finite and the smallest eigenvalue at about the eps * lambda_max floor.
All operate on stacked right-hand sides x of shape (J, p, n).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp

from . import riccati
from .costs import PaddedCosts
from .layout import padded_layout
from .linalg import apply_blocks, spd_inverse_dense, woodbury_parts
from .rho import power_rho, power_rho_riccati, power_rho_woodbury

__all__ = [
    "DenseHessian",
    "RiccatiHessian",
    "WoodburyHessian",
    "dense_hessian",
    "riccati_hessian",
    "woodbury_hessian",
]


def _shift(c: PaddedCosts, gram: Any, horizon: int, layout: Any) -> Any:
    """(J, 1, 1) delta = eps * trace(H_j) / n_j; ``gram`` = trace(Y_u' 2Qbar Y_u)."""
    dt = c.E.dtype
    nj = jnp.asarray([horizon * u for u in layout.u_sizes], dt)
    um = jnp.asarray(layout.umask, dt)
    tr = gram + horizon * jnp.einsum("jaa,ja->j", c.BH, um)
    return (jnp.finfo(dt).eps * tr / nj)[:, None, None]


class DenseHessian(NamedTuple):
    """H (J, n, n) formed; Hinv (J, n, n) = (H + delta I)^-1."""

    H: Any
    Hinv: Any

    def apply(self, x: Any) -> Any:
        """H_j x_j for x (J, p, n)."""
        return jnp.einsum("jab,jpb->jpa", self.H, x)

    def solve(self, x: Any) -> Any:
        """(H_j + delta I)^-1 x_j for x (J, p, n)."""
        return jnp.einsum("jab,jpb->jpa", self.Hinv, x)

    def pencil_rho(self, LamB: Any, mask: Any, iterations: int) -> Any:
        """eq.opt_ro's rho_j* by power iteration on the pencil (H_j, Lambda_j)."""
        return power_rho(self.H, self.Hinv, LamB, mask, iterations)


class WoodburyHessian(NamedTuple):
    """H_j = Y_u' Q2 Y_u + I (x) BH (BH shifted by delta) and the Woodbury parts of
    its inverse, (B^-1, W, P) (:func:`~.linalg.woodbury_parts`)."""

    Yu: Any
    Q2: Any
    BH: Any
    Binv: Any
    W: Any
    P: Any

    def apply(self, x: Any) -> Any:
        """H_j x_j for x (J, p, n), O(n r)."""
        return apply_blocks(self.BH, x) + _lowrank(self.Yu, self.Q2, self.Yu, x)

    def solve(self, x: Any) -> Any:
        """H_j^-1 x_j for x (J, p, n), O(n r)."""
        return apply_blocks(self.Binv, x) - _lowrank(self.W, self.P, self.W, x)

    def pencil_rho(self, LamB: Any, mask: Any, iterations: int) -> Any:
        return power_rho_woodbury(self, LamB, mask, iterations)


class RiccatiHessian(NamedTuple):
    """H_j by sweeps of the model: A, Bu, Qx as in :class:`~.costs.PaddedCosts`,
    BH (shifted by delta), and the Riccati factor of H_j (no rho term)."""

    A: Any
    Bu: Any
    Qx: Any
    BH: Any
    factor: Any

    def apply(self, x: Any) -> Any:
        """H_j x_j for x (J, p, n): a forward and an adjoint sweep."""
        return riccati.hessian_apply(self.A, self.Bu, self.Qx, self.BH, x)

    def solve(self, x: Any) -> Any:
        """H_j^-1 x_j for x (J, p, n): the Riccati solve."""
        return riccati.solve(self.factor, x)

    def pencil_rho(self, LamB: Any, mask: Any, iterations: int) -> Any:
        return power_rho_riccati(self, LamB, mask, iterations)


def _lowrank(L: Any, Mid: Any, R: Any, x: Any) -> Any:
    """L' Mid R x per objective, for x (J, p, n)."""
    y = jnp.einsum("jsn,jpn->jps", R, x)
    y = jnp.einsum("jst,jpt->jps", Mid, y)
    return jnp.einsum("jsn,jps->jpn", L, y)


def dense_hessian(c: PaddedCosts, topology: Any) -> DenseHessian:
    """From the formed H (``c.H``, condensed costs)."""
    lay = padded_layout(topology)
    N = topology.horizon
    gram = jnp.sum(c.Yu * (c.Q2 @ c.Yu), axis=(1, 2))
    delta = _shift(c, gram, N, lay)
    n = c.H.shape[-1]
    return DenseHessian(c.H, spd_inverse_dense(c.H + delta * jnp.eye(n, dtype=c.H.dtype)))


def woodbury_hessian(c: PaddedCosts, topology: Any) -> WoodburyHessian:
    """From the condensed costs' Y_u, Q2 and its factor Qh (no n x n matrix formed)."""
    lay = padded_layout(topology)
    N = topology.horizon
    U = c.BH.shape[-1]
    gram = jnp.sum(c.Yu * (c.Q2 @ c.Yu), axis=(1, 2))
    BH = c.BH + _shift(c, gram, N, lay) * jnp.eye(U, dtype=c.BH.dtype)
    Binv, W, P = woodbury_parts(c.Yu, c.Qh, BH, N)
    return WoodburyHessian(c.Yu, c.Q2, BH, Binv, W, P)


def riccati_hessian(c: PaddedCosts, topology: Any) -> RiccatiHessian:
    """From the stage form (``c.A``, ``c.Bu``, ``c.Qx``; no condensed matrices)."""
    lay = padded_layout(topology)
    N = topology.horizon
    U = c.BH.shape[-1]
    gram = riccati.trace_gram(c.A, c.Bu, c.Qx, N)
    BH = c.BH + _shift(c, gram, N, lay) * jnp.eye(U, dtype=c.BH.dtype)
    return RiccatiHessian(c.A, c.Bu, c.Qx, BH, riccati.factor(c.A, c.Bu, c.Qx, BH, N))
