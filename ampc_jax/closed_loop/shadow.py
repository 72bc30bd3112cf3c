"""The integrated MPC in shadow: an observer of the controller's problem, for e_sub.

At every step the integrated MPC (eq.integMPC, :class:`~ampc_jax.formulations.IntegratedADMM`)
solves the controller's own :class:`~ampc_jax.problem.ProblemData` at a tight
tolerance, warm started from its own previous step, so the suboptimality of
eq.suboptimality, ``e_sub = |U_distributed^(0) - U_integrated^(0)|`` (Nm per
agent input), can be logged. It never acts on the vehicle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ..admm.params import SolverParams
from ..admm.state import ADMMState
from ..formulations import PAPER_ITERATION, IntegratedADMM
from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import usable
from .config import SimConfig

__all__ = ["IntegratedShadow", "ShadowInfo", "shadow_for"]


class ShadowInfo(NamedTuple):
    u0: Any  # (n_u,) the integrated optimum's first-step inputs (topology's inputs)
    iterations: Any  # () int32
    status: Any  # () int32


@dataclass(frozen=True)
class IntegratedShadow:
    """The shadow integrated MPC of one controller topology (static).

    ``max_iter`` (default 5000) caps it; ``warm_shift`` builds its warm start
    as the controller's does. It runs the paper's iteration
    (:data:`~ampc_jax.formulations.PAPER_ITERATION`: no exact finish, eq.opt_ro
    at every step) to its tolerance, the reference of the reproduction's e_sub
    figures (docs/results.md).
    """

    topology: Topology
    max_iter: int = 5000
    warm_shift: int = 1

    @property
    def solver(self) -> IntegratedADMM:
        return IntegratedADMM(self.topology, max_iter=self.max_iter, **PAPER_ITERATION)

    def init(self, dtype: Any = None) -> ADMMState:
        return self.solver.cold_state(dtype)

    def observe(
        self, state: ADMMState, params: SolverParams, data: ProblemData
    ) -> tuple[ADMMState, ShadowInfo]:
        """Solve ``data`` to the shadow's tolerance; the next warm state and what it found."""
        solver = self.solver
        sh = solver.solve(data, params, state)
        ok = usable(sh.status) & jnp.all(jnp.isfinite(sh.u0))
        cold = solver.cold_state(jnp.result_type(data.A))
        nxt = jax.tree.map(
            lambda a, b: jnp.where(ok, a, b), solver.shift(sh.state, self.warm_shift), cold
        )
        return nxt, ShadowInfo(sh.u0, sh.iterations, sh.status)


def shadow_for(config: SimConfig, topology: Topology) -> IntegratedShadow | None:
    """The shadow of ``config`` on its controller's ``topology`` (cap
    ``shadow_max_iter``, the controller's warm shift), or None without one."""
    if not config.shadow:
        return None
    return IntegratedShadow(topology, config.shadow_max_iter, config.warm_shift)
