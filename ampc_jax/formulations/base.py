"""The protocol every formulation follows, so the closed loop, sweeps and tuning
take any of them by name (:data:`ampc_jax.formulations.FORMULATIONS`).

:class:`Formulation` is what a caller of a solve uses. Every formulation here
is also an :class:`~ampc_jax.admm.core.ADMMSolver`: the core protocol (setup,
init, step, converged, result, point / at) that its runners, the sweep
engine and the tuning loss iterate through."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from ..admm.params import SolverParams
from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import SolveResult

__all__ = ["Formulation"]


@runtime_checkable
class Formulation(Protocol):
    """An MPC solver for one :class:`Topology`: static options as fields,
    tunable numbers as the :class:`SolverParams` argument.

    * ``params(...)`` -- validated parameters (rho per ``n_rho``, relaxation,
      tolerances);
    * ``solve(data, params, warm)`` -- to tolerance (``while_loop``), jittable,
      vmappable over data and params together;
    * ``solve_fixed(data, iterations, params, warm)`` -- a fixed iteration
      count (``scan``), differentiable with respect to data and params;
    * ``cold_state(dtype)`` and ``shift(state, steps)`` -- the warm start story.
    """

    topology: Topology
    max_iter: int

    @property
    def n_rho(self) -> int: ...

    def params(self, *args: Any, **kwargs: Any) -> SolverParams: ...

    def cold_state(self, dtype: Any = None) -> Any: ...

    def shift(self, state: Any, steps: int = 1) -> Any: ...

    def solve(
        self, data: ProblemData, params: SolverParams | None = None, warm: Any = None
    ) -> SolveResult: ...

    def solve_fixed(
        self,
        data: ProblemData,
        iterations: int,
        params: SolverParams | None = None,
        warm: Any = None,
    ) -> SolveResult: ...
