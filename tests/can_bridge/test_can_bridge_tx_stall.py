"""Out: a reader that stops, anywhere in the byte stream, never gets a frame
older than one period, and a gap the actuator may have acted on restarts the
ramp (docs/bus-safety.md, "Out: what the wire sees").

Every case: a bridge on the pty with the vehicle's actuators (rise 500 Nm a
50 ms tick) and the command held fresh at RL = RR = 1500 Nm (FL steps each
command, so every frame's bytes are unique and its age can be read off the
bridge's candump log); a peer on the pty stops reading, then resumes. Frames
are judged by their E2E CRC (autosar-e2e), as an actuator judges them.
"""

from __future__ import annotations

import os
import select
import time
import tomllib
from pathlib import Path

import can
import e2e.p01
import pytest

import can_bridge
from ampc_jax.testing.budget import budget
from ampc_jax.testing.can_fault_peers import candump_tx, frame_ages, open_raw_host
from ampc_jax.testing.can_peers import data_id
from ampc_jax.vehicle.actuators import ACTUATORS, bridge_kwargs, load_limits

pytestmark = pytest.mark.timeout(60)

PERIOD = ACTUATORS.period_ms / 1e3
RISE_NM = 500.0  # 10,000 Nm/s over a 50 ms tick
# a frame of the last period, with room for a loaded machine's scheduling
# (the stalls below are 0.5 s and longer: a stale frame is at least that old)
FRESH = 4 * PERIOD
DID = data_id("WheelTorqueCmd")


class Commander:
    """A fresh command every 10 ms: FL steps, RL = RR = 1500 Nm."""

    def __init__(self, bridge: can_bridge.Bridge) -> None:
        import threading

        self.bridge = bridge
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        seq = 0
        while not self.stop.is_set():
            seq += 1
            try:
                self.bridge.set_command((-2.0 * (seq % 500), 0.0, 1500.0, 1500.0), seq)
            except can_bridge.CanBridgeError:
                return
            time.sleep(0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)


def _bridge(tmp_path: Path) -> tuple[can_bridge.Bridge, Path]:
    log = tmp_path / "bridge.log"
    b = can_bridge.Bridge("slcan-pty:", **bridge_kwargs(), log_path=log)
    b.start()
    return b, log


def _valid(data: bytes) -> bool:
    return len(data) == 8 and e2e.p01.e2e_p01_check(bytearray(data), DID)


def _rl(data: bytes) -> float:
    raw = (int.from_bytes(data, "little") >> 40) & 0xFFF
    return 2.0 * (raw - 4096 if raw >= 2048 else raw)


class RawReader:
    """Reads the pty in bulk; each line is stamped with the time the chunk
    holding its CR arrived."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buf = b""
        self.lines: list[tuple[float, bytes]] = []

    def read_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if select.select([self.fd], [], [], 0.005)[0]:
                try:
                    chunk = os.read(self.fd, 65536)
                except BlockingIOError:
                    continue
                self._add(time.time(), chunk)

    def _add(self, t: float, chunk: bytes) -> None:
        self.buf += chunk
        while b"\r" in self.buf:
            line, self.buf = self.buf.split(b"\r", 1)
            self.lines.append((t, line))

    def read_into_a_frame(self, k: int) -> None:
        """Read byte by byte until ``k`` bytes of a torque line are read."""
        end = time.monotonic() + budget(5)
        while time.monotonic() < end:
            if not select.select([self.fd], [], [], 0.05)[0]:
                continue
            try:
                b = os.read(self.fd, 1)
            except BlockingIOError:
                continue
            self._add(time.time(), b)
            if self.buf.startswith(b"t101"[: min(k, 4)]) and len(self.buf) >= k:
                return
        raise AssertionError("no torque line to stop in")


def _frames(lines: list[tuple[float, bytes]]) -> list[tuple[float, bytes, bool]]:
    """(time, data, E2E valid) of each torque line."""
    out = []
    for t, line in lines:
        if line.startswith(b"t1018") and len(line) == 21:
            data = bytes.fromhex(line[5:21].decode())
            out.append((t, data, _valid(data)))
    return out


@pytest.mark.parametrize(
    ("k", "stall"),
    [(1, 1.0), (9, 0.5), (20, 1.0)]
    + [pytest.param(k, s, marks=pytest.mark.slow) for k in (2, 5, 14, 19) for s in (0.5, 2.0)],
)
def test_tx_stall_mid_frame_a_raw_reader_gets_no_stale_frame(tmp_path: Path, k, stall) -> None:
    """A raw SLCAN host reads ``k`` bytes of a torque line and stops for
    ``stall`` s: on resume it reads the rest of that line ended so that its
    CRC fails, then frames of the last period only, the first of them a ramp
    from zero once the stall reached the actuator's timeout (before: the
    frame it stopped in and the one queued behind it, ``active RL=1500``,
    about 1 s old)."""
    b, log = _bridge(tmp_path)
    cmd = Commander(b)
    fd = open_raw_host(b.pty_path)
    r = RawReader(fd)
    try:
        r.read_for(0.6)
        r.read_into_a_frame(k)
        n0 = len(r.lines)
        t_stop = time.time()
        time.sleep(stall)
        r.read_for(0.4)
    finally:
        cmd.close()
        b.stop()
        os.close(fd)
    after = _frames(r.lines[n0:])
    assert after, r.lines[n0:]
    cut = after[0]
    assert not cut[2], f"the line the reader stopped in completed as a valid frame: {cut}"
    # it is the frame the bridge wrote, its last data digit changed
    fixed = cut[1][:7] + bytes([cut[1][7] ^ 0x08])
    assert _valid(fixed)
    valid = [(t, d) for t, d, ok in after if ok]
    assert valid, after
    ages = frame_ages(valid, candump_tx(str(log)))
    assert len(ages) == len(valid)
    assert max(ages) < FRESH, (ages, stall)
    if stall >= ACTUATORS.timeout_ms / 1e3:
        assert abs(_rl(valid[0][1])) <= RISE_NM, (valid[0], time.time() - t_stop)


def test_tx_stall_before_the_last_cr_is_the_stated_residual(tmp_path: Path) -> None:
    """The one place the bridge cannot end a line harmlessly: the reader has
    every byte of a frame but its CR. On resume it completes that frame (the
    residual docs/bus-safety.md states), and every frame after it is of the
    last period and ramps from zero."""
    b, log = _bridge(tmp_path)
    cmd = Commander(b)
    fd = open_raw_host(b.pty_path)
    r = RawReader(fd)
    try:
        r.read_for(0.6)
        r.read_into_a_frame(21)
        n0 = len(r.lines)
        time.sleep(0.5)
        r.read_for(0.4)
    finally:
        cmd.close()
        b.stop()
        os.close(fd)
    after = _frames(r.lines[n0:])
    assert after[0][2]  # the frame it stopped in, complete
    rest = [(t, d) for t, d, ok in after[1:] if ok]
    ages = frame_ages(rest, candump_tx(str(log)))
    assert rest and max(ages) < FRESH, ages
    assert abs(_rl(rest[0][1])) <= RISE_NM


@pytest.mark.parametrize(("k", "stall"), [(3, 1.0), (12, 0.5)])
def test_tx_stall_mid_frame_python_can_reader_gets_no_stale_frame(tmp_path: Path, k, stall) -> None:
    """python-can's slcan reader (one byte per read) stops after ``k`` bytes
    of a torque line, as a busy process does: it parses the line's end
    without an error, the frame fails its CRC, and every valid frame it
    returns afterwards is of the last period."""
    b, log = _bridge(tmp_path)
    cmd = Commander(b)
    bus = can.Bus(interface="slcan", channel=b.pty_path, sleep_after_open=0, bitrate=500000)
    orig = bus.serialPortOrig.read
    state = {"line": b"", "armed": False, "stopped": 0.0}

    def read(n: int = 1) -> bytes:
        got = orig(n)
        for c in got:
            state["line"] = b"" if c == 13 else state["line"] + bytes([c])
        if state["armed"] and state["line"].startswith(b"t") and len(state["line"]) == k:
            state["armed"] = False
            state["stopped"] = time.time()
            time.sleep(stall)
        return got

    bus.serialPortOrig.read = read
    seen: list[tuple[float, bytes]] = []
    try:
        end = time.monotonic() + 0.6
        while time.monotonic() < end:
            bus.recv(0.05)
        state["armed"] = True
        end = time.monotonic() + stall + 0.6
        while time.monotonic() < end:
            m = bus.recv(0.05)
            if m is not None and m.arbitration_id == 0x101:
                seen.append((time.time(), bytes(m.data)))
    finally:
        cmd.close()
        bus.shutdown()
        b.stop()
    assert state["stopped"], "the reader never stopped"
    after = [(t, d) for t, d in seen if t >= state["stopped"] + stall]
    valid = [(t, d) for t, d in after if _valid(d)]
    assert valid, after
    ages = frame_ages(valid, candump_tx(str(log)))
    assert len(ages) == len(valid) and max(ages) < FRESH, ages
    assert abs(_rl(valid[0][1])) <= RISE_NM


# ---------------------------------------------------------------- the gap


def test_tx_gap_one_actuator_contract() -> None:
    """The actuator's command timeout has one source: the actuator contract
    (``ACTUATORS.timeout_ms``), which the bridge's shipped vehicle.toml, the
    keyword arguments the runtime passes it, the configuration the bridge
    loads and the simulated vehicle's default all equal."""
    shipped = tomllib.loads(Path(can_bridge.default_config_path()).read_text())
    assert shipped["actuator_timeout_ms"] == ACTUATORS.timeout_ms
    assert load_limits(can_bridge.default_config_path()) == ACTUATORS
    assert bridge_kwargs()["actuator_timeout_ms"] == ACTUATORS.timeout_ms
    assert can_bridge.load_config()["actuator_timeout_ms"] == ACTUATORS.timeout_ms
    import inspect

    from ampc_jax.runtime.plant_node import PlantNode

    default = inspect.signature(PlantNode).parameters["cmd_timeout_ms"].default
    assert default == ACTUATORS.timeout_ms


def test_tx_gap_timeout_is_validated_by_name() -> None:
    with pytest.raises(can_bridge.ConfigError, match="actuator_timeout_ms = 60 must be between"):
        can_bridge.Bridge("slcan-pty:", period_ms=50, actuator_timeout_ms=60)
    can_bridge.Bridge("slcan-pty:", period_ms=50, actuator_timeout_ms=100)


def _gap_check(frames: list[tuple[float, bytes]]) -> list[tuple[float, float]]:
    """(gap, RL) of each valid frame that follows a gap of at least the
    actuator's timeout: the actuator applied 0 Nm meanwhile."""
    out = []
    valid = [(t, d) for t, d in frames if _valid(d)]
    for (t0, _), (t1, d) in zip(valid, valid[1:], strict=False):
        if t1 - t0 >= ACTUATORS.timeout_ms / 1e3:
            out.append((t1 - t0, _rl(d)))
    return out


@pytest.mark.parametrize("stall", [0.15, 0.21, 0.24, 0.3])
def test_tx_gap_a_reader_stall_the_actuator_acted_on_gets_a_ramp(tmp_path: Path, stall) -> None:
    """A raw host stops reading between two lines for ``stall`` s. Any gap
    between two frames it reads that reaches the actuator's 200 ms timeout
    (the simulated vehicle then applies 0 Nm) is followed by a ramp from
    zero, never the held 1500 Nm (before: a stall of 200-250 ms, under the
    bridge's 250 ms transport timeout, gave a 0 -> 1500 Nm step)."""
    b, _ = _bridge(tmp_path)
    cmd = Commander(b)
    fd = open_raw_host(b.pty_path)
    r = RawReader(fd)
    try:
        r.read_for(0.6)
        time.sleep(stall)
        r.read_for(0.4)
        s = b.stats()
    finally:
        cmd.close()
        b.stop()
        os.close(fd)
    frames = [(t, d) for t, d, _ in _frames(r.lines)]
    gaps = _gap_check(frames)
    if stall >= 0.2:
        assert gaps, "no gap reached the timeout"
    for gap, rl in gaps:
        assert abs(rl) <= RISE_NM, (gap, rl)
    if gaps:
        assert s["ramp_restarts"] >= 1


@pytest.mark.parametrize("stall", [0.19, 0.22, pytest.param(0.28, marks=pytest.mark.slow)])
def test_tx_gap_python_can_reader_stall(stall) -> None:
    """The same with python-can's reader, which stops between two frames."""
    b = can_bridge.Bridge("slcan-pty:", **bridge_kwargs())
    b.start()
    cmd = Commander(b)
    bus = can.Bus(interface="slcan", channel=b.pty_path, sleep_after_open=0, bitrate=500000)
    seen: list[tuple[float, bytes]] = []

    def take(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            m = bus.recv(0.02)
            if m is not None and m.arbitration_id == 0x101:
                seen.append((time.time(), bytes(m.data)))

    try:
        take(0.6)
        time.sleep(stall)
        take(0.4)
    finally:
        cmd.close()
        bus.shutdown()
        b.stop()
    for gap, rl in _gap_check(seen):
        assert abs(rl) <= RISE_NM, (gap, rl)
