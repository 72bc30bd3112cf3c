"""Independent peers for the can_bridge tests: cantools decodes and encodes
from the shipped DBC, the ``autosar-e2e`` package checks and computes every
CRC, python-can plays the SLCAN host. Nothing here uses the Rust codec."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from functools import lru_cache

import can
import cantools
import e2e.p01

import can_bridge

from .budget import budget

MODES = {0: "active", 1: "hold", 2: "safe", 3: "fault"}


@lru_cache(maxsize=1)
def db() -> cantools.database.can.Database:
    return cantools.database.load_file(can_bridge.dbc_path())


def data_id(name: str) -> int:
    return int(db().get_message_by_name(name).dbc.attributes["E2EDataID"].value)


def protect(
    name: str, values: dict[str, float], counter: int, *, strict: bool | None = None
) -> bytes:
    """cantools encode + autosar-e2e CRC: the peer's own framing."""
    msg = db().get_message_by_name(name)
    # strict=False only to let a test build the invalid counter 15 or a value
    # outside the DBC's range (an implausible sensor).
    strict = counter <= 14 if strict is None else strict
    data = bytearray(msg.encode({"CRC": 0, "Counter": counter, **values}, strict=strict))
    e2e.p01.e2e_p01_protect(data, data_id(name), increment_counter=False)
    return bytes(data)


class CmdChecker:
    """Checks WheelTorqueCmd frames one by one: ID, DLC, CRC (autosar-e2e),
    counter continuity, and that cantools re-encodes the decoded values to the
    same bytes. With ``continuous=True`` the counter must step by one; by
    default it may skip values (a frame dropped for its age advances the
    counter, so the receiver sees it as lost; 15 dropped frames look like a
    repeat): the skips are counted in ``gaps``."""

    def __init__(self, *, continuous: bool = False) -> None:
        self.continuous = continuous
        self.gaps = 0
        self.cut = 0
        self.msg = db().get_message_by_name("WheelTorqueCmd")
        self.did = data_id("WheelTorqueCmd")
        self.prev: int | None = None
        self.frames: list[dict] = []
        self.raw: list[bytes] = []

    def add(self, arbitration_id: int, is_extended: bool, data: bytes) -> dict | None:
        """Check one frame; ``None`` (counted in ``cut``) for the end of a
        line the bridge cut because the reader stopped inside it for a
        period: its last data digit changed (``data[7] ^ 0x08``) so the CRC
        fails, and nothing else."""
        assert arbitration_id == self.msg.frame_id and not is_extended
        assert len(data) == 8
        buf = bytearray(data)
        if not e2e.p01.e2e_p01_check(bytearray(buf), self.did):
            fixed = bytearray(data[:7]) + bytes([data[7] ^ 0x08])
            assert e2e.p01.e2e_p01_check(fixed, self.did), f"bad CRC in {data.hex()}"
            self.cut += 1
            return None
        assert e2e.p01.e2e_p01_check(buf, self.did), f"bad CRC in {data.hex()}"
        counter = data[1] & 0x0F
        assert counter <= 14
        if self.prev is not None:
            step = (counter - self.prev) % 15
            assert step == 1 or not self.continuous, f"counter {self.prev} -> {counter}"
            self.gaps += step != 1
        self.prev = counter
        values = self.msg.decode(bytes(data), decode_choices=False)
        again = bytearray(self.msg.encode(values))
        e2e.p01.e2e_p01_protect(again, self.did, increment_counter=False)
        assert bytes(again) == bytes(data)
        out = {
            "mode": MODES[int(values["Mode"])],
            "torques": tuple(values[k] for k in ("TorqueFL", "TorqueFR", "TorqueRL", "TorqueRR")),
            "counter": counter,
        }
        # decoded values are raw integers times the scale, so always finite; a
        # frame must also stay within each signal's DBC range
        for k in ("TorqueFL", "TorqueFR", "TorqueRL", "TorqueRR"):
            sig = self.msg.get_signal_by_name(k)
            assert sig.minimum <= values[k] <= sig.maximum, (k, values[k], data.hex())
        self.frames.append(out)
        self.raw.append(bytes(data))
        return out


def recv_cmds(bus: can.BusABC, checker: CmdChecker, n: int, timeout: float = 10.0) -> list[dict]:
    got = []
    end = time.monotonic() + budget(timeout)  # a deadline: stretched on a busy machine
    while len(got) < n and time.monotonic() < end:
        m = bus.recv(timeout=0.2)
        if m is not None:
            f = checker.add(m.arbitration_id, m.is_extended_id, bytes(m.data))
            if f is not None:
                got.append(f)
    assert len(got) == n, f"received {len(got)} of {n} frames"
    return got


def recv_until(bus: can.BusABC, checker: CmdChecker, pred, timeout: float = 10.0) -> list[dict]:
    got = []
    end = time.monotonic() + budget(timeout)  # a deadline: stretched on a busy machine
    while time.monotonic() < end:
        m = bus.recv(timeout=0.2)
        if m is None:
            continue
        f = checker.add(m.arbitration_id, m.is_extended_id, bytes(m.data))
        if f is None:
            continue
        got.append(f)
        if pred(got[-1]):
            return got
    raise AssertionError(f"condition not met within {timeout} s; last frames {got[-5:]}")


@contextlib.contextmanager
def slcan_peer(bridge: can_bridge.Bridge) -> Iterator[can.BusABC]:
    """Start the bridge on a pty and open python-can's slcan interface on it."""
    bridge.start()
    assert bridge.pty_path is not None
    bus = can.Bus(interface="slcan", channel=bridge.pty_path, sleep_after_open=0, bitrate=500000)
    try:
        yield bus
    finally:
        bus.shutdown()
        bridge.stop()


def state_message(
    name: str,
    values: dict[str, float],
    counter: int,
    *,
    corrupt: bool = False,
    strict: bool | None = None,
) -> can.Message:
    data = bytearray(protect(name, values, counter, strict=strict))
    if corrupt:
        data[2] ^= 0x01
    return can.Message(
        arbitration_id=db().get_message_by_name(name).frame_id, is_extended_id=False, data=data
    )


MOTION = {"LongSpeed": 12.34, "LatSpeed": -0.56, "YawRate": 0.123}
# physically consistent with MOTION (the bridge checks it): front wheels, which
# brake only, rolling at 12.34 m/s (35.2 rad/s at R = 0.351 m), rear wheels driving
WHEELS = {"WheelSpeedFL": 35.1, "WheelSpeedFR": 35.2, "WheelSpeedRL": 39.9, "WheelSpeedRR": 40.3}
STEER = {"SteeringAngle": 0.0456}
ACCEL = {"LongAccel": -3.21, "LatAccel": 7.5}
DRIVER = {"DriverTorque": -1234.5, "SetSpeed": 17.25, "RoadFriction": 0.35}

# Every message the bridge receives, with healthy values: latest_state() is
# valid only while all of them arrive sound.
SENSORS: tuple[tuple[str, dict[str, float]], ...] = (
    ("VehicleMotion", MOTION),
    ("WheelSpeeds", WHEELS),
    ("SteeringState", STEER),
    ("VehicleAccel", ACCEL),
    ("DriverDemand", DRIVER),
)


def send_sensors(
    bus: can.BusABC, counter: int, *, skip: tuple[str, ...] = (), corrupt: bool = False
) -> None:
    """One frame of every received message but ``skip``, all with ``counter``."""
    for name, values in SENSORS:
        if name not in skip:
            bus.send(state_message(name, values, counter, corrupt=corrupt))
