"""Generated test problems whose objectives couple only through shared agents.

Each objective O_j observes its own subsystem (a block of the state with its
own dynamics); private agents drive one subsystem, shared agents drive several.
Because the subsystems do not interact through A_d, the model-derived groups
S_j are exact and the decomposition of eq.integMPC_F3 is exact, so Local
Explicit must converge to the integrated optimum.

By default every objective has one output, references are held over the
horizon, weights are diagonal and there is no disturbance. The keywords
``outputs``, ``coupled_weights``, ``disturbance`` and ``per_step_reference``
add what the default problems leave out; they draw from a second random
stream, so the default problem of a seed is unchanged and the options only add
to it (same A_d, B_d, x0, bounds and R_(i) diagonals).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .problem import Agent, Objective, Problem

__all__ = ["problem_dict", "random_problem"]


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
    outputs: int = 1,
    coupled_weights: bool = False,
    disturbance: float = 0.0,
    per_step_reference: bool = False,
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
        unequal rho_j (paper-notes item 14).
    outputs : outputs per objective (1 .. states_per_objective): output r of
        objective j observes state r of its subsystem (plus, for r >= 1, a random
        share of state 0), each with its own reference.
    coupled_weights : non-diagonal (positive definite) Q_j when ``outputs`` > 1
        and R_(i) when ``inputs_per_agent`` > 1 (R_(i) keeps the default's diagonal).
    disturbance : scale of a random W_d^(k) that varies per step (N_p x n_x);
        0 (default) for none.
    per_step_reference : references that vary per predicted step (N_p x n_y):
        the default's held value plus a sinusoid of half its scale.
    """
    if not 1 <= outputs <= states_per_objective:
        raise ValueError(
            f"outputs: expected 1 .. states_per_objective ({states_per_objective}), got {outputs}"
        )
    rng = np.random.default_rng(seed)
    # the options' draws: a second stream, so that the default draws stay as they were
    extra = np.random.default_rng([seed, 1])

    def correlated(d: np.ndarray) -> np.ndarray:
        """A positive definite matrix with diagonal d and off-diagonal correlations."""
        n = d.size
        if not coupled_weights or n == 1:
            return np.diag(d)
        L = np.tril(extra.uniform(-1.0, 1.0, (n, n)), -1) + np.eye(n)
        S = L @ L.T
        corr = S / np.sqrt(np.outer(np.diag(S), np.diag(S)))  # unit diagonal, |corr| < 1
        return np.sqrt(d)[:, None] * corr * np.sqrt(d)[None, :]

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
        return Agent(name, B, correlated(R) if coupled_weights else R, lb, ub)

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
        C = np.zeros((outputs, nx))
        C[0, j * ns] = 1.0
        q = rng.uniform(1.0, 10.0) * (10.0 ** (j % 3) if rho_spread else 1.0)
        ref = reference_scale * rng.uniform(-1, 1) * np.ones(1)
        Q = [q]
        if outputs > 1:
            for r in range(1, outputs):
                C[r, j * ns + r] = 1.0
                C[r, j * ns] = extra.uniform(-0.5, 0.5)
            Q = correlated(q * extra.uniform(0.3, 1.0, outputs))
            ref = np.concatenate([ref, reference_scale * extra.uniform(-1, 1, outputs - 1)])
        if per_step_reference:
            k = np.arange(1, horizon + 1)[:, None]
            phase = extra.uniform(0.0, 2.0 * np.pi, outputs)
            ref = ref + 0.5 * reference_scale * np.sin(0.6 * k + phase)
        objectives.append(Objective(f"o{j}", C, Q, ref))
    x0 = rng.standard_normal(nx)
    w = disturbance * extra.standard_normal((horizon, nx)) if disturbance else None
    return Problem(horizon=horizon, A=A, x0=x0, agents=agents, objectives=objectives, w=w)


def problem_dict(problem: Problem) -> dict[str, Any]:
    """``problem`` in the JSON problem-file layout (:meth:`Problem.from_dict`; the
    README's format), plain lists, so a generated problem can be written with
    ``json.dump`` and solved by ``ampc solve``."""

    def arr(x: Any) -> Any:
        a = np.asarray(x, dtype=float)
        if not np.all(np.isfinite(a)):
            raise ValueError("problem: a bound or weight is not finite; JSON has no inf")
        return a.tolist()

    out: dict[str, Any] = {
        "horizon": int(problem.horizon),
        "A": arr(problem.A),
        "x0": arr(problem.x0),
        "agents": [
            {"name": a.name, "B": arr(a.B), "R": arr(a.R), "lb": arr(a.lb), "ub": arr(a.ub)}
            for a in problem.agents
        ],
        "objectives": [
            {
                "name": o.name,
                "C": arr(o.C),
                "Q": arr(o.Q),
                "ref": arr(o.ref),
                **({} if o.agents is None else {"agents": list(o.agents)}),
            }
            for o in problem.objectives
        ],
    }
    if problem.w is not None:
        out["w"] = arr(problem.w)
    if problem.constraints:
        out["constraints"] = [
            {"A": {k: arr(v) for k, v in c.A.items()}, "b": arr(c.b)} for c in problem.constraints
        ]
    return out
