"""The Rust packing against cantools (byte for byte) and autosar-e2e."""

from __future__ import annotations

import random

import e2e.p01
import pytest

import can_bridge
from ampc_jax.testing.can_peers import data_id, db, protect

pytestmark = pytest.mark.timeout(60)


def test_dbc_is_installed_and_describes_the_frames() -> None:
    d = db()
    cmd = d.get_message_by_name("WheelTorqueCmd")
    assert {s.name for s in cmd.signals} == {
        "CRC",
        "Counter",
        "Mode",
        "TorqueFL",
        "TorqueFR",
        "TorqueRL",
        "TorqueRR",
    }
    assert cmd.get_signal_by_name("TorqueFL").unit == "Nm"
    assert {int(k): str(v) for k, v in cmd.get_signal_by_name("Mode").choices.items()} == {
        0: "active",
        1: "hold",
        2: "safe",
        3: "fault",
    }
    received = {
        s.name
        for n in ("VehicleMotion", "WheelSpeeds", "SteeringState", "VehicleAccel", "DriverDemand")
        for s in d.get_message_by_name(n).signals
    }
    for sig in (
        "LongSpeed",
        "LatSpeed",
        "YawRate",
        "SteeringAngle",
        "WheelSpeedFL",
        "WheelSpeedFR",
        "WheelSpeedRL",
        "WheelSpeedRR",
        "LongAccel",
        "LatAccel",
        "DriverTorque",
        "SetSpeed",
        "RoadFriction",
    ):
        assert sig in received
    accel = d.get_message_by_name("VehicleAccel")
    driver = d.get_message_by_name("DriverDemand")
    assert (accel.frame_id, accel.length, data_id("VehicleAccel")) == (0x204, 6, 3092)
    assert (driver.frame_id, driver.length, data_id("DriverDemand")) == (0x205, 8, 3093)
    assert accel.cycle_time == driver.cycle_time == 20
    friction = driver.get_signal_by_name("RoadFriction")
    assert (friction.minimum, friction.maximum, friction.scale) == (0.05, 2, 0.01)
    assert "friction estimate" in friction.comment
    ids = [data_id(m.name) for m in d.messages]
    assert len(set(ids)) == len(ids) and all(i > 0 for i in ids)
    for m in d.messages:
        crc = m.get_signal_by_name("CRC")
        ctr = m.get_signal_by_name("Counter")
        assert (crc.start, crc.length) == (0, 8)
        assert (ctr.start, ctr.length) == (8, 4)


def test_e2e_published_vectors_and_rust_crc() -> None:
    # Profile 1 vectors (Data ID 0x123, mode BOTH): counter 0 -> CC, counter 1 -> 91.
    for counter, crc in ((0, 0xCC), (1, 0x91)):
        data = bytearray(8)
        data[1] = counter
        assert can_bridge.e2e_p01_crc(0x123, bytes(data)) == crc
        e2e.p01.e2e_p01_protect(data, 0x123, increment_counter=False)
        assert data[0] == crc
    rng = random.Random(7)
    for _ in range(500):
        data = bytearray(rng.randbytes(rng.randint(2, 8)))
        did = rng.randint(0, 0xFFFF)
        e2e.p01.e2e_p01_protect(data, did, increment_counter=False)
        assert can_bridge.e2e_p01_crc(did, bytes(data)) == data[0]


def _random_values(msg, rng: random.Random) -> dict[str, float]:
    out = {}
    for s in msg.signals:
        if s.name in ("CRC", "Counter"):
            continue
        if s.choices:
            out[s.name] = rng.choice(sorted(int(k) for k in s.choices))
            continue
        raw = rng.randint(round(s.minimum / s.scale), round(s.maximum / s.scale))
        # Sometimes a value off the grid, to exercise rounding (incl. ties).
        v = raw * s.scale
        if rng.random() < 0.3:
            v += rng.choice([0.5, 0.25, -0.5, 0.49, -0.37]) * s.scale
        out[s.name] = min(max(v, s.minimum), s.maximum)
    return out


@pytest.mark.parametrize(
    "name",
    [
        "WheelTorqueCmd",
        "VehicleMotion",
        "WheelSpeeds",
        "SteeringState",
        "VehicleAccel",
        "DriverDemand",
    ],
)
def test_rust_packing_matches_cantools_byte_for_byte(name: str) -> None:
    msg = db().get_message_by_name(name)
    rng = random.Random(name)
    for i in range(400):
        values = _random_values(msg, rng)
        counter = i % 15
        ours = can_bridge.encode_message(name, values, counter)
        theirs = protect(name, values, counter)
        assert ours == theirs, (values, ours.hex(), theirs.hex())


def test_encode_message_refuses_bad_input() -> None:
    with pytest.raises(can_bridge.CommandError, match="not a finite"):
        can_bridge.encode_message("SteeringState", {"SteeringAngle": float("nan")}, 0)
    with pytest.raises(can_bridge.CommandError, match="missing signal"):
        can_bridge.encode_message("SteeringState", {}, 0)
    with pytest.raises(can_bridge.ConfigError, match="unknown message"):
        can_bridge.encode_message("Nope", {}, 0)


_TORQUE = {"Mode": "active", "TorqueFL": 1, "TorqueFR": 1, "TorqueRL": 1, "TorqueRR": 1}


@pytest.mark.parametrize("counter", [15, 200, -1, 300, pytest.param(10**400, id="10**400")])
def test_encode_message_refuses_counter_outside_profile1_range(counter: int) -> None:
    with pytest.raises(can_bridge.CommandError, match=rf"counter = {str(counter)[:5]}.* 0\.\.=14"):
        can_bridge.encode_message("WheelTorqueCmd", _TORQUE, counter)


@pytest.mark.parametrize("counter", [True, 3.0, "3", None])
def test_encode_message_refuses_non_integer_counter(counter) -> None:
    with pytest.raises(can_bridge.CommandError, match="counter = .* alive counter"):
        can_bridge.encode_message("WheelTorqueCmd", _TORQUE, counter)


def test_encode_message_accepts_every_profile1_counter() -> None:
    for counter in range(15):
        data = can_bridge.encode_message("WheelTorqueCmd", _TORQUE, counter)
        assert data[1] & 0x0F == counter
        assert data == protect("WheelTorqueCmd", {**_TORQUE, "Mode": 0}, counter)


@pytest.mark.parametrize(
    ("name", "values", "match"),
    [
        (
            "WheelTorqueCmd",
            {**_TORQUE, "TorqueFL": 4095},
            r"TorqueFL = 4095 .*range -4096\.\.=4094",
        ),
        ("WheelTorqueCmd", {**_TORQUE, "TorqueRR": -4097}, r"TorqueRR = -4097 .*range"),
        ("WheelTorqueCmd", {**_TORQUE, "TorqueFR": 10**400}, r"TorqueFR = 1000.*range"),
        (
            "SteeringState",
            {"SteeringAngle": 1.5},
            r"SteeringAngle = 1.5 .*range -1\.\.=1",
        ),
        ("WheelTorqueCmd", {**_TORQUE, "Mode": 4}, r"Mode = 4 .*range 0\.\.=3"),
        ("WheelTorqueCmd", {**_TORQUE, "Mode": 2.6}, r"Mode = 2.6 is not an integer"),
        ("WheelTorqueCmd", {**_TORQUE, "Mode": 0.5}, r"Mode = 0.5 is not an integer"),
        ("WheelTorqueCmd", {**_TORQUE, "Mode": "ACTIVE"}, r"unknown Mode 'ACTIVE'"),
        ("WheelTorqueCmd", {**_TORQUE, "TorqueFL": "1"}, r"TorqueFL = '1' is not a real number"),
        ("WheelTorqueCmd", {**_TORQUE, "TorqueFL": 1j}, r"TorqueFL = 1j is not a real number"),
    ],
)
def test_encode_message_refuses_values_the_dbc_does_not_allow(name, values, match) -> None:
    with pytest.raises(can_bridge.CommandError, match=match):
        can_bridge.encode_message(name, values, 0)


@pytest.mark.parametrize("extra", [{"Bogus": 5}, {"CRC": 7}, {"Counter": 3}, {1: 2}])
def test_encode_message_refuses_unknown_keys(extra: dict) -> None:
    key = next(iter(extra))
    with pytest.raises(
        can_bridge.CommandError,
        match=rf"WheelTorqueCmd has no signal {key!r} .*Mode, TorqueFL, TorqueFR, TorqueRL, TorqueRR",
    ):
        can_bridge.encode_message("WheelTorqueCmd", {**_TORQUE, **extra}, 0)


def test_encode_message_accepts_limits_and_integral_floats() -> None:
    values = {"Mode": 3.0, "TorqueFL": -1000, "TorqueFR": 1000.0, "TorqueRL": 0.3, "TorqueRR": 0.25}
    assert can_bridge.encode_message("WheelTorqueCmd", values, 14) == protect(
        "WheelTorqueCmd", values, 14
    )
