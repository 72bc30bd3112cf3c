"""A learned start of an ADMM solve: a small network's prediction of the iterate
(Z, gamma) and a per-iteration schedule (rho_k, alpha_k), on the core protocol.

After Sambharya, Hall, Amos and Stellato, "Learning to warm-start fixed-point
optimization algorithms" (JMLR 25, 2024): a network h_w maps a case's
parameters theta (here the step's :class:`~ampc_jax.problem.ProblemData`) to
the point the fixed-point iteration starts from, x^0 = h_w(theta), and w is
trained through K unrolled iterations (:mod:`ampc_jax.tuning.warm_start`). After
Sambharya and Stellato, "Learning algorithm hyperparameters for fast
parametric convex optimization" (2024): the first k iterations run with their
own (rho_i, alpha_i), the rest with the steady ones.

Two kinds of network (:data:`KINDS`), both a multilayer perceptron (tanh hidden
layers, a linear output) on standardised inputs:

* ``"step"`` -- the input is the step's data alone (:func:`problem_features`);
  the output is the inputs u (N_p x n_u), as positions in their ranges, and
  the start is built from them so that it is a fixed point when u is the
  optimum::

      u = lb + (ub - lb) clip(m + s y, 0, 1),  Z = max(0, bin - A_in u),  gamma = kkt(u)

  (Z at the fixed point is the rows' slack b - A_in u*; gamma the least-norm
  multipliers that satisfy every local step's stationarity on the rows u
  leaves active, :func:`kkt_multipliers`: their split between objectives is
  not unique, so it is not learned, and an input the network puts beyond
  its bound is exactly at it, its row active). Used for a solve without a previous iterate (``ampc solve``,
  sweeps of single steps) and, in closed loop, in place of it.
* ``"loop"`` -- the input is the step's data and the previous control step's
  iterate (shifted), and the output a correction of that iterate::

      Z = max(0, Z_prev + s_Z y_Z),   gamma = gamma_prev + s_g y_g

  with the last layer initialised at zero, so an untrained network is the
  warm start of today (the previous step's iterate). Used in closed loop.

:class:`LearnedStart` wraps a formulation as an :class:`~ampc_jax.admm.core.ADMMSolver`:
its ``setup`` also factorises the schedule's k matrices K_j(rho_i) (so a
schedule of k values costs k more factorisations per control step, each one
setup's), and its ``init`` predicts the start and runs the k scheduled
iterations (plain ADMM; a pair frozen once it meets eq.Convergence), which
count as iterations. Everything downstream of the protocol (the runners, the
sweep engine, the closed loop, an exported step) then gets the learned start.
The fixed point, and so the solution, is the formulation's own: only the
path changes.

:class:`StartModel` holds the trained numbers as NumPy arrays (static data,
hashed by a digest of every number, so that a compiled step is specialised
on one model and carries its weights as constants); :meth:`StartModel.arrays`
gives them as the :class:`StartArrays` pytree that training differentiates.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.data import ProblemData
from ..results import SolveResult
from .core import ADMMSolver
from .params import SolverParams
from .runners import still_running
from .state import ADMMState

__all__ = [
    "ACTIVE_REL",
    "FEATURE_CLIP",
    "KINDS",
    "SCHEDULE_MAX",
    "LearnedStart",
    "StartArrays",
    "StartModel",
    "StartSetup",
    "box_coordinates",
    "input_of",
    "kkt_multipliers",
    "mlp",
    "model_document",
    "model_from_document",
    "n_features",
    "problem_features",
    "start_state",
]

KINDS = ("step", "loop")
"""What a start network reads: the step's data, or the data and the previous iterate."""

FEATURE_CLIP = 10.0
"""Standardised inputs are clipped to +- this many training standard deviations.
Reason: a setting far outside the training data (a weight set 1e4 times its
default) would otherwise drive the tanh layers into saturation at arbitrary
points; clipped, the network sees the nearest case it knows."""

ACTIVE_REL = 1e-6
"""A row whose slack is within this fraction of (1 + |b_c|) is active for
:func:`kkt_multipliers` (an optimum meets its bounds to round-off)."""

SCHEDULE_MAX = 16
"""Longest per-iteration schedule (each value is one more factorisation per step)."""


def problem_features(data: ProblemData) -> Any:
    """(F,) every number of the step's data, raveled in the pytree's order, with the
    absent bounds (+-inf) read as 0: the operating point (speed, friction, steering
    and driver torque enter A, B, w, the bounds and the references; the state is x0)."""
    f = jnp.concatenate([jnp.ravel(x) for x in jax.tree.leaves(data)])
    return jnp.where(jnp.isfinite(f), f, 0.0)


def n_features(data: ProblemData) -> int:
    """Length of :func:`problem_features` for one case of ``data``'s shapes."""
    return int(sum(int(np.size(x)) for x in jax.tree.leaves(data)))


class StartArrays(NamedTuple):
    """A start network and schedule as arrays (a pytree; what training differentiates).

    layers : ((W_1, b_1), ..., (W_L, b_L)), W_l (n_(l-1), n_l).
    input_mean, input_scale : (n_in,) standardisation of the inputs.
    out_mean, out_scale, out_mask : (n_out,) the outputs' affine map and which
        entries exist (0: a multiplier of a row its objective does not carry).
    schedule_rho : (k, J) factors on ``params.rho`` of the first k iterations.
    schedule_relaxation : (k,) their over-relaxation alpha_i.
    """

    layers: tuple
    input_mean: Any
    input_scale: Any
    out_mean: Any
    out_scale: Any
    out_mask: Any
    schedule_rho: Any
    schedule_relaxation: Any


def mlp(layers: tuple, x: Any) -> Any:
    """tanh hidden layers, a linear last layer."""
    for W, b in layers[:-1]:
        x = jnp.tanh(x @ W + b)
    W, b = layers[-1]
    return x @ W + b


def _point_state(state: Any) -> ADMMState:
    if not isinstance(state, ADMMState):
        raise TypeError(
            f"learned start: expected a formulation whose iterate is an ADMMState (Local "
            f"Explicit, the integrated ADMM), got {type(state).__name__}"
        )
    return state


def box_coordinates(u: Any, data: ProblemData) -> Any:
    """(N_p, n_u) t = (u - lb) / (ub - lb) where both bounds are finite (u itself
    elsewhere): the position of each input in its range, the coordinate a
    ``"step"`` network predicts (the ranges scale with friction and speed)."""
    lb, ub = data.lb, data.ub
    box = jnp.isfinite(lb) & jnp.isfinite(ub)
    width = jnp.where(box, ub - lb, 1.0)
    width = jnp.where(width > 0, width, 1.0)
    return jnp.where(box, (u - jnp.where(box, lb, 0.0)) / width, u)


def input_of(t: Any, data: ProblemData) -> Any:
    """:func:`box_coordinates`' inverse, clipped to the bounds."""
    lb, ub = data.lb, data.ub
    box = jnp.isfinite(lb) & jnp.isfinite(ub)
    u = jnp.where(box, jnp.where(box, lb, 0.0) + jnp.where(box, ub - lb, 0.0) * t, t)
    return jnp.clip(u, lb, ub)


def kkt_multipliers(solver: ADMMSolver, setup: Any, u: Any, Z: Any, b: Any) -> Any:
    """gamma (J, N_p, R): the multipliers that make ``u`` (N_p x n_u) a fixed point.

    At a fixed point every copy is U_j = P_j u, Z = b - Abar u on the rows, and
    each local step's stationarity (eq.F3_primal) reads Abar_j' gamma_j =
    -(H_j U_j + E_j); the consensus on the slack (eq.F3_dual) gives sum_j
    gamma_jc = 0 on every row c with Z_c > 0, while on an active row the sum,
    the integrated problem's multiplier lambda_c, is free (a row is active
    when Z_c <= :data:`ACTIVE_REL` (1 + |b_c|): an input clipped to its bound
    is exactly). These conditions leave the split of lambda_c between the
    objectives free, so the least-norm solution is taken, step by step (Abar_j
    = I_(N_p) (x) A_in,j), by regularised normal equations: a start at the
    optimum's u is a fixed point, whatever split the iterates would reach, and
    nothing about the multipliers has to be learned. ``setup``: Local
    Explicit's (``Ain``, ``E``, ``hessian``); ``Z``, ``b``: (N_p, n_c).
    """
    from .layout import padded_layout

    T = solver.topology
    lay = padded_layout(T)
    J, U = lay.cols.shape
    N, n_c = T.horizon, T.n_c
    R = lay.rows.shape[1]
    dt = u.dtype
    uj = jnp.moveaxis(jnp.pad(u, ((0, 0), (0, 1)))[:, lay.cols], 1, 0)  # (J, N, U)
    g = setup.hessian.apply(uj.reshape(J, -1)[:, None])[:, 0] + setup.E
    g = jnp.moveaxis(g.reshape(J, N, U), 1, 0)  # (N, J, U)
    exists = jnp.asarray(lay.rows < n_c, dt)  # (J, R)
    Ain = setup.Ain * exists[..., None]  # (J, R, U)
    A1 = jnp.einsum("jk,jra->jakr", jnp.eye(J, dtype=dt), Ain).reshape(J * U, J * R)
    S = jnp.asarray(lay.rows[None] == np.arange(n_c)[:, None, None], dt).reshape(n_c, J * R)
    reg = 1e3 * float(jnp.finfo(dt).eps)
    inactive = (Z > ACTIVE_REL * (1.0 + jnp.abs(b))).astype(dt)

    def one(gk: Any, ik: Any) -> Any:
        M = jnp.concatenate([A1, ik[:, None] * S])
        rhs = jnp.concatenate([-gk.ravel(), jnp.zeros((n_c,), dt)])
        MM = M @ M.T
        lam = reg * (jnp.trace(MM) / MM.shape[0] + jnp.finfo(dt).tiny)
        x = M.T @ jnp.linalg.solve(MM + lam * jnp.eye(MM.shape[0], dtype=dt), rhs)
        return x.reshape(J, R) * exists

    return jnp.moveaxis(jax.vmap(one)(g, inactive), 0, 1)


def start_state(
    arrays: StartArrays,
    kind: str,
    solver: ADMMSolver,
    setup: Any,
    data: ProblemData,
    prev: Any,
) -> ADMMState:
    """The predicted start of one solve (iteration 0, residuals inf).

    ``setup``: the formulation's (the multipliers of a ``"step"`` network's u,
    :func:`kkt_multipliers`); ``prev``: the previous iterate
    (:meth:`ADMMSolver.init`'s state; the cold start when there is none), read
    by a ``"loop"`` network and kept for its U.
    """
    prev = _point_state(prev)
    feats = problem_features(data)
    if kind == "loop":
        feats = jnp.concatenate([feats, solver.point(prev)])
    x = jnp.clip((feats - arrays.input_mean) / arrays.input_scale, -FEATURE_CLIP, FEATURE_CLIP)
    y = mlp(arrays.layers, x)
    if kind == "loop":
        step = arrays.out_mean + arrays.out_scale * y
        st = solver.at(solver.point(prev) + arrays.out_mask * step, prev)
        return st._replace(Z=jnp.maximum(st.Z, 0.0))
    if kind != "step":
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    N, n_u = data.lb.shape
    out = arrays.out_mask * (arrays.out_mean + arrays.out_scale * y)
    u = input_of(out.reshape(N, n_u), data)
    Z = jnp.maximum(data.bin - u @ data.Ain.T, 0.0)
    gamma = kkt_multipliers(solver, setup, u, Z, data.bin)
    return prev._replace(Z=Z.astype(prev.Z.dtype), gamma=gamma.astype(prev.gamma.dtype))


def _frozen_digest(parts: list[Any]) -> str:
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p, np.float64)
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
        else:
            h.update(repr(p).encode())
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class StartModel:
    """A trained start network and schedule, as static data (NumPy float64, read-only).

    ``kind``: ``"step"`` or ``"loop"`` (:data:`KINDS`); ``layers``, ``input_*``,
    ``out_*``, ``schedule_*``: as :class:`StartArrays`; ``n_point``: the length of
    the solver's map argument it was trained for (:meth:`ADMMSolver.point`);
    ``objectives`` and ``horizon``: the topology it was trained for. Hashed and
    compared by :attr:`digest` (every number), so a compiled step is specialised
    on one model; ``repr`` names the digest, not the weights.
    """

    kind: str
    layers: tuple
    input_mean: np.ndarray
    input_scale: np.ndarray
    out_mean: np.ndarray
    out_scale: np.ndarray
    out_mask: np.ndarray
    schedule_rho: np.ndarray
    schedule_relaxation: np.ndarray
    n_point: int
    objectives: tuple[str, ...]
    horizon: int

    def __post_init__(self) -> None:
        def arr(x: Any) -> np.ndarray:
            a = np.array(x, dtype=np.float64)
            a.setflags(write=False)
            return a

        if self.kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {self.kind!r}")
        layers = tuple((arr(W), arr(b)) for W, b in self.layers)
        if not layers:
            raise ValueError("layers: expected at least one layer")
        object.__setattr__(self, "layers", layers)
        for name in (
            "input_mean",
            "input_scale",
            "out_mean",
            "out_scale",
            "out_mask",
            "schedule_rho",
            "schedule_relaxation",
        ):
            object.__setattr__(self, name, arr(getattr(self, name)))
        object.__setattr__(self, "objectives", tuple(self.objectives))
        object.__setattr__(self, "n_point", int(self.n_point))
        object.__setattr__(self, "horizon", int(self.horizon))
        n_in, n_out = self.input_mean.shape[0], self.out_mean.shape[0]
        prev = n_in
        for k, (W, b) in enumerate(layers):
            if W.ndim != 2 or W.shape[0] != prev or b.shape != (W.shape[1],):
                raise ValueError(
                    f"layers[{k}]: expected W ({prev}, n) and b (n,), got {W.shape} and {b.shape}"
                )
            prev = W.shape[1]
        if prev != n_out:
            raise ValueError(f"layers: the last layer gives {prev} outputs, expected {n_out}")
        for name, n in (("input_scale", n_in), ("out_scale", n_out), ("out_mask", n_out)):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name}: expected shape ({n},), got {getattr(self, name).shape}")
        k = self.schedule_relaxation.shape[0] if self.schedule_relaxation.ndim == 1 else -1
        J = len(self.objectives)
        if k < 0 or k > SCHEDULE_MAX or self.schedule_rho.shape != (k, J):
            raise ValueError(
                f"schedule: expected rho (k, {J}) and relaxation (k,) with k <= {SCHEDULE_MAX}, "
                f"got {self.schedule_rho.shape} and {self.schedule_relaxation.shape}"
            )
        numbers = [a for W, b in layers for a in (W, b)] + [
            self.input_mean,
            self.input_scale,
            self.out_mean,
            self.out_scale,
            self.out_mask,
            self.schedule_rho,
            self.schedule_relaxation,
        ]
        if not all(np.all(np.isfinite(a)) for a in numbers):
            raise ValueError("weights: every weight and scale must be finite")
        if not np.all(self.input_scale > 0):
            raise ValueError("input_scale: expected positive scales")
        if k and not (
            np.all(self.schedule_rho > 0)
            and np.all((self.schedule_relaxation > 0) & (self.schedule_relaxation < 2))
        ):
            raise ValueError("schedule: expected rho factors > 0 and relaxation in (0, 2)")
        digest = _frozen_digest([self.kind, self.n_point, self.objectives, self.horizon, *numbers])
        object.__setattr__(self, "_digest", digest)

    @property
    def digest(self) -> str:
        """SHA-256 of the kind, the sizes and every number."""
        return self._digest  # type: ignore[attr-defined]

    @property
    def schedule_length(self) -> int:
        return int(self.schedule_relaxation.shape[0])

    @property
    def n_parameters(self) -> int:
        """Number of weights and biases of the network."""
        return int(sum(W.size + b.size for W, b in self.layers))

    def __hash__(self) -> int:
        return hash(self.digest)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, StartModel) and other.digest == self.digest

    def __repr__(self) -> str:
        sizes = [self.input_mean.shape[0]] + [W.shape[1] for W, _ in self.layers]
        return (
            f"StartModel(kind={self.kind!r}, sizes={sizes}, schedule={self.schedule_length}, "
            f"sha256={self.digest[:16]})"
        )

    def arrays(self, dtype: Any = None) -> StartArrays:
        """The model as a :class:`StartArrays` pytree of ``dtype`` arrays."""
        dt = jnp.result_type(float) if dtype is None else dtype

        def a(x: np.ndarray) -> Any:
            return jnp.asarray(x, dt)

        return StartArrays(
            layers=tuple((a(W), a(b)) for W, b in self.layers),
            input_mean=a(self.input_mean),
            input_scale=a(self.input_scale),
            out_mean=a(self.out_mean),
            out_scale=a(self.out_scale),
            out_mask=a(self.out_mask),
            schedule_rho=a(self.schedule_rho),
            schedule_relaxation=a(self.schedule_relaxation),
        )

    @classmethod
    def from_arrays(cls, arrays: StartArrays, kind: str, **sizes: Any) -> StartModel:
        """A model from trained :class:`StartArrays` (``sizes``: ``n_point``,
        ``objectives``, ``horizon``)."""
        n = jax.tree.map(lambda x: np.asarray(x, np.float64), arrays)
        return cls(
            kind=kind,
            layers=n.layers,
            input_mean=n.input_mean,
            input_scale=n.input_scale,
            out_mean=n.out_mean,
            out_scale=n.out_scale,
            out_mask=n.out_mask,
            schedule_rho=n.schedule_rho,
            schedule_relaxation=n.schedule_relaxation,
            **sizes,
        )

    def mismatch(self, solver: ADMMSolver) -> str | None:
        """Why this model does not fit ``solver``'s problem (sizes, objectives,
        horizon), or None when it does."""
        T = solver.topology
        if tuple(T.objective_names) != self.objectives:
            return (
                f"trained for the objectives {list(self.objectives)}, the solver has "
                f"{list(T.objective_names)}"
            )
        if T.horizon != self.horizon:
            return f"trained for N_p = {self.horizon}, the solver has N_p = {T.horizon}"
        n_point = int(np.size(solver.point(solver.cold_state())))
        if n_point != self.n_point:
            return f"trained for an iterate of {self.n_point} numbers, the solver's has {n_point}"
        return None


_ARRAY_FIELDS = (
    ("input_mean", 1),
    ("input_scale", 1),
    ("out_mean", 1),
    ("out_scale", 1),
    ("out_mask", 1),
    ("schedule_rho", 2),
    ("schedule_relaxation", 1),
)
_DOC_KEYS = ("kind", "layers", *(k for k, _ in _ARRAY_FIELDS), "n_point", "objectives", "horizon")


def model_document(model: StartModel) -> dict[str, Any]:
    """``model`` as a JSON-ready object (arrays as nested lists of floats):
    the ``warm_start`` entry of a tuned-parameters file."""
    doc: dict[str, Any] = {
        "kind": model.kind,
        "layers": [{"W": W.tolist(), "b": b.tolist()} for W, b in model.layers],
    }
    for name, _ in _ARRAY_FIELDS:
        doc[name] = getattr(model, name).tolist()
    if model.schedule_length == 0:  # (0, J) has no list form that keeps J
        doc["schedule_rho"] = []
    doc.update(n_point=model.n_point, objectives=list(model.objectives), horizon=model.horizon)
    return doc


def _doc_array(name: str, value: Any, ndim: int) -> np.ndarray:
    def numbers(x: Any) -> bool:
        if isinstance(x, (list, tuple)):
            return all(numbers(y) for y in x)
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    if not isinstance(value, (list, tuple)) or not numbers(value):
        raise ValueError(
            f"{name}: expected a list of numbers ({ndim}-D), got a {type(value).__name__}"
        )
    try:
        a = np.asarray(value, dtype=np.float64)
    except (ValueError, OverflowError):
        raise ValueError(f"{name}: expected a rectangular {ndim}-D list of numbers") from None
    if a.ndim != ndim and not (a.size == 0 and ndim == 2):
        raise ValueError(f"{name}: expected a {ndim}-D list of numbers, got {a.ndim}-D")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite numbers")
    return a


def model_from_document(doc: Any, name: str = "warm_start") -> StartModel:
    """The :class:`StartModel` of a :func:`model_document` object (ValueError naming
    the field, ``warm_start.layers[1].W: ...``)."""
    from collections.abc import Mapping

    if not isinstance(doc, Mapping):
        raise ValueError(f"{name}: expected an object, got a {type(doc).__name__}")
    for key in doc:
        if key not in _DOC_KEYS:
            raise ValueError(f"{name}: unknown field {str(key)[:40]!r}; expected {list(_DOC_KEYS)}")
    for key in _DOC_KEYS:
        if key not in doc:
            raise ValueError(f"{name}.{key}: missing")
    layers = doc["layers"]
    if not isinstance(layers, (list, tuple)) or not layers:
        raise ValueError(f"{name}.layers: expected a non-empty list of {{W, b}} objects")
    parsed = []
    for k, layer in enumerate(layers):
        if not isinstance(layer, Mapping) or set(layer) != {"W", "b"}:
            raise ValueError(f"{name}.layers[{k}]: expected an object with W and b")
        parsed.append(
            (
                _doc_array(f"{name}.layers[{k}].W", layer["W"], 2),
                _doc_array(f"{name}.layers[{k}].b", layer["b"], 1),
            )
        )
    arrays = {k: _doc_array(f"{name}.{k}", doc[k], nd) for k, nd in _ARRAY_FIELDS}
    objectives = doc["objectives"]
    if not isinstance(objectives, (list, tuple)) or not all(isinstance(o, str) for o in objectives):
        raise ValueError(f"{name}.objectives: expected a list of objective names")
    if arrays["schedule_rho"].size == 0:
        arrays["schedule_rho"] = np.zeros((0, len(objectives)))
    for key in ("n_point", "horizon"):
        v = doc[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name}.{key}: expected an integer >= 1, got {str(v)[:40]}")
    try:
        return StartModel(
            kind=doc["kind"],
            layers=tuple(parsed),
            n_point=doc["n_point"],
            objectives=tuple(objectives),
            horizon=doc["horizon"],
            **arrays,
        )
    except ValueError as exc:
        raise ValueError(f"{name}.{exc}") from None


class StartSetup(NamedTuple):
    """:class:`LearnedStart`'s setup: the formulation's own, the schedule's k setups
    (stacked on a leading axis; None without a schedule), the step's data and the
    model's arrays (what :meth:`LearnedStart.init` predicts from)."""

    main: Any
    schedule: Any
    data: ProblemData
    arrays: StartArrays


@dataclass(frozen=True)
class LearnedStart(ADMMSolver):
    """``inner`` started from a :class:`StartModel`'s prediction and schedule.

    The core protocol delegates to ``inner`` except ``setup`` (also the
    schedule's factorisations) and ``init`` (the prediction, then the k
    scheduled iterations). With a ``"step"`` model a given ``warm`` state wins
    over the prediction; a ``"loop"`` model reads it (the cold start when none).
    """

    inner: ADMMSolver
    model: StartModel

    def __post_init__(self) -> None:
        why = self.model.mismatch(self.inner)
        if why is not None:
            raise ValueError(f"warm_start: the start network does not fit this problem: {why}")

    @property
    def topology(self) -> Any:  # type: ignore[override]
        return self.inner.topology

    @property
    def max_iter(self) -> int:  # type: ignore[override]
        return self.inner.max_iter

    @property
    def anderson(self) -> int:  # type: ignore[override]
        return self.inner.anderson

    @property
    def n_rho(self) -> int:
        return self.inner.n_rho

    def __getattr__(self, name: str) -> Any:
        # the formulation's own views (local_inputs, multipliers, state_of, kkt, ...)
        if name.startswith("__") or name in ("inner", "model"):
            raise AttributeError(name)
        return getattr(self.inner, name)

    def setup_with(
        self, data: ProblemData, params: SolverParams | None, arrays: StartArrays
    ) -> Any:
        """:meth:`setup` with the model's numbers given as ``arrays`` (for training)."""
        n_in = n_features(data) + (self.model.n_point if self.model.kind == "loop" else 0)
        if self.model.input_mean.shape[0] != n_in:
            raise ValueError(
                f"warm_start: the start network reads {self.model.input_mean.shape[0]} "
                f"inputs, this problem's step gives {n_in} (trained for another problem)"
            )
        dt = data.A.dtype
        p = self.inner.params(dtype=dt) if params is None else params
        main = self.inner.setup(data, p)
        sched = None
        if arrays.schedule_rho.shape[0]:
            rho = jnp.asarray(p.rho, dt)

            def one(r: Any, a: Any) -> Any:
                return self.inner.setup(data, p._replace(rho=rho * r, relaxation=a))

            sched = jax.vmap(one)(arrays.schedule_rho, arrays.schedule_relaxation)
        return StartSetup(main, sched, data, arrays)

    def setup(self, data: ProblemData, params: SolverParams | None = None) -> StartSetup:
        """The formulation's setup, the schedule's k setups and the model's arrays."""
        return self.setup_with(data, params, self.model.arrays(data.A.dtype))

    def init(self, setup: StartSetup, warm: Any = None) -> Any:
        """The predicted start, then the scheduled iterations (counted)."""
        prev = self.inner.init(setup.main, warm)
        if self.model.kind == "step" and warm is not None:
            start = prev
        else:
            start = start_state(
                setup.arrays, self.model.kind, self.inner, setup.main, setup.data, prev
            )
        if setup.schedule is None:
            return start

        def body(st: Any, s_k: Any) -> tuple[Any, None]:
            go = still_running(
                st, lambda x: self.inner.converged(setup.main, x), self.inner.max_iter
            )
            new = self.inner.step(s_k, st)
            return jax.tree.map(lambda a, b: jnp.where(go, a, b), new, st), None

        return jax.lax.scan(body, start, setup.schedule)[0]

    def step(self, setup: StartSetup, state: Any) -> Any:
        return self.inner.step(setup.main, state)

    def converged(self, setup: StartSetup, state: Any) -> Any:
        return self.inner.converged(setup.main, state)

    def result(self, setup: StartSetup, state: Any) -> SolveResult:
        return self.inner.result(setup.main, state)

    def point(self, state: Any) -> Any:
        return self.inner.point(state)

    def at(self, x: Any, state: Any) -> Any:
        return self.inner.at(x, state)

    def cold_state(self, dtype: Any = None) -> Any:
        return self.inner.cold_state(dtype)

    def shift(self, state: Any, steps: int = 1) -> Any:
        return self.inner.shift(state, steps)
