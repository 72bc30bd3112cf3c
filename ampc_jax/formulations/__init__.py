"""The paper's formulations, all behind one protocol (:class:`Formulation`).

* ``"local_explicit"`` -- Formulation 3, Local Explicit (:class:`LocalExplicit`);
* ``"fully_distributed"`` -- Formulation 1, Fully Distributed (:class:`FullyDistributed`);
* ``"virtual_center"`` -- Formulation 2, Virtual Center Node (:class:`VirtualCenter`);
* ``"integrated"`` -- the integrated MPC by the same explicit ADMM
  (:class:`IntegratedADMM`), what the decomposed ones are compared with.
"""

from __future__ import annotations

from typing import Any

from ..problem.topology import Topology
from .base import Formulation
from .consensus import ConsensusADMM, ConsensusSetup, ConsensusState
from .fully_distributed import FullyDistributed
from .integrated import IntegratedADMM
from .local_explicit import LocalExplicit, LocalSetup
from .virtual_center import VirtualCenter

__all__ = [
    "FORMULATIONS",
    "ConsensusADMM",
    "ConsensusSetup",
    "ConsensusState",
    "Formulation",
    "FullyDistributed",
    "IntegratedADMM",
    "LocalExplicit",
    "LocalSetup",
    "VirtualCenter",
    "formulation",
]

FORMULATIONS: dict[str, type] = {
    "local_explicit": LocalExplicit,
    "fully_distributed": FullyDistributed,
    "virtual_center": VirtualCenter,
    "integrated": IntegratedADMM,
}
"""Name -> formulation class."""


def formulation(name: str, topology: Topology, **options: Any) -> Formulation:
    """The formulation ``name`` for ``topology`` with its static ``options``
    (ValueError naming ``formulation`` for an unknown name)."""
    if name not in FORMULATIONS:
        raise ValueError(f"formulation: expected one of {sorted(FORMULATIONS)}, got {name!r}")
    return FORMULATIONS[name](topology, **options)
