"""The start network: a small multilayer perceptron on the step's data, as arrays
(:class:`StartArrays`, what training differentiates) and as static data
(:class:`StartModel`, hashed by every number), with the coordinates it reads and
predicts (:func:`problem_features`, :func:`box_coordinates`)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...problem.data import ProblemData
from ..core import ADMMSolver

__all__ = [
    "FEATURE_CLIP",
    "KINDS",
    "SCHEDULE_MAX",
    "StartArrays",
    "StartModel",
    "box_coordinates",
    "input_of",
    "mlp",
    "n_features",
    "problem_features",
]

KINDS = ("step", "loop")
"""What a start network reads: the step's data, or the data and the previous iterate."""

FEATURE_CLIP = 10.0
"""Standardised inputs are clipped to +- this many training standard deviations.
Reason: a setting far outside the training data (a weight set 1e4 times its
default) would otherwise drive the tanh layers into saturation at arbitrary
points; clipped, the network sees the nearest case it knows."""

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
