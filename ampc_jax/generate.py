"""Generated test problems whose objectives couple only through shared agents.

Each objective O_j observes its own subsystem (a block of the state with its
own dynamics); private agents drive one subsystem, shared agents drive several.
Because the subsystems do not interact through A_d, the model-derived groups
S_j are exact and the decomposition of eq.integMPC_F3 is exact, so Local
Explicit must converge to the integrated optimum.
"""

from __future__ import annotations

import numpy as np

from .topology import Agent, Objective, Problem

__all__ = ["random_problem"]


def random_problem(
    seed: int,
    n_objectives: int = 2,
    *,
    states_per_objective: int = 2,
    horizon: int = 10,
    private_agents: int = 1,
    inputs_per_agent: int = 1,
    shared: str = "chain",
    bound: float = 1.0,
    reference_scale: float = 3.0,
    rho_spread: bool = True,
) -> Problem:
    """A random stable MACS with active input bounds.

    Parameters
    ----------
    seed : RNG seed.
    n_objectives : number of objectives (>= 1).
    shared : ``"chain"`` (agent shared by objectives j and j+1), ``"all"`` (one
        agent shared by all objectives), ``"both"`` or ``"none"``.
    bound : input bounds are about +-bound (randomised, asymmetric).
    reference_scale : references large enough that some bounds are active.
    rho_spread : scale the objectives' weights differently, so eq.opt_ro gives
        unequal rho_j (NOTES item 14).
    """
    rng = np.random.default_rng(seed)
    ns = states_per_objective
    nx = ns * n_objectives
    A = np.zeros((nx, nx))
    for j in range(n_objectives):
        M = rng.standard_normal((ns, ns))
        M = 0.95 * M / max(1.0, np.max(np.abs(np.linalg.eigvals(M))))
        A[j * ns : (j + 1) * ns, j * ns : (j + 1) * ns] = 0.5 * np.eye(ns) + 0.5 * M
    agents: list[Agent] = []

    def agent(name: str, subsystems: list[int]) -> Agent:
        B = np.zeros((nx, inputs_per_agent))
        for j in subsystems:
            B[j * ns : (j + 1) * ns] = rng.standard_normal((ns, inputs_per_agent))
        lb = -bound * rng.uniform(0.3, 1.0, inputs_per_agent)
        ub = bound * rng.uniform(0.3, 1.0, inputs_per_agent)
        R = rng.uniform(0.01, 0.2, inputs_per_agent)
        return Agent(name, B, R, lb, ub)

    for j in range(n_objectives):
        for p in range(private_agents):
            agents.append(agent(f"p{j}_{p}", [j]))
    if n_objectives > 1 and shared in ("chain", "both"):
        for j in range(n_objectives - 1):
            agents.append(agent(f"s{j}{j + 1}", [j, j + 1]))
    if n_objectives > 1 and shared in ("all", "both"):
        agents.append(agent("s_all", list(range(n_objectives))))
    objectives = []
    for j in range(n_objectives):
        C = np.zeros((1, nx))
        C[0, j * ns] = 1.0
        q = rng.uniform(1.0, 10.0) * (10.0 ** (j % 3) if rho_spread else 1.0)
        ref = reference_scale * rng.uniform(-1, 1) * np.ones(1)
        objectives.append(Objective(f"o{j}", C, [q], ref))
    x0 = rng.standard_normal(nx)
    return Problem(horizon=horizon, A=A, x0=x0, agents=agents, objectives=objectives)
