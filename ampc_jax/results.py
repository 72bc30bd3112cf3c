"""Result type shared by every formulation and reference solver."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

__all__ = ["STATUS", "USABLE_STATUS", "SolveResult", "status_name"]

#: Status codes carried by :class:`SolveResult` (an int inside jit).
STATUS = {
    0: "solved",
    1: "max_iter_reached",
    2: "numerical_error",
    3: "infeasible",
    4: "solver_error",
    5: "solved_inaccurate",  # reference solvers only: Clarabel AlmostSolved, OSQP inaccurate
}

#: Codes whose inputs are a solution (exact, at the iteration cap, or inaccurate).
USABLE_STATUS = (0, 1, 5)


def status_name(code: Any) -> str:
    """Readable name of a status code."""
    return STATUS.get(int(code), f"unknown({int(code)})")


class SolveResult(NamedTuple):
    """Outcome of one MPC solve (a pytree; batched results carry a leading axis).

    Attributes
    ----------
    u : (N_p, n_u) inputs over the horizon, agent columns in topology order.
        For the ADMM formulations this is the average of the objectives' copies
        of each agent, projected onto the agent's bounds.
    iterations : number of iterations run.
    converged : whether the stopping rule (eq.Convergence) held.
    status : see :data:`STATUS`.
    primal_residual, dual_residual : (n_obj,) squared residual norms per
        objective, ||r_j||^2 and ||s_j||^2 (eq.Convergence; NOTES item 17).
    rho : (n_obj,) penalty parameters used.
    state : the final solver state (for warm starts), or ``None``.
    certificate : for a solve to tolerance that did not converge, the
        evidence of primal infeasibility
        (:class:`~ampc_jax.admm.feasibility.Certificate`; status 3 when found),
        else ``None``.
    """

    u: Any
    iterations: Any
    converged: Any
    status: Any
    primal_residual: Any
    dual_residual: Any
    rho: Any
    state: Any = None
    certificate: Any = None

    @property
    def u0(self) -> Any:
        """(n_u,) first-step inputs U^(0), the ones applied."""
        return self.u[..., 0, :]

    def per_agent(self, topology: Any, first_step: bool = False) -> dict[str, np.ndarray]:
        """Inputs split by agent name (numpy)."""
        u = np.asarray(self.u0 if first_step else self.u)
        o = topology.agent_offsets
        return {name: u[..., o[i] : o[i + 1]] for i, name in enumerate(topology.agent_names)}
