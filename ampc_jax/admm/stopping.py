"""The stopping rule (eq.Convergence): which dual residual is tested.

eq.Convergence tests, per objective, ||r_j||^2 <= eps_r and ||s_j||^2 <= eps_s.
What s_j is comes in two forms, strategies behind one interface (``dual``)
chosen by name at construction (``dual_residual``; :func:`select_dual_residual`):

* :class:`ChangeResidual` (``"slack"`` in Local Explicit, ``"change"`` in
  Formulations 1 and 2; the default) -- the change of the global variable
  between iterations, Z_j^q - Z_j^(q-1), in its own units;
* :class:`PaperResidual` (``"paper"``) -- rho_j (Z_j^q - Z_j^(q-1)), as printed.
  It scales with rho_j, and eq.opt_ro gives rho_j ~ 1e-6 when the weights are
  per Nm^2 (the vehicle examples): a fixed eps_s is then met while Z still
  moves by newtons.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["DUAL_RESIDUALS", "ChangeResidual", "PaperResidual", "select_dual_residual"]


@dataclass(frozen=True)
class ChangeResidual:
    """s_j = Z_j^q - Z_j^(q-1): the global variable's change, in its own units."""

    name: str = "slack"

    def dual(self, rho: Any, dz: Any) -> Any:
        """The tested dual residual from the change ``dz`` (J, ...) and rho (J, 1, 1)."""
        return dz


@dataclass(frozen=True)
class PaperResidual:
    """s_j = rho_j (Z_j^q - Z_j^(q-1)), eq.Convergence as printed."""

    name: str = "paper"

    def dual(self, rho: Any, dz: Any) -> Any:
        return rho * dz


DUAL_RESIDUALS: dict[str, Any] = {
    "slack": ChangeResidual("slack"),
    "change": ChangeResidual("change"),
    "paper": PaperResidual(),
}
"""``dual_residual`` name -> strategy (a formulation accepts some of them)."""


def select_dual_residual(name: str, allowed: tuple[str, ...]) -> Any:
    """The dual-residual strategy ``name`` among ``allowed``, or a ValueError
    naming ``dual_residual``."""
    if name not in allowed:
        raise ValueError(f"dual_residual: expected one of {allowed}, got {name!r}")
    return DUAL_RESIDUALS[name]
