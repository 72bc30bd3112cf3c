"""The integrated MPC (eq.integMPC), JAX-native: explicit ADMM on the undecomposed problem.

The same machinery as Local Explicit applied to the merged problem (one
objective that stacks every C_j, Q_j and reference and owns all agents:
:func:`~ampc_jax.problem.merged_topology`), so time ratios (eq.t_ratio)
compare like with like on the same stack. The reference optimum from an
established solver is :func:`ampc_jax.reference.solve_reference`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..admm.params import DEFAULT_TOL, SolverParams
from ..admm.state import ADMMState, cold_state, shift_state
from ..problem.condensed import merged_data, merged_topology
from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import SolveResult
from .local_explicit import LocalExplicit

__all__ = ["IntegratedADMM"]


@dataclass(frozen=True)
class IntegratedADMM:
    """JAX-native integrated MPC: the static options of :class:`LocalExplicit`
    (there: their meaning and defaults) on the merged problem.

    ``params.rho`` has one entry (one objective): by default a factor on
    eq.opt_ro's rho* of the whole problem. ``max_iter`` defaults to 2000.
    """

    topology: Topology
    max_iter: int = 2000
    anderson: int = 0
    kkt: str = "auto"
    rho_method: str = "power"
    rho_iterations: int = 8
    dual_residual: str = "slack"

    def __post_init__(self) -> None:
        _ = self.inner  # validates the options

    @property
    def inner(self) -> LocalExplicit:
        """Local Explicit on the merged (one-objective) topology."""
        return LocalExplicit(
            merged_topology(self.topology),
            max_iter=self.max_iter,
            anderson=self.anderson,
            kkt=self.kkt,
            rho_method=self.rho_method,
            rho_iterations=self.rho_iterations,
            dual_residual=self.dual_residual,
        )

    @property
    def n_rho(self) -> int:
        return 1

    def params(
        self,
        rho: Any = 1.0,
        relaxation: Any = 1.0,
        tol_primal: Any = DEFAULT_TOL,
        tol_dual: Any = DEFAULT_TOL,
        dtype: Any = None,
    ) -> SolverParams:
        """:meth:`LocalExplicit.params` with one rho."""
        return self.inner.params(rho, relaxation, tol_primal, tol_dual, dtype)

    def cold_state(self, dtype: Any = None) -> ADMMState:
        return cold_state(merged_topology(self.topology), dtype)

    @staticmethod
    def shift(state: ADMMState, steps: int = 1) -> ADMMState:
        return shift_state(state, steps)

    def solve(
        self, data: ProblemData, params: SolverParams | None = None, warm: Any = None
    ) -> SolveResult:
        return self.inner.solve(merged_data(data), params, warm)

    def solve_fixed(
        self,
        data: ProblemData,
        iterations: int,
        params: SolverParams | None = None,
        warm: Any = None,
    ) -> SolveResult:
        return self.inner.solve_fixed(merged_data(data), iterations, params, warm)
