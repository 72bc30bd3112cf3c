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

The bus vector: the 13 values of :class:`BusVector` in its field order, the
one input of the compiled runtime step, of the exported artefact and of a
replay. :data:`SIGNALS` names each field in the DBC and in the bridge's
``latest_state()``, so no other module spells a signal or an index.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..closed_loop.controller import DriverInputs
from ..vehicle.params import WHEELS, Measurement, VehicleParams
from ..vehicle.plant import PlantState, measure

__all__ = [
    "BUS_FIELDS",
    "MESSAGES",
    "SIGNALS",
    "BusSignal",
    "BusVector",
    "bus_from_bridge",
    "bus_measurement",
    "bus_vector",
    "message_values",
]


class BusVector(NamedTuple):
    """The 13 values the bus carries each tick, by name (SI units; wheels FL,
    FR, RL, RR). The one record of the bus's signals: :data:`SIGNALS` gives
    each field's DBC message and signal and its key in
    ``can_bridge.Bridge.latest_state()``; the flat vector every compiled step,
    artefact and replay takes is its fields in this order
    (:meth:`as_array`, :meth:`of`)."""

    v_x: Any
    v_y: Any
    yaw_rate: Any
    omega_FL: Any
    omega_FR: Any
    omega_RL: Any
    omega_RR: Any
    steer: Any
    a_x: Any
    a_y: Any
    driver_torque: Any
    v_ref: Any
    mu: Any

    @classmethod
    def of(cls, vec: Any) -> BusVector:
        """The record viewing a flat (13,) vector (numpy or JAX; no copy of the values)."""
        return cls(*(vec[i] for i in range(len(cls._fields))))

    def as_array(self) -> np.ndarray:
        """The flat float64 vector, fields in order."""
        return np.array([float(v) for v in self], np.float64)

    @property
    def omega(self) -> tuple[Any, Any, Any, Any]:
        """Wheel speeds in :data:`~ampc_jax.vehicle.params.WHEELS` order."""
        return tuple(getattr(self, f"omega_{w}") for w in WHEELS)


class BusSignal(NamedTuple):
    """Where one :class:`BusVector` field travels: its DBC message and signal,
    the bridge's ``latest_state()`` key (with the entry of a per-wheel tuple),
    and its unit as the DBC writes it ("" for none)."""

    field: str
    message: str
    signal: str
    bridge_key: str
    bridge_index: int | None
    unit: str


SIGNALS: tuple[BusSignal, ...] = (
    BusSignal("v_x", "VehicleMotion", "LongSpeed", "long_speed_mps", None, "m/s"),
    BusSignal("v_y", "VehicleMotion", "LatSpeed", "lat_speed_mps", None, "m/s"),
    BusSignal("yaw_rate", "VehicleMotion", "YawRate", "yaw_rate_radps", None, "rad/s"),
    *(
        BusSignal(f"omega_{w}", "WheelSpeeds", f"WheelSpeed{w}", "wheel_speeds_radps", i, "rad/s")
        for i, w in enumerate(WHEELS)
    ),
    BusSignal("steer", "SteeringState", "SteeringAngle", "steering_angle_rad", None, "rad"),
    BusSignal("a_x", "VehicleAccel", "LongAccel", "long_accel_mps2", None, "m/s2"),
    BusSignal("a_y", "VehicleAccel", "LatAccel", "lat_accel_mps2", None, "m/s2"),
    BusSignal("driver_torque", "DriverDemand", "DriverTorque", "driver_torque_nm", None, "Nm"),
    BusSignal("v_ref", "DriverDemand", "SetSpeed", "set_speed_mps", None, "m/s"),
    BusSignal("mu", "DriverDemand", "RoadFriction", "road_friction", None, ""),
)
"""Every bus signal's names in the four places it appears (the record's field,
the DBC's message and signal, the bridge's key), in :class:`BusVector` order."""

BUS_FIELDS: tuple[str, ...] = BusVector._fields
"""The bus vector's entries, :class:`BusVector`'s fields."""


def _messages() -> dict[str, dict[str, str]]:
    out: dict[str, dict[str, str]] = {}
    for sig in SIGNALS:
        out.setdefault(sig.message, {})[sig.signal] = sig.field
    return out


MESSAGES: dict[str, dict[str, str]] = _messages()
"""The DBC's state messages: signal -> bus-vector entry (derived from :data:`SIGNALS`)."""


def bus_vector(
    state: PlantState, steer: Any, driver_torque: Any, v_ref: Any, mu: Any
) -> np.ndarray:
    """The bus vector of a plant state and the driver's inputs (float64, exact)."""
    om = np.asarray(state.omega, np.float64)
    return BusVector(
        state.v_x, state.v_y, state.r, *om, steer, state.a_x, state.a_y, driver_torque, v_ref, mu
    ).as_array()


def message_values(bus: np.ndarray) -> dict[str, dict[str, float]]:
    """Per DBC message, its signals' values from a bus vector (what a sensor node sends)."""
    out: dict[str, dict[str, float]] = {}
    for i, sig in enumerate(SIGNALS):
        out.setdefault(sig.message, {})[sig.signal] = float(bus[i])
    return out


def bus_from_bridge(state: dict[str, Any]) -> tuple[np.ndarray | None, str | None]:
    """The bus vector of ``can_bridge.Bridge.latest_state()``, or ``(None, why)``.

    None unless the bridge calls the state valid (every message fresh and its
    E2E stream sound) and every value is present and finite."""
    if not state.get("valid", False):
        return None, f"state invalid: {state.get('reason') or 'no reason given'}"
    out = np.empty(len(SIGNALS))
    for i, sig in enumerate(SIGNALS):
        v = state.get(sig.bridge_key)
        if v is not None and sig.bridge_index is not None:
            v = v[sig.bridge_index]
        if v is None or not np.isfinite(v):
            return None, f"state value {sig.field} missing or not finite ({v!r})"
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
    b = BusVector.of(bus)
    z = jnp.zeros((), bus.dtype)
    ps = PlantState(z, z, z, b.v_x, b.v_y, b.yaw_rate, jnp.stack(b.omega), b.a_x, b.a_y)
    meas = measure(ps, b.steer, jnp.zeros(4, bus.dtype), b.mu, vehicle)
    return meas, DriverInputs(steer=b.steer, driver_torque=b.driver_torque, v_ref=b.v_ref, mu=b.mu)
