"""The actuators' limits: one contract for the controller, the bridge and the bus.

Rule: every torque limit of the vehicle lives here, and the rest derives
from it; reason: the controller, the CAN bridge and the DBC disagreeing is a
torque the controller plans and the vehicle never gets (or one the bridge
clamps without saying). What derives from :data:`ACTUATORS`:

* the vehicle examples' agent bounds (``CruiseSettings``, ``StabilitySettings``:
  front brakes in ``[FRONT_MIN_NM, 0]``, ``|DTR/2| + |RTV|`` within a rear
  wheel's range);
* the bridge's configuration (:func:`bridge_kwargs`, passed to
  ``can_bridge.Bridge``; the bridge's shipped ``vehicle.toml`` must equal it),
  including the geometry of its wheel/vehicle speed check
  (:func:`wheel_geometry`) and the floor under its rate-of-change limits
  (:func:`signal_rate_bounds`: the fastest each received signal can change
  for this vehicle, which the shipped limits must not undercut);
* the DBC's torque signals, whose range must hold every limit (2 Nm steps);
* the actuators' command timeout (:attr:`ActuatorLimits.timeout_ms`: 0 Nm
  after that long without a valid frame), which the simulated vehicle
  (``ampc plant``) applies and from which the bridge derives when a gap in
  transmission restarts its ramp (``actuator_timeout_ms``).

``tests/vehicle/test_actuators.py`` fails when any of them disagrees.

:func:`bridge_actuators` is the bridge's limiter as a pure JAX function (the
rules of ``can_bridge/src/safety.rs``: a target rounded half-to-even onto the
2 Nm grid, clamped to the wheel's range rounded toward zero, moved by at most
the rise step away from zero and the release step toward zero per tick, never
across zero in one tick), so a simulated closed loop applies the torques a run
over the bus applies (``SimConfig(actuators="bridge")``).
"""

from __future__ import annotations

import math
import tomllib
from os import PathLike
from typing import Any, NamedTuple

import jax.numpy as jnp
from jax import Array

from .params import CONTROL_DT, WHEELS, VehicleParams

__all__ = [
    "ACTUATORS",
    "FRONT_MIN_NM",
    "MU_MAX",
    "REAR_MAX_NM",
    "TORQUE_STEP_NM",
    "ActuatorLimits",
    "WheelLimits",
    "bridge_actuators",
    "bridge_kwargs",
    "load_limits",
    "signal_rate_bounds",
    "wheel_geometry",
]

TORQUE_STEP_NM = 2.0
"""Resolution of the DBC's torque signals (Nm): the bridge works on this grid."""


class WheelLimits(NamedTuple):
    """One wheel's actuator: range (Nm, negative brakes) and rates (Nm/s)."""

    min_nm: float
    max_nm: float
    rise_nm_per_s: float  # |torque| increasing
    release_nm_per_s: float  # |torque| decreasing


class ActuatorLimits(NamedTuple):
    """The four wheels' actuators, [FL, FR, RL, RR], the command period and
    the command timeout: an actuator that has had no valid frame for
    ``timeout_ms`` applies 0 Nm (and the bridge restarts its ramp from zero
    after any gap the actuator may have acted on)."""

    wheels: tuple[WheelLimits, WheelLimits, WheelLimits, WheelLimits]
    period_ms: float = 1e3 * CONTROL_DT
    timeout_ms: float = 200.0

    def steps(self) -> dict[str, Array]:
        """The limits on the 2 Nm grid as integer steps per tick (the bridge's rule)."""
        q = TORQUE_STEP_NM
        dt = self.period_ms * 1e-3
        w = self.wheels
        return {
            "min": jnp.array([math.ceil(x.min_nm / q) for x in w], jnp.int32),
            "max": jnp.array([math.floor(x.max_nm / q) for x in w], jnp.int32),
            "rise": jnp.array([max(1, math.floor(x.rise_nm_per_s * dt / q)) for x in w]),
            "release": jnp.array([max(1, math.floor(x.release_nm_per_s * dt / q)) for x in w]),
        }


FRONT_MIN_NM = -2000.0
"""Front wheels brake only, down to -2000 Nm (a locked wheel at mu = 1, Table I loads)."""

REAR_MAX_NM = 2000.0
"""Rear wheels drive and brake up to +-2000 Nm (what a rear tyre transmits at mu = 1)."""

_RISE, _RELEASE = 10000.0, 20000.0

ACTUATORS = ActuatorLimits(
    wheels=(
        WheelLimits(FRONT_MIN_NM, 0.0, _RISE, _RELEASE),
        WheelLimits(FRONT_MIN_NM, 0.0, _RISE, _RELEASE),
        WheelLimits(-REAR_MAX_NM, REAR_MAX_NM, _RISE, _RELEASE),
        WheelLimits(-REAR_MAX_NM, REAR_MAX_NM, _RISE, _RELEASE),
    )
)
"""The vehicle examples' actuators (docs/vehicle.md, "Actuator bounds"); rates
10,000 Nm/s rising and 20,000 Nm/s releasing (500 and 1,000 Nm per 50 ms tick)."""


def load_limits(path: str | PathLike[str]) -> ActuatorLimits:
    """Read the actuator limits from a bridge configuration file (``vehicle.toml``
    schema: ``period_ms``, ``actuator_timeout_ms`` and ``[wheels.FL]`` ...
    ``[wheels.RR]`` with ``min_nm``,
    ``max_nm``, ``rise_nm_per_s``, ``release_nm_per_s``; a missing key keeps
    :data:`ACTUATORS`' value). ValueError naming the key otherwise."""
    with open(path, "rb") as f:
        cfg = tomllib.load(f)
    wheels_cfg = cfg.get("wheels", {})
    if not isinstance(wheels_cfg, dict):
        raise ValueError(f"{path}: wheels: expected a table per wheel {WHEELS}")
    unknown = sorted(set(wheels_cfg) - set(WHEELS))
    if unknown:
        raise ValueError(f"{path}: wheels: unknown wheel(s) {unknown}; expected {WHEELS}")
    wheels = []
    for name, default in zip(WHEELS, ACTUATORS.wheels, strict=True):
        w = wheels_cfg.get(name, {})
        vals = {}
        for field in WheelLimits._fields:
            v = w.get(field, getattr(default, field))
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{path}: wheels.{name}.{field}: expected a number, got {v!r}")
            vals[field] = float(v)
        if not vals["min_nm"] <= 0.0 <= vals["max_nm"]:
            raise ValueError(f"{path}: wheels.{name}: expected min_nm <= 0 <= max_nm")
        wheels.append(WheelLimits(**vals))
    scalars = {}
    for key, default in (
        ("period_ms", ACTUATORS.period_ms),
        ("actuator_timeout_ms", ACTUATORS.timeout_ms),
    ):
        v = cfg.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ValueError(f"{path}: {key}: expected a positive number, got {v!r}")
        scalars[key] = float(v)
    return ActuatorLimits(
        tuple(wheels),  # type: ignore[arg-type]
        scalars["period_ms"],
        scalars["actuator_timeout_ms"],
    )


MU_MAX = 2.0
"""The highest road friction the bus can report (the DBC's ``RoadFriction`` maximum)."""


def wheel_geometry(vehicle: VehicleParams | None = None) -> dict[str, float]:
    """The geometry of the bridge's wheel/vehicle speed check (``rx_wheels``).

    A wheel that brakes only cannot turn faster than the road under it; the
    bridge bounds its circumferential speed ``|omega| R_w`` by the vehicle's
    speed at that wheel, ``|v_x| + |r| T_w/2 + (|v_y| + |r| a) |delta|``, plus
    its tolerances (``can_bridge/src/plausibility.rs``)."""
    p = VehicleParams() if vehicle is None else vehicle
    return {"radius_m": float(p.R_w), "track_m": float(p.T_w), "cg_to_front_m": float(p.a)}


def signal_rate_bounds(
    vehicle: VehicleParams | None = None,
    limits: ActuatorLimits = ACTUATORS,
    mu_max: float = MU_MAX,
) -> dict[str, float]:
    """The fastest each received signal of the vehicle's motion can change (per s).

    The bridge refuses a received value that moved faster than its limit
    (``vehicle.toml``, ``[rx_max_rate]``); these bounds are the physics under
    those limits, so a real vehicle's signal is never refused:

    * ``LongSpeed``: the tyres' grip, ``mu_max g``;
    * ``LatSpeed``: ``dv_y/dt = a_y - r v_x``, each at most ``mu_max g``;
    * ``YawRate``: all lateral grip on the longer axle arm plus the largest
      torque difference across the track, over ``I_z``;
    * ``WheelSpeed*``: a wheel's largest torque plus the grip of half the
      vehicle's weight on it, over ``I_w``.
    """
    p = VehicleParams() if vehicle is None else vehicle
    g_mu = mu_max * p.g
    t_max = max(max(abs(w.min_nm), abs(w.max_nm)) for w in limits.wheels)
    yaw = (g_mu * p.m * max(p.a, p.b) + 2.0 * t_max / p.R_w * p.T_w / 2.0) / p.I_z
    wheel = (t_max + g_mu * p.m / 2.0 * p.R_w) / p.I_w
    out = {"LongSpeed": g_mu, "LatSpeed": 2.0 * g_mu, "YawRate": yaw}
    out.update({f"WheelSpeed{w}": wheel for w in WHEELS})
    return out


def bridge_kwargs(
    limits: ActuatorLimits = ACTUATORS, vehicle: VehicleParams | None = None
) -> dict[str, Any]:
    """``can_bridge.Bridge`` keyword arguments that give the bridge these limits
    and the vehicle's geometry for its wheel/vehicle speed check."""
    w = limits.wheels
    return {
        "period_ms": float(limits.period_ms),
        "actuator_timeout_ms": float(limits.timeout_ms),
        "torque_min_nm": [x.min_nm for x in w],
        "torque_max_nm": [x.max_nm for x in w],
        "rise_nm_per_s": [x.rise_nm_per_s for x in w],
        "release_nm_per_s": [x.release_nm_per_s for x in w],
        "rx_wheels": wheel_geometry(vehicle),
    }


def bridge_actuators(
    prev_steps: Array, target: Array, limits: ActuatorLimits = ACTUATORS
) -> tuple[Array, Array]:
    """One tick of the bridge's limiter (``safety.rs``, ``Limiter::follow``).

    Parameters
    ----------
    prev_steps : (4,) int32, the previous output in 2 Nm steps.
    target : (4,) float, the commanded torques (Nm); non-finite entries hold
        the previous output (the bridge refuses such a command).

    Returns
    -------
    (steps, torques) : the new output in steps, and in Nm (dtype of ``target``).
    """
    g = limits.steps()
    q = TORQUE_STEP_NM
    finite = jnp.isfinite(target)
    want = jnp.round(jnp.where(finite, target, 0.0) / q).astype(jnp.int32)  # half to even
    want = jnp.clip(want, g["min"], g["max"])
    want = jnp.where(finite, want, prev_steps)
    y = prev_steps
    sign = jnp.sign(y)
    up = jnp.where(sign < 0, g["release"], g["rise"])
    down = jnp.where(sign > 0, g["release"], g["rise"])
    nxt = y + jnp.clip(want - y, -down, up)
    crossed = ((y > 0) & (nxt < 0)) | ((y < 0) & (nxt > 0))
    nxt = jnp.clip(jnp.where(crossed, 0, nxt), g["min"], g["max"]).astype(jnp.int32)
    return nxt, (nxt * q).astype(target.dtype)
