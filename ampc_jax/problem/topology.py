"""Static structure of a multi-objective MACS: sizes, names, groups, constraint rows.

The paper's section "Multi-objective MACS" (Notation): agents A_(i) with
inputs U_(i), objectives O_j with agent groups S_j = {i | G_j(i) = 1},
contribution sets S_(i) = {j | G_j(i) = 1} and multiplicities m_(i) = |S_(i)|.

Constraint rows. Per prediction step the rows of A_in are, in this order: one
row ``+e_k`` for every input with a finite upper bound, one row ``-e_k`` for
every input with a finite lower bound, then the general rows of each
``constraints`` entry. Which rows exist is static (a bound's finiteness is part
of the topology); their right-hand sides are data and may differ per step
(paper-notes item 11: the TCR agent's bound moves with the driver's torque).

A :class:`Topology` is hashable, so it is a static argument of compiled steps;
the numbers live in :class:`~ampc_jax.problem.data.ProblemData`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from .errors import ProblemError

__all__ = ["Topology"]


@dataclass(frozen=True)
class Topology:
    """Static (hashable) structure of a MACS: sizes, names, groups, constraint rows.

    Attributes
    ----------
    n_x, horizon : state size and N_p.
    agent_names, agent_sizes : agents A_(i) and n_u(i).
    objective_names, output_sizes : objectives O_j and n_y(j).
    groups : S_j as sorted tuples of agent indices.
    box_rows : per constraint row of the box part, ``(input index, +1 | -1)``.
    general_agents : per general row, the agents it involves (``i -> c``).
    covered_inputs : per input, whether any constraint row has a non-zero coefficient on it.
    pinned_rank : per agent, rank of its own rows (box rows and single-agent general rows).
    group_rank : per objective, rank of its per-step rows A_in,j (restricted to U_j);
        full column rank lets eq.opt_ro skip any eigenvalue threshold (see
        ``formulations.optimal_rho``).
    total_rank : rank of all per-step rows A_in (the undecomposed problem's).
    singular_r : agents whose weight R_(i) is singular, from the problem's
        numbers when built by :class:`Problem` (``Topology.build`` takes it as
        an argument, default none). Local Explicit's low-rank factorisation
        needs R_(i) > 0; with other R in a ``ProblemData`` (a sweep, or a
        gradient through R) keep them positive definite, or use
        ``kkt="dense"``.
    """

    n_x: int
    horizon: int
    agent_names: tuple[str, ...]
    agent_sizes: tuple[int, ...]
    objective_names: tuple[str, ...]
    output_sizes: tuple[int, ...]
    groups: tuple[tuple[int, ...], ...]
    box_rows: tuple[tuple[int, int], ...]
    general_agents: tuple[tuple[int, ...], ...]
    covered_inputs: tuple[bool, ...] = ()
    pinned_rank: tuple[int, ...] = ()
    group_rank: tuple[int, ...] = ()
    total_rank: int = 0
    singular_r: tuple[int, ...] = ()

    @classmethod
    def build(
        cls,
        *,
        n_x: int,
        horizon: int,
        agent_names: Sequence[str],
        agent_sizes: Sequence[int],
        objective_names: Sequence[str],
        output_sizes: Sequence[int],
        groups: Sequence[Sequence[int]],
        finite_lb: Sequence[bool] | None = None,
        finite_ub: Sequence[bool] | None = None,
        general_rows: Sequence[np.ndarray] = (),
        singular_r: Sequence[int] = (),
    ) -> Topology:
        """Build a topology. Bounds are finite by default (two box rows per input);
        ``singular_r`` lists the agents whose R_(i) is singular."""
        n_u = int(sum(agent_sizes))
        finite_lb = np.ones(n_u, bool) if finite_lb is None else np.asarray(finite_lb, bool)
        finite_ub = np.ones(n_u, bool) if finite_ub is None else np.asarray(finite_ub, bool)
        box = tuple((int(k), 1) for k in np.nonzero(finite_ub)[0]) + tuple(
            (int(k), -1) for k in np.nonzero(finite_lb)[0]
        )
        offsets = np.cumsum([0, *agent_sizes])
        gen_agents = []
        for rows in general_rows:
            for r in np.atleast_2d(rows):
                gen_agents.append(
                    tuple(
                        i
                        for i in range(len(agent_sizes))
                        if np.any(r[offsets[i] : offsets[i + 1]] != 0)
                    )
                )
        # Rows that pin each agent by itself (its box rows and its single-agent
        # general rows): their rank decides whether shared copies must agree.
        allrows = (
            np.concatenate([np.atleast_2d(r) for r in general_rows], 0)
            if len(general_rows)
            else np.zeros((0, n_u))
        )
        covered = np.zeros(n_u, bool)
        for k, _ in box:
            covered[k] = True
        covered |= np.any(allrows != 0, axis=0)
        ranks = []
        for i in range(len(agent_sizes)):
            own = [np.eye(n_u)[k] for k, _ in box if offsets[i] <= k < offsets[i + 1]]
            own += [allrows[c] for c, ag in enumerate(gen_agents) if ag == (i,)]
            block = np.array(own)[:, offsets[i] : offsets[i + 1]] if own else np.zeros((0, 1))
            ranks.append(int(np.linalg.matrix_rank(block)) if own else 0)
        topo = cls(
            n_x=int(n_x),
            horizon=int(horizon),
            agent_names=tuple(agent_names),
            agent_sizes=tuple(int(s) for s in agent_sizes),
            objective_names=tuple(objective_names),
            output_sizes=tuple(int(s) for s in output_sizes),
            groups=tuple(tuple(sorted(int(i) for i in g)) for g in groups),
            box_rows=box,
            general_agents=tuple(gen_agents),
            covered_inputs=tuple(bool(x) for x in covered),
            pinned_rank=tuple(ranks),
            singular_r=tuple(sorted(int(i) for i in singular_r)),
        )
        box_A = np.zeros((len(box), n_u))
        for r, (k, s) in enumerate(box):
            box_A[r, k] = s
        Ain = np.concatenate([box_A, allrows], axis=0)
        full = []
        for j in range(topo.n_objectives):
            Aj = Ain[np.ix_(topo.group_rows(j), topo.group_columns(j))]
            full.append(int(np.linalg.matrix_rank(Aj)) if Aj.size else 0)
        total = int(np.linalg.matrix_rank(Ain)) if Ain.size else 0
        return replace(topo, group_rank=tuple(full), total_rank=total)

    # -- derived sizes ----------------------------------------------------------
    @property
    def n_u(self) -> int:
        return sum(self.agent_sizes)

    @property
    def n_agents(self) -> int:
        return len(self.agent_sizes)

    @property
    def n_objectives(self) -> int:
        return len(self.groups)

    @property
    def n_c(self) -> int:
        """Constraint rows per step (box rows then general rows)."""
        return len(self.box_rows) + len(self.general_agents)

    @property
    def agent_offsets(self) -> tuple[int, ...]:
        return tuple(int(x) for x in np.cumsum([0, *self.agent_sizes]))

    def agent_columns(self, i: int) -> tuple[int, ...]:
        o = self.agent_offsets
        return tuple(range(o[i], o[i + 1]))

    def group_columns(self, j: int) -> tuple[int, ...]:
        """Columns of U (within one step) belonging to U_j, in agent order."""
        return tuple(k for i in self.groups[j] for k in self.agent_columns(i))

    def contributions(self, i: int) -> tuple[int, ...]:
        """S_(i): objectives agent i contributes to."""
        return tuple(j for j, g in enumerate(self.groups) if i in g)

    @property
    def multiplicity(self) -> tuple[int, ...]:
        """m_(i) = |S_(i)| for every agent."""
        return tuple(len(self.contributions(i)) for i in range(self.n_agents))

    def row_agents(self, c: int) -> tuple[int, ...]:
        """Agents linearly involved in constraint row c (i -> c)."""
        nb = len(self.box_rows)
        if c < nb:
            k = self.box_rows[c][0]
            return (self.agent_of_input(k),)
        return self.general_agents[c - nb]

    def agent_of_input(self, k: int) -> int:
        o = self.agent_offsets
        return int(np.searchsorted(o, k, side="right") - 1)

    def group_rows(self, j: int) -> tuple[int, ...]:
        """Constraint rows objective j carries: rows whose agents all lie in S_j."""
        g = set(self.groups[j])
        return tuple(
            c for c in range(self.n_c) if set(self.row_agents(c)) <= g and self.row_agents(c)
        )

    @property
    def row_multiplicity(self) -> tuple[int, ...]:
        """m_(c) (eq.F3_dual_1): number of objectives that carry row c."""
        return tuple(
            sum(c in self.group_rows(j) for j in range(self.n_objectives)) for c in range(self.n_c)
        )

    def check_local_explicit(self) -> None:
        """Local Explicit's structural requirements (paper-notes item 10).

        * every input appears in at least one constraint row;
        * every constraint row lies within one objective's group (so some
          objective can evaluate it);
        * every agent shared by several objectives is pinned by its own rows
          (box rows or single-agent general rows of full column rank), so that
          the shared slack makes the objectives' copies agree.
        """
        covered = np.asarray(self.covered_inputs, bool)
        o = self.agent_offsets
        for k in np.nonzero(~covered)[0]:
            i = self.agent_of_input(int(k))
            raise ProblemError(
                f"agents[{i}] ({self.agent_names[i]}): input {int(k) - o[i]} appears in no "
                f"constraint row; Local Explicit needs every input bounded (paper, after "
                f"eq.F3_multiplier; paper-notes item 10): give the agent finite 'lb' and 'ub' (a "
                f"bound wider than any input it will take leaves the optimum unchanged), put "
                f"the input in a 'constraints' row, or solve with the integrated formulation"
            )
        mult = self.row_multiplicity
        for c, m in enumerate(mult):
            if m == 0:
                names = [self.agent_names[i] for i in self.row_agents(c)]
                raise ProblemError(
                    f"constraints: row {c - len(self.box_rows)} couples agents {names} that share "
                    f"no objective; Local Explicit needs each row's agents within one group"
                )
        for i in range(self.n_agents):
            if len(self.contributions(i)) < 2:
                continue
            if self.pinned_rank[i] < self.agent_sizes[i]:
                raise ProblemError(
                    f"agents[{i}] ({self.agent_names[i]}): shared by objectives "
                    f"{[self.objective_names[j] for j in self.contributions(i)]} but its inputs "
                    f"are not pinned by rows of its own (bounds); their copies could disagree"
                )
