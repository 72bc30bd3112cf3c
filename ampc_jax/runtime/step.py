"""The runtime's controller step: one compiled function from the bus vector to torques.

``f(leaves, bus) -> (torques, leaves, report)``: ``leaves`` is the
controller's warm state (:class:`~ampc_jax.closed_loop.controller.ControllerState`)
as a flat tuple of arrays, ``bus`` the 13-entry bus vector
(:data:`~ampc_jax.runtime.signals.BUS_FIELDS`), ``torques`` the (4,) wheel
torques [FL, FR, RL, RR] in Nm and ``report`` (iterations, status, fallback,
primal residual, dual residual). The configuration's numbers (rho, weights,
bounds) are constants of the function: one compiled step is one controller,
the same in process (:meth:`RuntimeStep.compiled`), in an exported artefact
(:mod:`~ampc_jax.runtime.artefact`) and in a replay.

Rule: the step is compiled before actuation starts (:meth:`RuntimeStep.compiled`
lowers and compiles ahead of time; calling the result never traces); reason:
a compilation inside the 50 ms loop is a missed deadline.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..closed_loop.config import NO_MPC, SimConfig
from ..closed_loop.controller import Controller, controller_for
from ..results import usable
from ..vehicle.actuators import ACTUATORS, ActuatorLimits
from .signals import BUS_FIELDS, bus_measurement

__all__ = [
    "BOUND_TOL_NM",
    "RuntimeStep",
    "StepReport",
    "clamp_to_limits",
    "command_problem",
    "config_hash",
]


class StepReport(NamedTuple):
    """What one step reports besides its torques (shapes ())."""

    iterations: Any  # int32
    status: Any  # int32 (results.STATUS)
    fallback: Any  # bool: the controller's guard replaced the solver's output
    primal_residual: Any
    dual_residual: Any
    bound_violation: Any  # Nm: how far U^(0) leaves its agents' bounds (0 within them)


BOUND_TOL_NM = 1.0
"""A step whose U^(0) leaves its bounds by more than this (Nm) is not sent."""


def config_hash(config: SimConfig, dtype: Any) -> str:
    """SHA-256 of what defines the controller: the configuration and the dtype."""
    text = json.dumps({"config": repr(config), "dtype": str(jnp.dtype(dtype))}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def command_problem(torques: np.ndarray, report: StepReport) -> str | None:
    """Why a step's torques must not be sent, or None: a fallback, a status that
    is not usable, a non-finite torque, or agent inputs U^(0) outside their
    bounds by more than :data:`BOUND_TOL_NM` (a solver that broke its own
    constraints). A wheel torque beyond its actuator's range is not a failed
    step (the stability example adds the driver's torque to the controller's):
    :func:`clamp_to_limits` clamps it, as the bridge and the simulation do."""
    t = np.asarray(torques, np.float64)
    if bool(report.fallback) or not usable(int(report.status)):
        return f"solve failed (status {int(report.status)}, fallback {bool(report.fallback)})"
    if t.shape != (4,) or not np.all(np.isfinite(t)):
        return f"non-finite torque {t.tolist()}"
    viol = float(report.bound_violation)
    if not viol <= BOUND_TOL_NM:  # NaN refuses too
        return f"U^(0) leaves its bounds by {viol:.3g} Nm"
    return None


def clamp_to_limits(
    torques: np.ndarray, limits: ActuatorLimits = ACTUATORS
) -> tuple[np.ndarray, str | None]:
    """The torques clamped to each wheel's range, and which wheels were clamped."""
    t = np.asarray(torques, np.float64)
    lo = np.array([w.min_nm for w in limits.wheels])
    hi = np.array([w.max_nm for w in limits.wheels])
    out = np.clip(t, lo, hi)
    moved = [
        f"{n} {x:.0f}" for n, x, y in zip(("FL", "FR", "RL", "RR"), t, out, strict=True) if x != y
    ]
    return out, (f"clamped {', '.join(moved)} Nm" if moved else None)


@dataclass(frozen=True)
class RuntimeStep:
    """The compiled controller step of one configuration (hashable).

    Parameters
    ----------
    config : the closed-loop configuration (example, formulation, solver options,
        settings); its ``vehicle`` is the estimator's vehicle data.
    dtype : ``"float64"`` (default) or ``"float32"``.
    """

    config: SimConfig
    dtype: str = "float64"

    def __post_init__(self) -> None:
        if self.dtype not in ("float64", "float32"):
            raise ValueError(f"dtype: expected 'float64' or 'float32', got {self.dtype!r}")
        if not self.config.mpc:
            raise ValueError(f"formulation: the runtime needs a controller, got {NO_MPC!r}")
        if self.dtype == "float64" and not jax.config.jax_enable_x64:
            raise ValueError("dtype: float64 needs jax_enable_x64 (jax.config.update)")

    @functools.cached_property
    def controller(self) -> Controller:
        return controller_for(self.config)

    @property
    def jnp_dtype(self) -> Any:
        return jnp.dtype(self.dtype)

    def init_leaves(self) -> tuple[Any, ...]:
        """The cold controller state as a flat tuple of arrays."""
        return tuple(jax.tree.leaves(self.controller.init(self.jnp_dtype)))

    @functools.cached_property
    def _treedef(self) -> Any:
        return jax.tree.structure(self.controller.init(self.jnp_dtype))

    def function(self) -> Any:
        """The pure step ``f(leaves, bus) -> (torques, leaves, report)`` (not jitted)."""
        ctrl, treedef = self.controller, self._treedef
        params = self.config.loop_params(self.jnp_dtype).controller
        vehicle = self.config.vehicle
        cols = ctrl.input_columns

        def step(leaves: tuple[Any, ...], bus: Any) -> tuple[Any, tuple[Any, ...], StepReport]:
            state = jax.tree.unflatten(treedef, leaves)
            meas, driver = bus_measurement(bus, vehicle)
            torques, state, info = ctrl.step(state, params, meas, driver)
            u0 = info.u_ctrl[cols]
            lb, ub = info.data.lb[0], info.data.ub[0]
            below = jnp.where(jnp.isfinite(lb), lb - u0, 0.0)
            above = jnp.where(jnp.isfinite(ub), u0 - ub, 0.0)
            report = StepReport(
                info.iterations.astype(jnp.int32),
                info.status.astype(jnp.int32),
                info.fallback,
                info.primal_residual,
                info.dual_residual,
                jnp.maximum(jnp.max(jnp.maximum(below, above)), 0.0),
            )
            return torques, tuple(jax.tree.leaves(state)), tuple(report)

        return step

    def example_args(self) -> tuple[tuple[Any, ...], Any]:
        """Arguments of the right shapes and dtypes (a cold state, a zero bus vector)."""
        return self.init_leaves(), jnp.zeros((len(BUS_FIELDS),), self.jnp_dtype)

    def compiled(self) -> Any:
        """The step lowered and compiled ahead of time (calls never trace)."""
        return jax.jit(self.function()).lower(*self.example_args()).compile()

    def config_hash(self) -> str:
        return config_hash(self.config, self.jnp_dtype)
