"""Result type shared by every formulation and reference solver, and its statuses.

A status is a :class:`Status` (an ``IntEnum``: inside ``jit`` an int32 array
of its values). Which ones carry inputs one may apply is decided in one place,
:func:`usable`; every caller (the controller's fallback guard, the shadow, the
replay, ``ampc solve``, the references) asks it.
"""

from __future__ import annotations

import enum
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "STATUS",
    "USABLE",
    "USABLE_STATUS",
    "SolveResult",
    "SolveStats",
    "Status",
    "status_message",
    "status_name",
    "usable",
]


class Status(enum.IntEnum):
    """What a solve ended with (:attr:`SolveResult.status`)."""

    SOLVED = 0
    MAX_ITER_REACHED = 1
    NUMERICAL_ERROR = 2
    INFEASIBLE = 3
    SOLVER_ERROR = 4
    SOLVED_INACCURATE = 5

    @property
    def label(self) -> str:
        """The name printed and written to files (``"max_iter_reached"``)."""
        return self.name.lower()

    @property
    def message(self) -> str:
        """One sentence on what the status means for the inputs returned."""
        return _MESSAGES[self]


_MESSAGES = {
    Status.SOLVED: (
        "the stopping rule held (eq.Convergence); stats.gap bounds how far the inputs' "
        "cost is above the optimum"
    ),
    Status.MAX_ITER_REACHED: (
        "stopped at the iteration cap before the stopping rule held; the inputs are the "
        "last iterate, projected on the bounds"
    ),
    Status.NUMERICAL_ERROR: (
        "the iterate is not finite (non-finite data or an overflow); the inputs are zeros, "
        "not a solution"
    ),
    Status.INFEASIBLE: (
        "the constraint set is empty (a Farkas certificate is in SolveResult.certificate); "
        "no inputs"
    ),
    Status.SOLVER_ERROR: "the reference solver failed or stopped without a solution; no inputs",
    Status.SOLVED_INACCURATE: (
        "a reference solver's solution short of its requested accuracy (Clarabel "
        "AlmostSolved, OSQP solved inaccurate, or a duality gap above 1e-5 of the full cost)"
    ),
}

STATUS: dict[int, str] = {int(s): s.label for s in Status}
"""Status code -> name (``STATUS[1] == "max_iter_reached"``)."""

USABLE = frozenset({Status.SOLVED, Status.MAX_ITER_REACHED, Status.SOLVED_INACCURATE})
"""The statuses whose inputs are a solution one may apply: exact (solved), the
last iterate at the cap, or a reference solver's inaccurate solution. The ADMM
formulations never return ``SOLVED_INACCURATE``; the closed loop applies
``MAX_ITER_REACHED`` (a warm-started iterate a few iterations short of the
tolerance is better than holding the previous command)."""

USABLE_STATUS: tuple[int, ...] = tuple(sorted(int(s) for s in USABLE))
""":data:`USABLE` as plain codes (0, 1, 5)."""


def usable(status: Any) -> Any:
    """Whether ``status`` (a code, a :class:`Status`, or an int array, traced or not)
    is in :data:`USABLE`: a Python bool for a scalar int, else a bool array."""
    if isinstance(status, (int, np.integer)):
        return int(status) in USABLE_STATUS
    import jax.numpy as jnp

    return jnp.isin(jnp.asarray(status), jnp.asarray(USABLE_STATUS, jnp.int32))


def status_name(code: Any) -> str:
    """Readable name of a status code."""
    return STATUS.get(int(code), f"unknown({int(code)})")


def status_message(code: Any) -> str:
    """One sentence on what status ``code`` means for the inputs returned."""
    c = int(code)
    return Status(c).message if c in STATUS else f"unknown status code {c}"


class SolveStats(NamedTuple):
    """What a solve measured besides its iterate (a pytree; fields may be None).

    gap : () a duality gap of the result: the integrated cost of ``u`` minus a
        Lagrangian dual bound from the multipliers, so J(u) - J* <= gap (cost
        units; :func:`~ampc_jax.admm.stopping.duality_gap`). For ``u``
        satisfying every row (always with box rows only: ``u`` is projected on
        the bounds), 1/2 ||u - U*||_H^2 <= gap, H the integrated Hessian: the
        inputs are within sqrt(2 gap / lambda_min(H)) of the optimum. It
        bounds the distance to the optimum of the problem the formulation
        solves, the integrated one when the groups S_j hold every agent that
        moves their outputs (as derived from the model). Computed once, in the
        result; unused, it costs nothing under ``jit``.
    solve_time : seconds the solve took, timed on the host around the solver
        call (reference solvers); None inside ``jit``, where nothing is timed.
    """

    gap: Any = None
    solve_time: Any = None


class SolveResult(NamedTuple):
    """Outcome of one MPC solve (a pytree; batched results carry a leading axis).

    Attributes
    ----------
    u : (N_p, n_u) inputs over the horizon, agent columns in topology order.
        For the ADMM formulations this is the average of the objectives' copies
        of each agent, projected onto the agent's bounds.
    iterations : number of iterations run.
    converged : whether the stopping rule (eq.Convergence) held.
    status : a :class:`Status` code (int32 inside jit); :func:`usable` says
        whether ``u`` may be applied.
    primal_residual, dual_residual : (n_obj,) squared residual norms per
        objective, ||r_j||^2 and ||s_j||^2 (eq.Convergence; paper-notes item 17).
    rho : (n_obj,) penalty parameters used.
    state : the final solver state (for warm starts), or ``None``.
    certificate : for a solve to tolerance that did not converge, the
        evidence of primal infeasibility
        (:class:`~ampc_jax.admm.feasibility.Certificate`; status 3 when found),
        else ``None``.
    stats : :class:`SolveStats`, or ``None``.
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
    stats: Any = None

    @property
    def u0(self) -> Any:
        """(n_u,) first-step inputs U^(0), the ones applied."""
        return self.u[..., 0, :]

    def per_agent(self, topology: Any, first_step: bool = False) -> dict[str, np.ndarray]:
        """Inputs split by agent name (numpy)."""
        u = np.asarray(self.u0 if first_step else self.u)
        o = topology.agent_offsets
        return {name: u[..., o[i] : o[i + 1]] for i, name in enumerate(topology.agent_names)}
