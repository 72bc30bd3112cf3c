"""The paper's formulations, all behind one protocol (:class:`Formulation`).

* ``"local_explicit"`` -- Formulation 3, Local Explicit (:class:`LocalExplicit`);
* ``"integrated"`` -- the integrated MPC by the same explicit ADMM
  (:class:`IntegratedADMM`), what the decomposed ones are compared with.

Formulations 1 (Fully Distributed) and 2 (Virtual Center Node) are not built
yet; :func:`formulation` refuses their names with a message saying so.
"""

from __future__ import annotations

from typing import Any

from ..problem.topology import Topology
from .base import Formulation
from .integrated import IntegratedADMM
from .local_explicit import LocalExplicit, LocalSetup

__all__ = [
    "FORMULATIONS",
    "Formulation",
    "IntegratedADMM",
    "LocalExplicit",
    "LocalSetup",
    "formulation",
]

FORMULATIONS: dict[str, type] = {"local_explicit": LocalExplicit, "integrated": IntegratedADMM}
"""Name -> formulation class."""

_PLANNED = ("fully_distributed", "virtual_center")


def formulation(name: str, topology: Topology, **options: Any) -> Formulation:
    """The formulation ``name`` for ``topology`` with its static ``options``
    (ValueError naming ``formulation`` for an unknown name)."""
    if name in _PLANNED:
        raise ValueError(
            f"formulation: {name!r} (the paper's Formulation "
            f"{1 if name == 'fully_distributed' else 2}) is not implemented yet; "
            f"expected one of {sorted(FORMULATIONS)}"
        )
    if name not in FORMULATIONS:
        raise ValueError(f"formulation: expected one of {sorted(FORMULATIONS)}, got {name!r}")
    return FORMULATIONS[name](topology, **options)
