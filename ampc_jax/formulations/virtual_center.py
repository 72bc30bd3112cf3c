"""Formulation 2, Virtual Center Node (eq.ConsensusADMM_F2 to eq.F2_dual).

The local QPs carry only the objectives' tracking costs (eq.F2_primal), with
the same inequality rows as Formulation 1; the input weights act in the
global step, Z_(i) = (2 R_(i) + sum_j rho_j I)^-1 sum_j (gamma_j(i) + rho_j U_j(i))
(eq.F2_dual with paper-notes items 5, 7 and 14). The machinery is
:class:`~ampc_jax.formulations.consensus.ConsensusADMM`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..admm.core import FormulationInfo
from .consensus import ConsensusADMM

__all__ = ["VirtualCenter"]


@dataclass(frozen=True)
class VirtualCenter(ConsensusADMM):
    """Formulation 2, Virtual Center Node: consensus ADMM with the input weights in
    the global step. Options and parameters: :class:`ConsensusADMM`."""

    info = FormulationInfo(
        name="virtual_center",
        title="Virtual Center Node (Formulation 2)",
        label="Virtual Center Node",
        rho="objective",
        rho_basis="hessian",
        decomposed=True,
        closed_loop=True,
    )
    center = True
