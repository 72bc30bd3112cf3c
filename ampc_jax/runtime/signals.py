"""What travels on the bus each tick, and the measurement built from it.

The controller's measurement (:class:`~ampc_jax.vehicle.params.Measurement`)
holds tyre forces, loads and slips, which no vehicle's bus carries. Rule: the
bus carries what a production vehicle's sensors give (speeds and yaw rate
from the ESC, wheel speeds, the steering angle, the IMU's accelerations, the
driver's torque request and cruise set speed, a road-friction estimate), and
:func:`bus_measurement` estimates the rest with the plant's own tyre model at
the measured slips and the loads the measured accelerations transfer; reason:
a real vehicle runs the same estimator, and the simulated closed loop's
measurement (:func:`~ampc_jax.vehicle.plant.measure`) is this very function of
the same seven states, so a run over the bus and a simulation differ only by
the signals' resolution and age (docs/runtime.md, "What the bus carries").

The bus vector: 13 float values in :data:`BUS_FIELDS` order, the one input of
the compiled runtime step, of the exported artefact and of a replay.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..closed_loop.controller import DriverInputs
from ..vehicle.params import WHEELS, Measurement, VehicleParams
from ..vehicle.plant import PlantState, measure

__all__ = [
    "BUS_FIELDS",
    "MESSAGES",
    "bus_from_bridge",
    "bus_measurement",
    "bus_vector",
    "message_values",
]

BUS_FIELDS = (
    "v_x",
    "v_y",
    "yaw_rate",
    "omega_FL",
    "omega_FR",
    "omega_RL",
    "omega_RR",
    "steer",
    "a_x",
    "a_y",
    "driver_torque",
    "v_ref",
    "mu",
)
"""The bus vector's entries (SI units; wheels FL, FR, RL, RR)."""

MESSAGES: dict[str, dict[str, str]] = {
    "VehicleMotion": {"LongSpeed": "v_x", "LatSpeed": "v_y", "YawRate": "yaw_rate"},
    "WheelSpeeds": {
        "WheelSpeedFL": "omega_FL",
        "WheelSpeedFR": "omega_FR",
        "WheelSpeedRL": "omega_RL",
        "WheelSpeedRR": "omega_RR",
    },
    "SteeringState": {"SteeringAngle": "steer"},
    "VehicleAccel": {"LongAccel": "a_x", "LatAccel": "a_y"},
    "DriverDemand": {"DriverTorque": "driver_torque", "SetSpeed": "v_ref", "RoadFriction": "mu"},
}
"""The DBC's state messages: signal -> bus-vector entry."""

_BRIDGE_KEYS = {
    "v_x": "long_speed_mps",
    "v_y": "lat_speed_mps",
    "yaw_rate": "yaw_rate_radps",
    "steer": "steering_angle_rad",
    "a_x": "long_accel_mps2",
    "a_y": "lat_accel_mps2",
    "driver_torque": "driver_torque_nm",
    "v_ref": "set_speed_mps",
    "mu": "road_friction",
}


def bus_vector(
    state: PlantState, steer: Any, driver_torque: Any, v_ref: Any, mu: Any
) -> np.ndarray:
    """The bus vector of a plant state and the driver's inputs (float64, exact)."""
    om = np.asarray(state.omega, np.float64)
    vals = [state.v_x, state.v_y, state.r, *om, steer, state.a_x, state.a_y]
    return np.array([*map(float, vals), float(driver_torque), float(v_ref), float(mu)])


def message_values(bus: np.ndarray) -> dict[str, dict[str, float]]:
    """Per DBC message, its signals' values from a bus vector (what a sensor node sends)."""
    idx = {name: i for i, name in enumerate(BUS_FIELDS)}
    return {
        msg: {sig: float(bus[idx[field]]) for sig, field in sigs.items()}
        for msg, sigs in MESSAGES.items()
    }


def bus_from_bridge(state: dict[str, Any]) -> tuple[np.ndarray | None, str | None]:
    """The bus vector of ``can_bridge.Bridge.latest_state()``, or ``(None, why)``.

    None unless the bridge calls the state valid (every message fresh and its
    E2E stream sound) and every value is present and finite."""
    if not state.get("valid", False):
        return None, f"state invalid: {state.get('reason') or 'no reason given'}"
    out = np.empty(len(BUS_FIELDS))
    wheels = state.get("wheel_speeds_radps")
    for i, name in enumerate(BUS_FIELDS):
        if name.startswith("omega_"):
            v = None if wheels is None else wheels[WHEELS.index(name[6:])]
        else:
            v = state.get(_BRIDGE_KEYS[name])
        if v is None or not np.isfinite(v):
            return None, f"state value {name} missing or not finite ({v!r})"
        out[i] = float(v)
    return out, None


def bus_measurement(bus: Array, vehicle: VehicleParams) -> tuple[Measurement, DriverInputs]:
    """The estimator: measurement and driver inputs from a bus vector (pure JAX).

    Speeds, yaw rate, wheel speeds and accelerations are measured; vertical
    loads follow from the accelerations (quasi-static load transfer), slips and
    slip angles from the speeds, wheel speeds and steering angle, and the tyre
    forces from the tyre model at those slips, loads and the friction estimate
    (:func:`~ampc_jax.vehicle.plant.measure` on the measured states).
    """
    bus = jnp.asarray(bus)
    z = jnp.zeros((), bus.dtype)
    ps = PlantState(z, z, z, bus[0], bus[1], bus[2], bus[3:7], bus[8], bus[9])
    steer, mu = bus[7], bus[12]
    meas = measure(ps, steer, jnp.zeros(4, bus.dtype), mu, vehicle)
    return meas, DriverInputs(steer=steer, driver_torque=bus[10], v_ref=bus[11], mu=mu)
