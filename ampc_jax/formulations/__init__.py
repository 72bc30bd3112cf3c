"""The paper's formulations, each an :class:`~ampc_jax.admm.core.ADMMSolver`
that declares what it is (``info``), registered by name (:mod:`.registry`).

* ``"local_explicit"`` -- Formulation 3, Local Explicit (:class:`LocalExplicit`);
* ``"fully_distributed"`` -- Formulation 1, Fully Distributed (:class:`FullyDistributed`);
* ``"virtual_center"`` -- Formulation 2, Virtual Center Node (:class:`VirtualCenter`);
* ``"integrated"`` -- the integrated MPC by the same explicit ADMM
  (:class:`IntegratedADMM`), what the decomposed ones are compared with.

A new formulation is one file with its class (its ``info`` declared) and one
``register_formulation`` line below.
"""

from __future__ import annotations

from ..admm.core import ADMMSolver, FormulationInfo
from .consensus import ConsensusADMM, ConsensusSetup, ConsensusState
from .fully_distributed import FullyDistributed
from .integrated import IntegratedADMM
from .local_explicit import PAPER_ITERATION, LocalExplicit, LocalSetup
from .registry import (
    DEFAULT_FORMULATION,
    FORMULATIONS,
    check_formulation,
    formulation,
    formulation_info,
    formulation_names,
    formulation_options,
    register_formulation,
    unregister_formulation,
)
from .virtual_center import VirtualCenter

Formulation = ADMMSolver
"""The type of every formulation: the core protocol (:class:`~ampc_jax.admm.core.ADMMSolver`)."""

__all__ = [
    "DEFAULT_FORMULATION",
    "FORMULATIONS",
    "ConsensusADMM",
    "ConsensusSetup",
    "ConsensusState",
    "Formulation",
    "FormulationInfo",
    "FullyDistributed",
    "IntegratedADMM",
    "LocalExplicit",
    "PAPER_ITERATION",
    "LocalSetup",
    "VirtualCenter",
    "check_formulation",
    "formulation",
    "formulation_info",
    "formulation_names",
    "formulation_options",
    "register_formulation",
    "unregister_formulation",
]

register_formulation(LocalExplicit)
register_formulation(FullyDistributed)
register_formulation(VirtualCenter)
register_formulation(IntegratedADMM)
