"""The KKT solve of the local step: K_j^-1 applied, K_j = H_j + rho_j Abar_j' Abar_j.

Local Explicit's primal update (eq.F3_primal) solves with K_j at every
iteration; the setup factorises K_j once per control step and an iteration
only applies the factors. Three strategies behind one interface
(``factor``, ``apply``), chosen per topology by :func:`select_kkt`:

* :class:`DenseKKT` -- K_j formed and inverted (n = N_p n_u,j square). The
  cheaper one when an objective has about as many outputs as inputs (the
  stability example: two outputs, three inputs);
* :class:`WoodburyKKT` ``(factored=False)`` -- K_j^-1 formed through the
  Woodbury identity over the N_p n_y,j outputs (:func:`~.linalg.woodbury_parts`):
  only U x U and r x r systems are factorised. For r = n / 2 (the merged
  cruise problem: two outputs, four inputs) formed beats factored by 1 us;
* :class:`WoodburyKKT` ``(factored=True)`` -- the Woodbury parts kept, O(n r)
  per iteration and no O(n^2 r) forming: the cheaper one for r < n / 2 (the
  cruise example: one output, three or four inputs;
  ``bench/bench_local_explicit.py`` and ``bench/bench_batched_layout.py``);
* :class:`RiccatiKKT` -- no condensed matrix at all: K_j^-1 applied by the
  backward Riccati recursion over the horizon and a backward and a forward
  sweep per right-hand side (:mod:`~.riccati`), O(N_p (n_x^3 + U^3)) to
  factorise against O((N_p U)^3), and the costs E_j built by sweeps of the
  model instead of Y_u,j. Valid because every constraint row acts on one
  step's inputs (Abar_j = I (x) A_in,j).

Each strategy says whether it needs the condensed form (``condensed``: Y_u,j
built by :func:`~.costs.padded_costs`) and the formed H_j (``forms_H``), and
makes the local Hessian in its own form (``hessian``: a
:class:`~.hessian.DenseHessian`, :class:`~.hessian.WoodburyHessian` or
:class:`~.hessian.RiccatiHessian`), which eq.opt_ro's power iteration and the
duality gap apply and invert.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp

from ..problem.topology import Topology
from . import riccati
from .costs import PaddedCosts
from .hessian import dense_hessian, riccati_hessian, woodbury_hessian
from .layout import padded_layout
from .linalg import block_diag, spd_inverse_dense, woodbury_inverse, woodbury_parts

__all__ = ["KKT", "KKT_SOLVES", "DenseKKT", "RiccatiKKT", "WoodburyKKT", "select_kkt"]

KKT_SOLVES = ("auto", "dense", "woodbury", "woodbury_factored", "riccati")
"""Names :func:`select_kkt` accepts."""


@dataclass(frozen=True)
class DenseKKT:
    """K_j formed and inverted: ``K^-1 = (H + I (x) rho A_in'A_in)^-1``, applied as a product."""

    name: str = "dense"
    woodbury: bool = False  # H_j^-1 for eq.opt_ro: from the formed H_j
    condensed: bool = True
    forms_H: bool = True

    def hessian(self, c: PaddedCosts, topology: Topology) -> Any:
        """H_j formed and inverted (:class:`~.hessian.DenseHessian`)."""
        return dense_hessian(c, topology)

    def factor(self, c: PaddedCosts, rho_AtA: Any, horizon: int) -> Any:
        """(J, n, n) K_j^-1 from the costs (H formed) and the per-step rho_j A_in,j'A_in,j."""
        return spd_inverse_dense(c.H + block_diag(rho_AtA, horizon))

    def apply(self, Kinv: Any, x: Any) -> Any:
        """K_j^-1 x_j for x (J, n)."""
        return jnp.einsum("jab,jb->ja", Kinv, x)


@dataclass(frozen=True)
class WoodburyKKT:
    """K_j^-1 = I (x) B^-1 - W' P W with B = 2 R_j / m + rho_j A_in,j'A_in,j per step.

    ``factored``: keep (B^-1, W, P W) and apply them (O(n r) per iteration);
    otherwise form K_j^-1 once (one n x n product per iteration).
    """

    factored: bool = True
    woodbury: bool = True  # H_j^-1 for eq.opt_ro: by the Woodbury identity too
    condensed: bool = True
    forms_H: bool = False

    def hessian(self, c: PaddedCosts, topology: Topology) -> Any:
        """H_j in the Woodbury form (:class:`~.hessian.WoodburyHessian`)."""
        return woodbury_hessian(c, topology)

    @property
    def name(self) -> str:
        return "woodbury_factored" if self.factored else "woodbury"

    def factor(self, c: PaddedCosts, rho_AtA: Any, horizon: int) -> Any:
        BK = c.BH + rho_AtA
        if not self.factored:
            return woodbury_inverse(c.Yu, c.Qh, BK, horizon)
        Binv, W, P = woodbury_parts(c.Yu, c.Qh, BK, horizon)
        return Binv, W, P @ W

    def apply(self, Kinv: Any, x: Any) -> Any:
        """K_j^-1 x_j. Factored: two (r x n) products and the per-step U x U
        block product as a broadcast sum, which XLA fuses with the work around
        it (0.52 -> 0.49 us per batched iteration at N_p = 10 against a dot)."""
        if not isinstance(Kinv, tuple):
            return jnp.einsum("jab,jb->ja", Kinv, x)
        Binv, W, PW = Kinv
        J, n = x.shape
        U = Binv.shape[-1]
        low = jnp.matmul(jnp.swapaxes(W, 1, 2), jnp.matmul(PW, x[..., None]))[..., 0]
        blk = jnp.sum(Binv[:, None] * x.reshape(J, n // U, 1, U), axis=-1).reshape(J, n)
        return blk - low


@dataclass(frozen=True)
class RiccatiKKT:
    """K_j^-1 by the Riccati recursion over the horizon (:mod:`~.riccati`): the
    factor is a :class:`~.riccati.RiccatiFactor`, an application one backward
    and one forward sweep (no condensed matrix formed)."""

    name: str = "riccati"
    woodbury: bool = False
    condensed: bool = False
    forms_H: bool = False

    def hessian(self, c: PaddedCosts, topology: Topology) -> Any:
        """H_j by sweeps of the model (:class:`~.hessian.RiccatiHessian`)."""
        return riccati_hessian(c, topology)

    def factor(self, c: PaddedCosts, rho_AtA: Any, horizon: int) -> Any:
        return riccati.factor(c.A, c.Bu, c.Qx, c.BH + rho_AtA, horizon)

    def apply(self, Kinv: Any, x: Any) -> Any:
        """K_j^-1 x_j for x (J, n)."""
        return riccati.solve(Kinv, x)


KKT = DenseKKT | WoodburyKKT | RiccatiKKT


def select_kkt(topology: Topology, name: str = "auto") -> KKT:
    """The KKT strategy ``name`` (one of :data:`KKT_SOLVES`) for ``topology``.

    ``"auto"``: Woodbury when every objective (padded) has at most half as
    many outputs as inputs per step (r <= n / 2), kept factored when fewer
    than half (r < n / 2); dense otherwise, and whenever some R_(i) is
    singular (``Topology.singular_r``: the Woodbury form inverts the per-step
    block 2 R_j / m + rho_j A_in,j'A_in,j, singular when the rows leave a null
    direction of R_j free, although K_j itself is positive definite).
    ValueError naming ``kkt`` for an unknown name or an impossible choice.
    """
    if name not in KKT_SOLVES:
        raise ValueError(f"kkt: expected one of {KKT_SOLVES}, got {name!r}")
    if name in ("woodbury", "woodbury_factored") and topology.singular_r:
        names = [topology.agent_names[i] for i in topology.singular_r]
        raise ValueError(
            f"kkt: {name!r} needs every R_(i) positive definite; singular for {names} "
            f"(use 'dense' or 'auto')"
        )
    if name == "dense":
        return DenseKKT()
    if name in ("woodbury", "woodbury_factored"):
        return WoodburyKKT(factored=name == "woodbury_factored")
    if name == "riccati":
        return RiccatiKKT()
    lay = padded_layout(topology)
    r, n = max(lay.y_sizes), lay.cols.shape[1]
    if 2 * r > n or topology.singular_r:
        return DenseKKT()
    return WoodburyKKT(factored=2 * r < n)
