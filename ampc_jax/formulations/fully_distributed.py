"""Formulation 1, Fully Distributed (eq.F1_obj to eq.F1_dual).

Every objective's local QP carries its tracking cost and its agents' input
weights shared out as R_(i) / m_(i) (eq.F1_obj, paper-notes item 8), with the
inequality rows that involve its agents (eq.F1_primal, eq.F1_1); the global
step is the rho-weighted average of the copies (eq.F1_dual, paper-notes item 14).
The machinery is :class:`~ampc_jax.formulations.consensus.ConsensusADMM`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..admm.core import FormulationInfo
from .consensus import ConsensusADMM

__all__ = ["FullyDistributed"]


@dataclass(frozen=True)
class FullyDistributed(ConsensusADMM):
    """Formulation 1, Fully Distributed: consensus ADMM with the input weights in
    the local QPs. Options and parameters: :class:`ConsensusADMM`."""

    info = FormulationInfo(
        name="fully_distributed",
        title="Fully Distributed (Formulation 1)",
        label="Fully Distributed",
        rho="objective",
        rho_basis="hessian",
        decomposed=True,
        closed_loop=True,
    )
    center = False
