"""The integrated MPC (eq.integMPC), JAX-native: explicit ADMM on the undecomposed problem.

The same machinery as Local Explicit applied to the merged problem (one
objective that stacks every C_j, Q_j and reference and owns all agents:
:func:`~ampc_jax.problem.merged_topology`), so time ratios (eq.t_ratio)
compare like with like on the same stack. The reference optimum from an
established solver is :func:`ampc_jax.reference.solve_reference`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

from ..admm.core import ADMMSolver, FormulationInfo
from ..admm.params import SolverParams
from ..admm.rho import RHO_STEPS
from ..admm.state import ADMMState
from ..problem.condensed import merged_data, merged_topology
from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import SolveResult
from .local_explicit import LocalExplicit, LocalSetup

__all__ = ["IntegratedADMM"]


@dataclass(frozen=True)
class IntegratedADMM(ADMMSolver):
    """JAX-native integrated MPC: the static options of :class:`LocalExplicit`
    (there: their meaning and defaults) on the merged problem.

    It implements the core protocol itself (:class:`~ampc_jax.admm.core.ADMMSolver`):
    :meth:`setup` merges the objectives of the data it is given
    (:func:`~ampc_jax.problem.merged_data`) and factorises as Local Explicit
    does on the merged topology (:attr:`merged`); the state, the step and the
    result are that Local Explicit's. ``params.rho`` has one entry (one
    objective): by default a factor on eq.opt_ro's rho* of the whole problem.
    ``max_iter`` defaults to 2000; ``rho_method`` (default ``"carried"``) and
    ``finish`` (default ``"active_set"``, the exact finish; ``"none"``: ADMM
    alone) as Local Explicit's.
    """

    info = FormulationInfo(
        name="integrated",
        title="the integrated MPC (ADMM)",
        label="integrated MPC (ADMM)",
        rho="one",
        rho_basis="opt_ro",
        decomposed=False,
        batch_kkt="riccati",
        closed_loop=True,
    )

    topology: Topology
    max_iter: int = 2000
    anderson: int = 0
    kkt: str = "auto"
    rho_method: str = "carried"
    rho_iterations: int = RHO_STEPS
    dual_residual: str = "slack"
    finish: str = "active_set"

    def __post_init__(self) -> None:
        _ = self.merged  # validates the options

    @functools.cached_property
    def merged(self) -> LocalExplicit:
        """Local Explicit on the merged (one-objective) topology."""
        return LocalExplicit(
            merged_topology(self.topology),
            max_iter=self.max_iter,
            anderson=self.anderson,
            kkt=self.kkt,
            rho_method=self.rho_method,
            rho_iterations=self.rho_iterations,
            dual_residual=self.dual_residual,
            finish=self.finish,
        )

    @property
    def n_rho(self) -> int:
        return 1

    def setup(self, data: ProblemData, params: SolverParams | None = None) -> LocalSetup:
        """The merged problem's setup: ``data``'s objectives stacked into one, then
        :meth:`LocalExplicit.setup`."""
        return self.merged.setup(merged_data(data), params)

    def setup_from(
        self, data: ProblemData, params: SolverParams | None, warm: ADMMState | None
    ) -> LocalSetup:
        """:meth:`setup` with the rho* ``warm`` carries (``rho_method="carried"``)."""
        return self.merged.setup_from(merged_data(data), params, warm)

    @property
    def finish_every(self) -> int:  # type: ignore[override]
        return self.merged.finish_every

    @property
    def finish_first(self) -> int:  # type: ignore[override]
        return self.merged.finish_first

    def finisher(self, setup: LocalSetup) -> Any:
        """The merged Local Explicit's exact finish (``finish``; None for ``"none"``)."""
        return self.merged.finisher(setup)

    def init(self, setup: LocalSetup, warm: ADMMState | None = None) -> ADMMState:
        return self.merged.init(setup, warm)

    def step(self, setup: LocalSetup, state: ADMMState) -> ADMMState:
        return self.merged.step(setup, state)

    def converged(self, setup: LocalSetup, state: ADMMState) -> Any:
        return self.merged.converged(setup, state)

    def result(self, setup: LocalSetup, state: ADMMState) -> SolveResult:
        return self.merged.result(setup, state)

    def point(self, state: ADMMState) -> Any:
        return self.merged.point(state)

    def at(self, x: Any, state: ADMMState) -> ADMMState:
        return self.merged.at(x, state)

    def cold_state(self, dtype: Any = None) -> ADMMState:
        return self.merged.cold_state(dtype)

    def shift(self, state: ADMMState, steps: int = 1) -> ADMMState:
        return self.merged.shift(state, steps)
