"""The bus vector and its estimator (ampc_jax.runtime.signals).

* The estimator on the exact bus vector of a plant state is the simulation's
  measurement of that state (``vehicle.plant.measure``), bit for bit.
* Through the DBC (cantools encode, decode) every signal is rounded to its
  resolution, and the measurement moves by no more than the estimator's
  first-order response to those roundings.
* ``bus_from_bridge`` turns ``can_bridge.Bridge.latest_state()`` into the
  vector only when the bridge calls the state valid and every value is there
  and finite; otherwise it says why.
"""

from __future__ import annotations

import cantools
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import can_bridge
from ampc_jax.runtime.signals import (
    BUS_FIELDS,
    MESSAGES,
    SIGNALS,
    BusVector,
    bus_from_bridge,
    bus_measurement,
    bus_vector,
    message_values,
)
from ampc_jax.vehicle.params import Measurement, VehicleParams
from ampc_jax.vehicle.plant import initial_state, measure, plant_step

pytestmark = pytest.mark.timeout(120)

VEHICLE = VehicleParams()
IDX = {name: i for i, name in enumerate(BUS_FIELDS)}

# Two manoeuvres held for 12 control periods from 20 m/s straight running:
# steering with front braking and rear drive (lateral acceleration, wheels at
# different slips), and braking on all wheels while steering the other way on a
# lower friction (longitudinal load transfer, negative slips). Driver torque and
# set speed are arbitrary values inside the DBC's ranges.
CASES = {
    "steer_and_drive": dict(steer=0.04, torques=(-300.0, -300.0, 400.0, 400.0), mu=0.8),
    "brake_and_steer": dict(steer=-0.06, torques=(-900.0, -900.0, -600.0, -600.0), mu=0.5),
}
DRIVER_TORQUE, V_REF = 850.0, 21.0
PERIODS = (2, 6, 12)


@pytest.fixture(scope="module")
def states() -> dict[str, list]:
    """Per case, the plant states after PERIODS control periods."""
    step = jax.jit(lambda s, d, t, mu: plant_step(s, d, t, mu, VEHICLE))
    out = {}
    for name, c in CASES.items():
        s = initial_state(20.0, VEHICLE, dtype=jnp.float64)
        got = []
        for k in range(1, max(PERIODS) + 1):
            s = step(s, c["steer"], jnp.asarray(c["torques"]), c["mu"])
            if k in PERIODS:
                got.append(s)
        out[name] = got
    return out


def _bus(state, case: str) -> np.ndarray:
    c = CASES[case]
    return bus_vector(state, c["steer"], DRIVER_TORQUE, V_REF, c["mu"])


@pytest.mark.parametrize("case", CASES)
def test_estimator_is_the_simulations_measurement(states, case) -> None:
    c = CASES[case]
    for state in states[case]:
        # the states are nontrivial: the load-transfer terms and all slips are in play
        assert abs(float(state.a_x)) > 0.01 and abs(float(state.a_y)) > 1.0
        assert abs(float(state.v_y)) > 1e-3 and abs(float(state.r)) > 1e-2
        bus = _bus(state, case)
        assert bus.shape == (len(BUS_FIELDS),) and bus.dtype == np.float64
        meas, driver = bus_measurement(jnp.asarray(bus), VEHICLE)
        want = measure(state, c["steer"], jnp.zeros(4), c["mu"], VEHICLE)
        assert isinstance(meas, Measurement)
        for field in Measurement._fields:
            got, ref = np.asarray(getattr(meas, field)), np.asarray(getattr(want, field))
            assert got.shape == ref.shape, field
            # the same function of the same seven states: identical, not close
            np.testing.assert_array_equal(got, ref, err_msg=field)
        assert float(driver.steer) == c["steer"]
        assert float(driver.driver_torque) == DRIVER_TORQUE
        assert float(driver.v_ref) == V_REF
        assert float(driver.mu) == c["mu"]


def test_bus_vector_order(states) -> None:
    s = states["steer_and_drive"][-1]
    bus = _bus(s, "steer_and_drive")
    want = {
        "v_x": s.v_x,
        "v_y": s.v_y,
        "yaw_rate": s.r,
        "steer": CASES["steer_and_drive"]["steer"],
        "a_x": s.a_x,
        "a_y": s.a_y,
        "driver_torque": DRIVER_TORQUE,
        "v_ref": V_REF,
        "mu": CASES["steer_and_drive"]["mu"],
        **{f"omega_{w}": s.omega[i] for i, w in enumerate(("FL", "FR", "RL", "RR"))},
    }
    assert set(want) == set(BUS_FIELDS)
    for name, v in want.items():
        assert bus[IDX[name]] == float(v), name
    # every bus entry travels in exactly one DBC signal
    carried = [f for sigs in MESSAGES.values() for f in sigs.values()]
    assert sorted(carried) == sorted(BUS_FIELDS)


def _dbc() -> cantools.database.can.Database:
    return cantools.database.load_file(can_bridge.dbc_path())


def _through_dbc(db, bus: np.ndarray) -> np.ndarray:
    """The bus vector a receiver rebuilds from the five messages' frames."""
    back = np.full_like(bus, np.nan)
    for name, values in message_values(bus).items():
        msg = db.get_message_by_name(name)
        data = msg.encode({"CRC": 0, "Counter": 0, **values})
        decoded = msg.decode(data, decode_choices=False)
        for sig, field in MESSAGES[name].items():
            back[IDX[field]] = decoded[sig]
    assert np.all(np.isfinite(back))
    return back


def _resolution(db) -> np.ndarray:
    """Each bus entry's signal resolution (the DBC's scale)."""
    res = np.full(len(BUS_FIELDS), np.nan)
    for name, sigs in MESSAGES.items():
        msg = db.get_message_by_name(name)
        for sig, field in sigs.items():
            res[IDX[field]] = msg.get_signal_by_name(sig).scale
    assert np.all(res > 0)
    return res


def test_message_values_cover_the_dbc_messages() -> None:
    db = _dbc()
    bus = np.arange(1.0, len(BUS_FIELDS) + 1) * 0.1
    vals = message_values(bus)
    assert set(vals) == set(MESSAGES)
    for name, sigs in vals.items():
        msg = db.get_message_by_name(name)
        payload = {s.name for s in msg.signals} - {"CRC", "Counter"}
        assert set(sigs) == payload, name
        for sig, v in sigs.items():
            assert v == bus[IDX[MESSAGES[name][sig]]]


# The first-order bound holds up to the estimator's curvature over half a
# resolution step (the tyre model is smooth at these slips); 10 % covers it.
CURVATURE_MARGIN = 1.1


@pytest.mark.parametrize("case", CASES)
def test_measurement_through_the_dbc_within_resolution(states, case) -> None:
    """Bound: cantools rounds each signal to the nearest raw step, so each bus
    entry moves by at most half its resolution ``q_j / 2``; the measurement's
    entry i then moves by at most ``sum_j |d m_i / d b_j| q_j / 2`` to first order
    (the estimator's Jacobian at the exact bus vector, which is the worst case
    of the roundings' signs). Directly carried entries (speeds, yaw rate, wheel
    speeds, accelerations, driver inputs) have a Jacobian of one: half their
    resolution."""
    db = _dbc()
    res = _resolution(db)
    jac = jax.jit(jax.jacfwd(lambda b: bus_measurement(b, VEHICLE)[0]))
    for state in states[case]:
        bus = _bus(state, case)
        back = _through_dbc(db, bus)
        # the quantization itself: half a step, and not exact (the test has teeth)
        assert np.all(np.abs(back - bus) <= res / 2 * (1 + 1e-9)), (back - bus) / res
        assert np.count_nonzero(back != bus) >= 8
        m0, d0 = bus_measurement(jnp.asarray(bus), VEHICLE)
        m1, d1 = bus_measurement(jnp.asarray(back), VEHICLE)
        J = jac(jnp.asarray(bus))
        for field in Measurement._fields:
            Jf = np.asarray(getattr(J, field)).reshape(-1, len(BUS_FIELDS))
            bound = np.abs(Jf) @ (res / 2)
            err = np.abs(np.asarray(getattr(m1, field)) - np.asarray(getattr(m0, field)))
            err = err.ravel()
            assert np.all(err <= CURVATURE_MARGIN * bound + 1e-12), (field, err, bound)
        for field in ("steer", "driver_torque", "v_ref", "mu"):
            err = abs(float(getattr(d1, field)) - float(getattr(d0, field)))
            assert err <= res[IDX[field]] / 2 * (1 + 1e-9), field


# -- bus_from_bridge --------------------------------------------------------------

# The keys of can_bridge's VehicleState (can_bridge/__init__.pyi)
STATE_KEYS = {
    "valid",
    "long_speed_mps",
    "lat_speed_mps",
    "yaw_rate_radps",
    "steering_angle_rad",
    "wheel_speeds_radps",
    "long_accel_mps2",
    "lat_accel_mps2",
    "driver_torque_nm",
    "set_speed_mps",
    "road_friction",
    "age_ms",
    "status",
    "reason",
}
SCALAR_KEYS = {
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
WHEELS = ("FL", "FR", "RL", "RR")
# distinct values, so that a swapped pair of entries shows
BUS = np.array([17.5, -0.25, 0.125, 55.5, 56.5, 57.5, 58.5, 0.03, -1.5, 3.25, 640.0, 18.0, 0.9])


def _valid_state(bus: np.ndarray = BUS) -> dict:
    """A valid latest_state() dict carrying ``bus``."""
    state = {key: bus[IDX[field]] for field, key in SCALAR_KEYS.items()}
    state["wheel_speeds_radps"] = tuple(bus[IDX[f"omega_{w}"]] for w in WHEELS)
    status = dict.fromkeys(MESSAGES, "ok")
    state.update(valid=True, age_ms=12.0, status=status, reason=None)
    return state


def test_state_keys_are_the_bridges() -> None:
    never_started = can_bridge.Bridge("slcan-pty:", period_ms=50).latest_state()
    assert set(never_started) == STATE_KEYS
    assert set(_valid_state()) == STATE_KEYS
    assert set(never_started["status"]) == set(MESSAGES)


def test_valid_state_gives_the_vector_in_order() -> None:
    vec, why = bus_from_bridge(_valid_state())
    assert why is None
    assert vec is not None and vec.shape == (len(BUS_FIELDS),)
    np.testing.assert_array_equal(vec, BUS)


def test_invalid_state_gives_the_bridges_reason() -> None:
    # a bridge that never received anything: invalid, its reason names every message
    state = can_bridge.Bridge("slcan-pty:", period_ms=50).latest_state()
    assert state["valid"] is False and state["reason"]
    vec, why = bus_from_bridge(state)
    assert vec is None and state["reason"] in why and "invalid" in why
    # values present but the bridge says no (a stale message): still refused
    stale = {**_valid_state(), "valid": False, "reason": "WheelSpeeds: stale (130 ms)"}
    vec, why = bus_from_bridge(stale)
    assert vec is None and "WheelSpeeds: stale (130 ms)" in why
    # no reason given: refused all the same
    vec, why = bus_from_bridge({**_valid_state(), "valid": False, "reason": None})
    assert vec is None and why
    vec, why = bus_from_bridge({k: v for k, v in _valid_state().items() if k != "valid"})
    assert vec is None and why


@pytest.mark.parametrize("bad", [None, float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("field", BUS_FIELDS)
def test_missing_or_non_finite_value_names_the_field(field, bad) -> None:
    state = _valid_state()
    if field.startswith("omega_"):
        wheels = list(state["wheel_speeds_radps"])
        wheels[WHEELS.index(field[6:])] = bad
        state["wheel_speeds_radps"] = tuple(wheels)
    else:
        state[SCALAR_KEYS[field]] = bad
    vec, why = bus_from_bridge(state)
    assert vec is None
    assert why is not None and f" {field} " in why, why


def test_missing_wheel_speeds_name_a_wheel() -> None:
    vec, why = bus_from_bridge({**_valid_state(), "wheel_speeds_radps": None})
    assert vec is None and "omega_FL" in why
    absent = {k: v for k, v in _valid_state().items() if k != "road_friction"}
    vec, why = bus_from_bridge(absent)
    assert vec is None and " mu " in why


def test_the_signal_table_names_the_dbc_and_the_bridge() -> None:
    """One record (BusVector, SIGNALS) names every signal in the DBC (read by
    cantools) and in the bridge's latest_state(); nothing else spells them."""
    db = cantools.database.load_file(can_bridge.dbc_path())
    state = can_bridge.Bridge("slcan-pty:", period_ms=50).latest_state()
    assert tuple(s.field for s in SIGNALS) == BusVector._fields == BUS_FIELDS
    for sig in SIGNALS:
        dbc = db.get_message_by_name(sig.message).get_signal_by_name(sig.signal)
        assert (dbc.unit or "") == sig.unit, sig
        assert sig.bridge_key in state, sig
    payload = {
        m.name: {s.name for s in m.signals if s.name not in ("CRC", "Counter")}
        for m in db.messages
        if m.name in MESSAGES
    }
    assert {m: set(sigs) for m, sigs in MESSAGES.items()} == payload
    # the record views a flat vector by name, and back
    rec = BusVector.of(BUS)
    assert rec.v_x == BUS[IDX["v_x"]] and rec.omega[2] == BUS[IDX["omega_RL"]]
    np.testing.assert_array_equal(rec.as_array(), BUS)
