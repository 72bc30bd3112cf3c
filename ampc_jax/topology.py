"""Problem model of a multi-objective multi-agent control system (MACS).

The paper's section "Multi-objective MACS" (Notation) defines agents A_(i) with
inputs U_(i), objectives O_j, the contribution flags G_j(i), the agent groups
S_j = {i | G_j(i) = 1}, the contribution sets S_(i) = {j | G_j(i) = 1} and the
multiplicities m_(i) = |S_(i)|. The integrated MPC (eq.integMPC, eq_linear)
is defined by the shared model

    X^(k+1) = A_d X^(k) + sum_i B_d(i) U_(i)^(k) + W_d^(k)
    h_j = || C_j X^(k) - ref_j^(k) ||^2_{Q_j},   g_(i) = || U_(i)^(k) ||^2_{R_(i)}
    A_in U^(k) <= b_in^(k)

Two layers live here:

* :class:`Problem` -- the user-facing, validated description (from a JSON
  problem file, a ``dict`` or Python objects). Every validation error is a
  :class:`ProblemError` naming the offending field.
* :class:`Topology` (static, hashable: sizes, names, groups and constraint-row
  structure) plus :class:`ProblemData` (a pytree of arrays: the numbers). Only
  the latter is traced by JAX, so a time-varying model (the vehicle examples
  re-linearise every step) is rebuilt inside one compiled step, and batches of
  scenarios are ``vmap``-ed over :class:`ProblemData`.

Constraint rows. Per prediction step the rows of A_in are, in this order: one
row ``+e_k`` for every input with a finite upper bound, one row ``-e_k`` for
every input with a finite lower bound, then the general rows of each
``constraints`` entry. Which rows exist is static (a bound's finiteness is part
of the topology); their right-hand sides are data and may differ per step
(NOTES item 11: the TCR agent's bound moves with the driver's torque).
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

__all__ = [
    "Agent",
    "Constraint",
    "GROUP_TOL",
    "Objective",
    "Problem",
    "ProblemData",
    "ProblemError",
    "Topology",
    "make_data",
]

#: Relative tolerance of the model-derived agent groups: agent i is in S_j when
#: ||C_j A_d^k B_d(i)||_F > GROUP_TOL * ||C_j||_F ||A_d^k||_F ||B_d(i)||_F for
#: some k < N_p.
GROUP_TOL = 1e-10


class ProblemError(ValueError):
    """Invalid problem description; the message names the field and what was expected."""


# ----------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------


def _non_number(value: Any) -> Any:
    """The first entry of nested lists that is not a number (a string, a
    boolean, null), or None when every entry is one."""
    if isinstance(value, (str, bytes, bool, np.bool_)) or value is None:
        return repr(value) if value is not None else "null"
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "biufc":
            return "a boolean array" if value.dtype.kind == "b" else None
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        for v in value:
            bad = _non_number(v)
            if bad is not None:
                return bad
    return None


def _array(value: Any, field_name: str) -> np.ndarray:
    if value is None:
        raise ProblemError(f"{field_name}: a number or array is required, got nothing")
    bad = _non_number(value)
    if bad is not None:
        raise ProblemError(f"{field_name}: expected numbers, got {bad:.40}")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ProblemError(
            f"{field_name}: expected numbers (nested lists, row-major), got {value!r:.80}"
        ) from exc
    if not np.all(np.isfinite(arr)):
        bad = "NaN" if np.any(np.isnan(arr)) else "inf"
        raise ProblemError(f"{field_name}: contains {bad}; every entry must be a finite number")
    return arr


def _bound(value: Any, field_name: str, n: int, side: str, hint: str = "") -> np.ndarray:
    """Bounds may be -inf (``side="lower"``) or +inf (upper): no row; never
    NaN, and never the infinity that no input can satisfy."""
    bad = _non_number(value)
    if bad is not None:
        raise ProblemError(
            f"{field_name}: expected {n} numbers, got {bad:.40} (no bound: leave the "
            f"field out, or JSON -Infinity / Infinity)"
        )
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ProblemError(f"{field_name}: expected {n} numbers, got {value!r:.80}") from exc
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ProblemError(f"{field_name}: expected {n} numbers, got shape {arr.shape}{hint}")
    if np.any(np.isnan(arr)):
        raise ProblemError(f"{field_name}: contains NaN; use a number or +-inf (no bound)")
    wrong = np.inf if side == "lower" else -np.inf
    if np.any(arr == wrong):
        free = "-inf" if side == "lower" else "+inf"
        raise ProblemError(
            f"{field_name}: contains {'+' if wrong > 0 else '-'}inf, which no input "
            f"satisfies; use a number, or {free} for no {side} bound"
        )
    return arr


def _matrix(
    value: Any, field_name: str, rows: int | None, cols: int | None, hint: str = ""
) -> np.ndarray:
    arr = _array(value, field_name)
    if arr.ndim != 2:
        raise ProblemError(
            f"{field_name}: expected a matrix ({_dims(rows, cols)}), got shape {arr.shape}"
        )
    if (rows is not None and arr.shape[0] != rows) or (cols is not None and arr.shape[1] != cols):
        raise ProblemError(
            f"{field_name}: expected shape ({_dims(rows, cols)}), "
            f"got {arr.shape[0]} x {arr.shape[1]}{hint}"
        )
    return arr


def _inputs_of(i: int, n_u: int) -> str:
    """The end of a size error whose size is agent i's input count."""
    return f" (n_u = {n_u}: the columns of agents[{i}].B)"


def _dims(rows: int | None, cols: int | None) -> str:
    return f"{rows if rows is not None else 'n'} x {cols if cols is not None else 'm'}"


def _weight(value: Any, field_name: str, n: int, *, definite: bool, hint: str = "") -> np.ndarray:
    """A weight given as an n x n symmetric matrix or a length-n diagonal.

    ``hint`` ends a shape error with where n comes from (e.g. the columns of B)."""
    arr = _array(value, field_name)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.ndim == 1:
        if arr.shape != (n,):
            raise ProblemError(
                f"{field_name}: expected {n} x {n} or a diagonal of length {n}, "
                f"got {arr.shape}{hint}"
            )
        arr = np.diag(arr)
    elif arr.shape != (n, n):
        raise ProblemError(
            f"{field_name}: expected {n} x {n} or a diagonal of length {n}, "
            f"got shape {arr.shape}{hint}"
        )
    scale = max(1.0, float(np.max(np.abs(arr))))
    if not np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12 * scale):
        raise ProblemError(f"{field_name}: must be symmetric")
    eig = np.linalg.eigvalsh(arr)
    if definite and eig.min() <= 1e-12 * scale:
        raise ProblemError(
            f"{field_name}: must be positive definite (smallest eigenvalue {eig.min():.3g})"
        )
    if not definite and eig.min() < -1e-12 * scale:
        raise ProblemError(
            f"{field_name}: must be positive semi-definite, not negative "
            f"(smallest eigenvalue {eig.min():.3g})"
        )
    return arr


def _is_singular(R: np.ndarray) -> bool:
    """Whether a validated symmetric positive semi-definite weight is singular
    (smallest eigenvalue at most 1e-12 of the largest entry, as :func:`_weight`)."""
    scale = max(1.0, float(np.max(np.abs(R))))
    return bool(np.linalg.eigvalsh(R).min() <= 1e-12 * scale)


def _per_step(
    value: Any, field_name: str, n: int, horizon: int, default: float = 0.0, hint: str = ""
) -> np.ndarray:
    """A vector of length n held over the horizon, or an N_p x n sequence."""
    if value is None:
        return np.full((horizon, n), default)
    arr = _array(value, field_name)
    if arr.ndim == 0 and n == 1:
        arr = arr.reshape(1)
    if arr.ndim == 1:
        if arr.shape != (n,):
            raise ProblemError(
                f"{field_name}: expected {n} numbers or a {horizon} x {n} sequence, got {arr.shape}{hint}"
            )
        return np.tile(arr, (horizon, 1))
    if arr.shape != (horizon, n):
        raise ProblemError(
            f"{field_name}: expected {n} numbers or a {horizon} x {n} sequence, got {arr.shape}{hint}"
        )
    return arr


def _name(value: Any, field_name: str) -> str:
    if not isinstance(value, str) or not value:
        raise ProblemError(f"{field_name}: expected a non-empty string name, got {value!r}")
    return value


# ----------------------------------------------------------------------------
# User-facing description
# ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Agent:
    """Agent A_(i): inputs U_(i) in R^{n_u(i)} entering through B_d(i).

    Parameters
    ----------
    name : unique name.
    B : (n_x, n_u) input matrix B_d(i).
    R : (n_u, n_u) weight R_(i) (positive semi-definite), or its diagonal.
    lb, ub : (n_u,) bounds; +-inf means "no bound" (no constraint row).
    """

    name: str
    B: Any
    R: Any
    lb: Any = -math.inf
    ub: Any = math.inf


@dataclass(frozen=True)
class Objective:
    """Objective O_j: track ``ref`` with outputs C_j X, weighted by Q_j.

    Parameters
    ----------
    name : unique name.
    C : (n_y, n_x) observation matrix C_j.
    Q : (n_y, n_y) weight Q_j (positive semi-definite: a zero weight on an
        output is allowed), or its diagonal.
    ref : (n_y,) held over the horizon, or (N_p, n_y) for predicted steps 1..N_p
        (NOTES item 19).
    agents : names of the agent group S_j; derived from the model when omitted.
    """

    name: str
    C: Any
    Q: Any
    ref: Any = 0.0
    agents: Sequence[str] | None = None


@dataclass(frozen=True)
class Constraint:
    """General rows ``sum_i A[i] U_(i)^(k) <= b^(k)`` at every step k.

    Parameters
    ----------
    A : mapping agent name -> (n_c, n_u(i)) coefficients.
    b : (n_c,) held over the horizon, or (N_p, n_c).
    """

    A: Mapping[str, Any]
    b: Any


@dataclass(frozen=True)
class Problem:
    """A validated MACS with its integrated MPC (eq.integMPC, eq_linear).

    Build it with :meth:`from_dict`, :meth:`from_json` or directly from
    :class:`Agent`, :class:`Objective` and :class:`Constraint` objects
    (validation runs in ``__post_init__``). :attr:`topology` and :meth:`data`
    give the static structure and the arrays the solvers take.
    """

    horizon: int
    A: Any
    x0: Any
    agents: Sequence[Agent]
    objectives: Sequence[Objective]
    w: Any = None
    constraints: Sequence[Constraint] = ()
    topology: Topology = field(init=False, repr=False)
    _data: dict = field(init=False, repr=False)

    # -- construction ---------------------------------------------------------
    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Problem:
        """Build from the JSON problem-file layout (see the README)."""
        if not isinstance(d, Mapping):
            raise ProblemError(f"problem: expected a JSON object, got {type(d).__name__}")
        known = {"horizon", "A", "x0", "w", "agents", "objectives", "constraints", "name"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ProblemError(
                f"problem: unknown key(s) {unknown}; expected some of {sorted(known)}"
            )
        for key in ("horizon", "A", "x0", "agents", "objectives"):
            if key not in d:
                raise ProblemError(f"{key}: required key is missing")
        agents_in = d["agents"]
        if not isinstance(agents_in, list) or not agents_in:
            raise ProblemError("agents: expected a non-empty list of agent objects")
        agents = []
        for i, a in enumerate(agents_in):
            if not isinstance(a, Mapping):
                raise ProblemError(f"agents[{i}]: expected an object with name, B, R, lb, ub")
            extra = sorted(set(a) - {"name", "B", "R", "lb", "ub"})
            if extra:
                raise ProblemError(f"agents[{i}]: unknown key(s) {extra}")
            for key in ("name", "B", "R"):
                if key not in a:
                    raise ProblemError(f"agents[{i}].{key}: required key is missing")
            agents.append(
                Agent(a["name"], a["B"], a["R"], a.get("lb", -math.inf), a.get("ub", math.inf))
            )
        objectives_in = d["objectives"]
        if not isinstance(objectives_in, list) or not objectives_in:
            raise ProblemError("objectives: expected a non-empty list of objective objects")
        objectives = []
        for j, o in enumerate(objectives_in):
            if not isinstance(o, Mapping):
                raise ProblemError(f"objectives[{j}]: expected an object with name, C, Q, ref")
            extra = sorted(set(o) - {"name", "C", "Q", "ref", "agents"})
            if extra:
                raise ProblemError(f"objectives[{j}]: unknown key(s) {extra}")
            for key in ("name", "C", "Q"):
                if key not in o:
                    raise ProblemError(f"objectives[{j}].{key}: required key is missing")
            objectives.append(
                Objective(o["name"], o["C"], o["Q"], o.get("ref", 0.0), o.get("agents"))
            )
        constraints = []
        for c, con in enumerate(d.get("constraints") or []):
            if not isinstance(con, Mapping) or "A" not in con or "b" not in con:
                raise ProblemError(f"constraints[{c}]: expected an object with keys A and b")
            constraints.append(Constraint(con["A"], con["b"]))
        return cls(
            horizon=d["horizon"],
            A=d["A"],
            x0=d["x0"],
            agents=agents,
            objectives=objectives,
            w=d.get("w"),
            constraints=constraints,
        )

    @classmethod
    def from_json(cls, path: str | Path) -> Problem:
        """Load a JSON problem file."""
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise ProblemError(f"problem file {path}: cannot read ({exc.strerror})") from exc
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ProblemError(f"problem file {path}: not valid JSON ({exc})") from exc
        return cls.from_dict(d)

    def __post_init__(self) -> None:
        horizon = self.horizon
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ProblemError(f"horizon: expected an integer >= 1, got {horizon!r}")
        horizon = int(horizon)
        A = _array(self.A, "A")
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ProblemError(f"A: expected a square n_x x n_x matrix, got shape {A.shape}")
        nx = A.shape[0]
        x0 = _array(self.x0, "x0").reshape(-1) if np.ndim(self.x0) <= 1 else _array(self.x0, "x0")
        if x0.shape != (nx,):
            raise ProblemError(f"x0: expected {nx} numbers (n_x from A), got shape {x0.shape}")
        w = _per_step(self.w, "w", nx, horizon)

        names: list[str] = []
        Bs, Rs, lbs, ubs = [], [], [], []
        for i, a in enumerate(self.agents):
            if not isinstance(a, Agent):
                raise ProblemError(f"agents[{i}]: expected an Agent, got {type(a).__name__}")
            name = _name(a.name, f"agents[{i}].name")
            if name in names:
                raise ProblemError(f"agents[{i}].name: duplicate agent name {name!r}")
            names.append(name)
            B = _array(a.B, f"agents[{i}].B ({name})")
            if B.ndim == 1 and B.shape[0] == nx:
                B = B.reshape(nx, 1)
            if B.ndim != 2 or B.shape[0] != nx or B.shape[1] < 1:
                raise ProblemError(
                    f"agents[{i}].B ({name}): expected an {nx} x n_u matrix, got shape {B.shape}"
                )
            nu = B.shape[1]
            hint = _inputs_of(i, nu)
            R = _weight(a.R, f"agents[{i}].R ({name})", nu, definite=False, hint=hint)
            lb = _bound(a.lb, f"agents[{i}].lb ({name})", nu, "lower", hint)
            ub = _bound(a.ub, f"agents[{i}].ub ({name})", nu, "upper", hint)
            bad = np.nonzero(lb > ub)[0]
            if bad.size:
                k = int(bad[0])
                raise ProblemError(
                    f"agents[{i}].lb ({name}): lb > ub at input {k} ({lb[k]} > {ub[k]})"
                )
            Bs.append(B)
            Rs.append(R)
            lbs.append(lb)
            ubs.append(ub)
        if not names:
            raise ProblemError("agents: at least one agent is required")

        obj_names: list[str] = []
        Cs, Qs, refs, groups = [], [], [], []
        powers = [np.linalg.matrix_power(A, k) for k in range(horizon)]
        for j, o in enumerate(self.objectives):
            if not isinstance(o, Objective):
                raise ProblemError(
                    f"objectives[{j}]: expected an Objective, got {type(o).__name__}"
                )
            name = _name(o.name, f"objectives[{j}].name")
            if name in obj_names:
                raise ProblemError(f"objectives[{j}].name: duplicate objective name {name!r}")
            obj_names.append(name)
            C = _array(o.C, f"objectives[{j}].C ({name})")
            if C.ndim == 1 and C.shape[0] == nx:
                C = C.reshape(1, nx)
            if C.ndim != 2 or C.shape[1] != nx or C.shape[0] < 1:
                raise ProblemError(
                    f"objectives[{j}].C ({name}): expected an n_y x {nx} matrix, got shape {C.shape}"
                )
            ny = C.shape[0]
            hint = f" (n_y = {ny}: the rows of objectives[{j}].C)"
            Q = _weight(o.Q, f"objectives[{j}].Q ({name})", ny, definite=False, hint=hint)
            ref = _per_step(o.ref, f"objectives[{j}].ref ({name})", ny, horizon, hint=hint)
            if o.agents is None:
                group = tuple(i for i, B in enumerate(Bs) if _influences(C, powers, B))
                if not group:
                    raise ProblemError(
                        f"objectives[{j}] ({name}): no agent influences C_j X within the horizon "
                        f"(derived group is empty); give 'agents' or check C and B"
                    )
            else:
                if isinstance(o.agents, str) or not isinstance(o.agents, Sequence):
                    raise ProblemError(
                        f"objectives[{j}].agents ({name}): expected a list of agent names"
                    )
                group_l = []
                for a_name in o.agents:
                    if a_name not in names:
                        raise ProblemError(
                            f"objectives[{j}].agents ({name}): unknown agent {a_name!r}; "
                            f"known agents are {names}"
                        )
                    if names.index(a_name) in group_l:
                        raise ProblemError(
                            f"objectives[{j}].agents ({name}): agent {a_name!r} listed twice"
                        )
                    group_l.append(names.index(a_name))
                if not group_l:
                    raise ProblemError(f"objectives[{j}].agents ({name}): the group is empty")
                group = tuple(sorted(group_l))
                missed = [
                    names[i]
                    for i, B in enumerate(Bs)
                    if i not in group and _influences(C, powers, B)
                ]
                if missed:
                    warnings.warn(
                        f"objectives[{j}] ({name}): agents {missed} influence C_j X but are "
                        f"not in its 'agents' group; the decomposed formulations ignore that "
                        f"influence, so they will not reach the integrated optimum",
                        stacklevel=3,
                    )
            Cs.append(C)
            Qs.append(Q)
            refs.append(ref)
            groups.append(group)
        if not obj_names:
            raise ProblemError("objectives: at least one objective is required")
        for i, name in enumerate(names):
            if not any(i in g for g in groups):
                raise ProblemError(
                    f"agents[{i}] ({name}): the agent belongs to no objective; "
                    f"list it in an objective's 'agents' or remove it"
                )

        gen_agents, gen_A, gen_b = [], [], []
        for c, con in enumerate(self.constraints):
            if not isinstance(con, Constraint):
                raise ProblemError(f"constraints[{c}]: expected a Constraint")
            if not isinstance(con.A, Mapping) or not con.A:
                raise ProblemError(
                    f"constraints[{c}].A: expected an object mapping agent names to matrices"
                )
            b0 = _array(con.b, f"constraints[{c}].b")
            nc = b0.shape[-1] if b0.ndim >= 1 else 1
            b = _per_step(con.b, f"constraints[{c}].b", nc, horizon)
            rows = np.zeros((nc, sum(B.shape[1] for B in Bs)))
            offsets = np.cumsum([0] + [B.shape[1] for B in Bs])
            involved = []
            for a_name, coeff in con.A.items():
                if a_name not in names:
                    raise ProblemError(
                        f"constraints[{c}].A: unknown agent {a_name!r}; known agents are {names}"
                    )
                i = names.index(a_name)
                M = _matrix(
                    coeff,
                    f"constraints[{c}].A.{a_name}",
                    nc,
                    Bs[i].shape[1],
                    hint=_inputs_of(i, Bs[i].shape[1]),
                )
                rows[:, offsets[i] : offsets[i + 1]] = M
                involved.append(i)
            gen_agents.append(tuple(sorted(involved)))
            gen_A.append(rows)
            gen_b.append(b)

        topo = Topology.build(
            n_x=nx,
            horizon=horizon,
            agent_names=names,
            agent_sizes=[B.shape[1] for B in Bs],
            objective_names=obj_names,
            output_sizes=[C.shape[0] for C in Cs],
            groups=groups,
            finite_lb=np.concatenate([np.isfinite(lb) for lb in lbs]),
            finite_ub=np.concatenate([np.isfinite(ub) for ub in ubs]),
            general_rows=gen_A,
            singular_r=[i for i, R in enumerate(Rs) if _is_singular(R)],
        )
        object.__setattr__(self, "topology", topo)
        object.__setattr__(
            self,
            "_data",
            dict(
                A=A,
                B=np.concatenate(Bs, axis=1),
                w=w,
                x0=x0,
                R=[R for R in Rs],
                C=Cs,
                Q=Qs,
                ref=refs,
                lb=np.tile(np.concatenate(lbs), (horizon, 1)),
                ub=np.tile(np.concatenate(ubs), (horizon, 1)),
                G=np.concatenate(gen_A, axis=0) if gen_A else np.zeros((0, topo.n_u)),
                g=np.concatenate(gen_b, axis=1) if gen_b else np.zeros((horizon, 0)),
            ),
        )

    def data(self, dtype: Any = None) -> ProblemData:
        """The numbers as a :class:`ProblemData` pytree (float64 unless ``dtype``)."""
        d = self._data
        return make_data(
            self.topology,
            A=d["A"],
            B=d["B"],
            w=d["w"],
            x0=d["x0"],
            R=d["R"],
            C=d["C"],
            Q=d["Q"],
            ref=d["ref"],
            lb=d["lb"],
            ub=d["ub"],
            G=d["G"],
            g=d["g"],
            dtype=dtype,
        )

    def check_local_explicit(self) -> None:
        """Raise :class:`ProblemError` if Local Explicit cannot solve this topology."""
        self.topology.check_local_explicit()


def _influences(C: np.ndarray, powers: list[np.ndarray], B: np.ndarray) -> bool:
    """G_j(i) = 1 when C_j A_d^k B_d(i) is non-zero for some k < N_p (GROUP_TOL)."""
    for Ak in powers:
        M = C @ Ak @ B
        scale = np.linalg.norm(C) * np.linalg.norm(Ak) * np.linalg.norm(B)
        if scale > 0 and np.linalg.norm(M) > GROUP_TOL * scale:
            return True
    return False


# ----------------------------------------------------------------------------
# Static structure
# ----------------------------------------------------------------------------


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
        ``factorisation="dense"``.
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
        """Local Explicit's structural requirements (NOTES item 10).

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
                f"constraint row; Local Explicit needs every input bounded (lb/ub) or in a "
                f"'constraints' row (paper, after eq.F3_multiplier; NOTES item 10)"
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


# ----------------------------------------------------------------------------
# The numbers
# ----------------------------------------------------------------------------


class ProblemData(NamedTuple):
    """Arrays of one MACS instance (a pytree; ``vmap`` over a leading batch axis).

    Attributes
    ----------
    A : (n_x, n_x) A_d.
    B : (n_x, n_u) [B_d(i) for all agents], columns in agent order.
    w : (N_p, n_x) W_d^(k), k = 0..N_p-1.
    x0 : (n_x,) X^(0).
    R : (n_u, n_u) block-diagonal [R_(i)].
    C, Q, ref : tuples over objectives of (n_y, n_x), (n_y, n_y), (N_p, n_y);
        ``ref[j][k]`` is the reference of C_j X^(k+1).
    Ain : (n_c, n_u) constraint rows A_in (box rows, then general rows).
    bin : (N_p, n_c) right-hand sides b_in^(k).
    lb, ub : (N_p, n_u) the bounds (+-inf where absent), for projecting outputs.
    """

    A: Any
    B: Any
    w: Any
    x0: Any
    R: Any
    C: tuple
    Q: tuple
    ref: tuple
    Ain: Any
    bin: Any
    lb: Any
    ub: Any


def make_data(
    topology: Topology,
    *,
    A: Any,
    B: Any,
    x0: Any,
    C: Sequence[Any],
    Q: Sequence[Any],
    ref: Sequence[Any],
    R: Any,
    lb: Any,
    ub: Any,
    w: Any = None,
    G: Any = None,
    g: Any = None,
    dtype: Any = None,
) -> ProblemData:
    """Assemble :class:`ProblemData` (jittable; used for time-varying models).

    ``B`` may be the (n_x, n_u) concatenation or a sequence of per-agent blocks;
    ``R`` the (n_u, n_u) matrix or a sequence of per-agent blocks; ``lb``/``ub``
    (n_u,) or (N_p, n_u) (also sequences of per-agent vectors); ``ref[j]``
    (n_y,) or (N_p, n_y); ``w`` (n_x,) or (N_p, n_x); ``G`` (n_g, n_u) and ``g``
    (n_g,) or (N_p, n_g) the general rows.
    """
    Np, nx, nu = topology.horizon, topology.n_x, topology.n_u
    if dtype is None:
        dtype = jnp.result_type(float)

    def arr(x: Any) -> Any:
        return jnp.asarray(x, dtype=dtype)

    def per_step(x: Any, n: int) -> Any:
        x = arr(x)
        return jnp.broadcast_to(x, (Np, n)) if x.ndim <= 1 else x

    if isinstance(B, (list, tuple)):
        B = jnp.concatenate([arr(b).reshape(nx, -1) for b in B], axis=1)
    if isinstance(R, (list, tuple)):
        blocks = [arr(r) for r in R]
        blocks = [jnp.diag(r) if r.ndim == 1 else r.reshape(r.shape[-1], -1) for r in blocks]
        R = jsl.block_diag(*blocks)
    if isinstance(lb, (list, tuple)):
        lb = jnp.concatenate([jnp.atleast_1d(arr(x)) for x in lb], axis=-1)
    if isinstance(ub, (list, tuple)):
        ub = jnp.concatenate([jnp.atleast_1d(arr(x)) for x in ub], axis=-1)
    lb, ub = per_step(lb, nu), per_step(ub, nu)
    w = jnp.zeros((Np, nx), dtype) if w is None else per_step(w, nx)
    Cs = tuple(arr(c).reshape(ny, nx) for c, ny in zip(C, topology.output_sizes, strict=True))
    Qs = tuple(
        (jnp.diag(arr(q).reshape(ny)) if arr(q).ndim <= 1 else arr(q))
        for q, ny in zip(Q, topology.output_sizes, strict=True)
    )
    refs = tuple(per_step(r, ny) for r, ny in zip(ref, topology.output_sizes, strict=True))

    up = [k for k, s in topology.box_rows if s > 0]
    lo = [k for k, s in topology.box_rows if s < 0]
    box_A = np.zeros((len(topology.box_rows), nu))
    for r, (k, s) in enumerate(topology.box_rows):
        box_A[r, k] = s
    box_b = jnp.concatenate([ub[:, up], -lb[:, lo]], axis=1)
    n_gen = len(topology.general_agents)
    if n_gen:
        G = arr(G).reshape(n_gen, nu)
        g = per_step(g, n_gen)
        Ain = jnp.concatenate([arr(box_A), G], axis=0)
        bin_ = jnp.concatenate([box_b, g], axis=1)
    else:
        Ain, bin_ = arr(box_A), box_b
    return ProblemData(
        A=arr(A),
        B=arr(B),
        w=w,
        x0=arr(x0),
        R=arr(R),
        C=Cs,
        Q=Qs,
        ref=refs,
        Ain=Ain,
        bin=bin_,
        lb=lb,
        ub=ub,
    )
