"""The user-facing problem description: agents, objectives, constraints, validated.

The paper's section "Multi-objective MACS" (Notation) and the integrated MPC
(eq.integMPC, eq_linear), on the shared model::

    X^(k+1) = A_d X^(k) + sum_i B_d(i) U_(i)^(k) + W_d^(k)
    h_j = || C_j X^(k) - ref_j^(k) ||^2_{Q_j},   g_(i) = || U_(i)^(k) ||^2_{R_(i)}
    A_in U^(k) <= b_in^(k)

:class:`Problem` is built from a JSON problem file, a ``dict`` or Python
objects; every validation error is a :class:`ProblemError` naming the
offending field. Its :attr:`Problem.topology` (static) and
:meth:`Problem.data` (arrays) are what the solvers take.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .data import ProblemData, make_data
from .errors import ProblemError, ProblemWarning
from .limits import MAX_MAGNITUDE, check_memory, log10_norm, max_power_log10
from .topology import Topology

__all__ = ["Agent", "Constraint", "GROUP_TOL", "Objective", "Problem"]

#: Relative tolerance of the model-derived agent groups: agent i is in S_j when
#: ||C_j A_d^k B_d(i)||_F > GROUP_TOL * ||C_j||_F ||A_d^k||_F ||B_d(i)||_F for
#: some k < N_p.
GROUP_TOL = 1e-10


# ----------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------


def _show(value: Any, width: int = 80) -> str:
    """``repr(value)`` cut to ``width`` characters; safe for any value (an
    integer beyond Python's 4,300-digit limit, lists nested past the recursion
    limit)."""
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        text = f"<a {type(value).__name__} too large to print>"
    return text if len(text) <= width else text[: width - 3] + "..."


def _non_number(value: Any, depth: int = 2) -> str | None:
    """What is wrong with nested lists of numbers at most ``depth`` deep: the
    first entry that is not a number (a string, a boolean, null), or nesting
    deeper than ``depth`` (every field is a number, vector or matrix); None
    when every entry is one. Iterative: any nesting is safe."""
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        v, level = stack.pop()
        if isinstance(v, (str, bytes, bool, np.bool_)) or v is None:
            return repr(v)[:40] if v is not None else "null"
        if isinstance(v, np.ndarray):
            if v.ndim + level > depth:
                return f"an array nested {v.ndim + level} deep (at most {depth}: a matrix)"
            if v.dtype.kind in "biufc":
                if v.dtype.kind == "b":
                    return "a boolean array"
                continue
            v = v.tolist()
        if isinstance(v, (list, tuple)):
            if level >= depth:
                return f"lists nested deeper than {depth} (a matrix at most)"
            stack.extend((x, level + 1) for x in reversed(v))
    return None


def _magnitude(arr: np.ndarray, field_name: str) -> None:
    """ProblemError naming ``field_name`` when a finite entry exceeds MAX_MAGNITUDE."""
    finite = arr[np.isfinite(arr)]
    if finite.size and float(np.max(np.abs(finite))) > MAX_MAGNITUDE:
        big = float(np.max(np.abs(finite)))
        raise ProblemError(
            f"{field_name}: an entry of magnitude {big:.3g}; every entry must be within "
            f"+-{MAX_MAGNITUDE:.0e} (the solver squares them: H_j = 2 (Y_u' Qbar Y_u + Rbar) "
            f"and the squared residuals of eq.Convergence overflow float64 beyond 1.3e154); "
            f"rescale the units"
        )


def _array(value: Any, field_name: str) -> np.ndarray:
    if value is None:
        raise ProblemError(f"{field_name}: a number or array is required, got nothing")
    bad = _non_number(value)
    if bad is not None:
        raise ProblemError(f"{field_name}: expected numbers, got {bad:.80}")
    try:
        arr = np.asarray(value, dtype=float)
    except OverflowError:
        raise ProblemError(
            f"{field_name}: an integer beyond float64's range (1.8e308); every entry must "
            f"be within +-{MAX_MAGNITUDE:.0e}"
        ) from None
    except (TypeError, ValueError) as exc:
        raise ProblemError(
            f"{field_name}: expected numbers (nested lists, row-major), got {_show(value)}"
        ) from exc
    if not np.all(np.isfinite(arr)):
        bad = "NaN" if np.any(np.isnan(arr)) else "inf"
        raise ProblemError(f"{field_name}: contains {bad}; every entry must be a finite number")
    _magnitude(arr, field_name)
    return arr


def _bound(value: Any, field_name: str, n: int, side: str, hint: str = "") -> np.ndarray:
    """Bounds may be -inf (``side="lower"``) or +inf (upper): no row; never
    NaN, and never the infinity that no input can satisfy."""
    bad = _non_number(value, depth=1)
    if bad is not None:
        raise ProblemError(
            f"{field_name}: expected {n} numbers, got {bad:.80} (no bound: leave the "
            f"field out, or JSON -Infinity / Infinity)"
        )
    try:
        arr = np.asarray(value, dtype=float)
    except OverflowError:
        raise ProblemError(
            f"{field_name}: an integer beyond float64's range (no bound: +-inf)"
        ) from None
    except (TypeError, ValueError) as exc:
        raise ProblemError(f"{field_name}: expected {n} numbers, got {_show(value)}") from exc
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
    _magnitude(arr, field_name)
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
        raise ProblemError(f"{field_name}: expected a non-empty string name, got {_show(value)}")
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
        (paper-notes item 19).
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
        cons_in = d.get("constraints") or []
        if not isinstance(cons_in, list):
            raise ProblemError("constraints: expected a list of objects with keys A and b")
        for c, con in enumerate(cons_in):
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
        except UnicodeDecodeError as exc:
            raise ProblemError(f"problem file {path}: not UTF-8 text ({exc.reason})") from None
        try:
            d = json.loads(text)
        except RecursionError:
            raise ProblemError(
                f"problem file {path}: lists or objects nested deeper than a JSON reader "
                f"follows; a field is at most a matrix (lists two deep)"
            ) from None
        except ValueError as exc:  # JSONDecodeError, or an integer of over 4,300 digits
            raise ProblemError(f"problem file {path}: not valid JSON ({exc})") from None
        return cls.from_dict(d)

    def __post_init__(self) -> None:
        horizon = self.horizon
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ProblemError(f"horizon: expected an integer >= 1, got {_show(horizon)}")
        horizon = int(horizon)
        A = _array(self.A, "A")
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ProblemError(f"A: expected a square n_x x n_x matrix, got shape {A.shape}")
        nx = A.shape[0]
        x0 = _array(self.x0, "x0")
        x0 = x0.reshape(-1) if x0.ndim <= 1 else x0
        if x0.shape != (nx,):
            raise ProblemError(f"x0: expected {nx} numbers (n_x from A), got shape {x0.shape}")

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

        # the objectives' sizes and weights first: nothing of horizon size is
        # formed before the memory estimate has passed (limits.check_memory)
        obj_names: list[str] = []
        Cs, Qs = [], []
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
            Cs.append(C)
            Qs.append(_weight(o.Q, f"objectives[{j}].Q ({name})", ny, definite=False, hint=hint))
        if not obj_names:
            raise ProblemError("objectives: at least one objective is required")
        check_memory(
            horizon=horizon, n_x=nx, n_u=sum(B.shape[1] for B in Bs), n_y=[C.shape[0] for C in Cs]
        )
        log_power = max_power_log10(A, horizon)
        _check_hessian_scales(A, Bs, names, Cs, Qs, obj_names, log_power, horizon)
        w = _per_step(self.w, "w", nx, horizon)

        refs, groups = [], []
        powers = [np.linalg.matrix_power(A, k) for k in range(horizon)]
        for j, o in enumerate(self.objectives):
            name, C = obj_names[j], Cs[j]
            hint = f" (n_y = {C.shape[0]}: the rows of objectives[{j}].C)"
            ref = _per_step(o.ref, f"objectives[{j}].ref ({name})", C.shape[0], horizon, hint=hint)
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
                    if not isinstance(a_name, str) or a_name not in names:
                        raise ProblemError(
                            f"objectives[{j}].agents ({name}): unknown agent {_show(a_name)}; "
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
                        ProblemWarning,
                        stacklevel=3,
                    )
            refs.append(ref)
            groups.append(group)
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
                if not isinstance(a_name, str) or a_name not in names:
                    raise ProblemError(
                        f"constraints[{c}].A: unknown agent {_show(a_name)}; "
                        f"known agents are {names}"
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


def _check_hessian_scales(
    A: np.ndarray,
    Bs: list[np.ndarray],
    agent_names: list[str],
    Cs: list[np.ndarray],
    Qs: list[np.ndarray],
    obj_names: list[str],
    log_power: float,
    horizon: int,
) -> None:
    """ProblemError naming the largest factor when some condensed Hessian
    H_j = 2 (Y_u' Qbar_j Y_u + Rbar) would exceed MAX_MAGNITUDE: its scale is
    ||Q_j|| ||C_j||^2 max_k ||A^k||^2 max_i ||B_(i)||^2 (Frobenius norms, in logs)."""
    limit = math.log10(MAX_MAGNITUDE)
    log_b = [log10_norm(B) for B in Bs]
    ib = int(np.argmax(log_b))
    for j, (C, Q) in enumerate(zip(Cs, Qs, strict=True)):
        parts = {
            f"objectives[{j}].Q ({obj_names[j]})": log10_norm(Q),
            f"objectives[{j}].C ({obj_names[j]})": 2 * log10_norm(C),
            "A": 2 * log_power,
            f"agents[{ib}].B ({agent_names[ib]})": 2 * log_b[ib],
        }
        if any(v == -math.inf for v in parts.values()):
            continue  # a zero factor: H_j = 2 Rbar
        total = sum(parts.values())
        if total <= limit:
            continue
        field_name = max(parts, key=lambda k: parts[k])
        what = (
            f"max_k ||A^k|| over the horizon (N_p = {horizon}) reaches 1e{log_power:.0f}"
            if field_name == "A"
            else f"its norm is 1e{parts[field_name] / (1 if '.Q' in field_name else 2):.0f}"
        )
        raise ProblemError(
            f"{field_name}: {what}, so the condensed Hessian of objectives[{j}] "
            f"({obj_names[j]}), ||Q_j|| ||C_j||^2 max_k ||A^k||^2 ||B||^2, reaches about "
            f"1e{total:.0f}, beyond 1e{limit:.0f} (the squared residuals of eq.Convergence "
            f"overflow float64); rescale the units or shorten the horizon"
        )
