"""Regression tests for reviewed defects: limits enforced on the wire value,
stop frames reaching a slow peer, reset_fault without a fault, log write
errors, a FIFO as log_path, start/stop racing, argument type errors."""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import pytest
from cb_peers import CmdChecker, recv_until, slcan_peer

import can_bridge

pytestmark = pytest.mark.timeout(60)


def open_raw_peer(path: str) -> int:
    """A raw SLCAN host on the pty slave that opens the channel."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    os.write(fd, b"C\rS6\rO\r")
    return fd


def parse_cmds(buf: bytes) -> list[dict]:
    chk = CmdChecker()
    for line in buf.split(b"\r"):
        if line.startswith(b"t"):
            ident = int(line[1:4], 16)
            dlc = int(line[4:5])
            chk.add(ident, False, bytes.fromhex(line[5 : 5 + 2 * dlc].decode()))
    return chk.frames


@pytest.mark.parametrize(
    ("max_torque", "rate"),
    [
        (300.3, 1000.0),
        ((100.8, 50.0, 0.76, 999.9), 1000.0),
        (300.0, 1.3),
        ((10.0, 2.9, 3.1, 1.2), 0.7),
    ],
)
def test_torque_and_step_on_the_wire_never_exceed_the_limits(max_torque, rate) -> None:
    limits = max_torque if isinstance(max_torque, tuple) else (max_torque,) * 4
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=5,
        max_torque_nm=max_torque,
        max_rate_nm_per_tick=rate,
        hold_after_ms=2000,
        safe_after_ms=3000,
        fault_after_ms=4000,
    )
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        bridge.set_command((1000.0, -1000.0, 1000.0, -1000.0), seq=1)
        # Limits round toward zero onto the 0.5 Nm grid: 300.3 -> 300.0, ...
        want = tuple(
            s * (int(lim / 0.5) * 0.5) for s, lim in zip((1, -1, 1, -1), limits, strict=True)
        )
        frames = recv_until(bus, chk, lambda f: f["torques"] == want, timeout=20)
    active = [f for f in frames if f["mode"] == "active"]
    assert active
    for f in frames:
        assert all(abs(t) <= lim for t, lim in zip(f["torques"], limits, strict=True)), f
    prev = (0.0,) * 4
    for f in active:
        assert all(abs(b - a) <= rate for a, b in zip(prev, f["torques"], strict=True)), (prev, f)
        prev = f["torques"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"max_torque_nm": 0.3}, r"max_torque_nm\[0\] = 0.3 .*resolution"),
        ({"max_torque_nm": (100.0, 100.0, 0.26, 100.0)}, r"max_torque_nm\[2\].*resolution"),
        ({"max_rate_nm_per_tick": 0.2}, "max_rate_nm_per_tick = 0.2 .*resolution"),
        ({"max_rate_nm_per_tick": 0.3}, "max_rate_nm_per_tick = 0.3 .*resolution"),
    ],
)
def test_limits_below_the_wire_resolution_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(can_bridge.ConfigError, match=match):
        can_bridge.Bridge("slcan-pty:", **kwargs)


def test_stop_frames_reach_a_peer_that_reads_only_every_150_ms() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=20, stop_safe_frames=3)
    bridge.start()
    fd = open_raw_peer(bridge.pty_path)
    buf = bytearray()
    ended = threading.Event()

    def reader() -> None:
        while True:
            time.sleep(0.15)
            try:
                d = os.read(fd, 65536)
            except BlockingIOError:
                continue
            except OSError:
                break
            if not d:
                break
            buf.extend(d)
        ended.set()

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        for i in range(25):
            bridge.set_command((50.0,) * 4, i + 1)
            time.sleep(0.02)
        t0 = time.monotonic()
        bridge.stop()
        assert time.monotonic() - t0 < 1.5
        th.join(3)
    finally:
        os.close(fd)
    frames = parse_cmds(bytes(buf))
    assert any(f["mode"] == "active" for f in frames)
    assert [f["mode"] for f in frames[-3:]] == ["safe"] * 3
    assert all(f["torques"] == (0.0,) * 4 for f in frames[-3:])


def test_reset_fault_without_a_fault_is_a_no_op() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=10, max_rate_nm_per_tick=10.0)
    bridge.start()
    fd = open_raw_peer(bridge.pty_path)
    try:
        seq = 0
        for _ in range(20):
            seq += 1
            bridge.set_command((100.0,) * 4, seq)
            time.sleep(0.01)
        bridge.reset_fault()
        for _ in range(5):
            seq += 1
            bridge.set_command((100.0,) * 4, seq)
            time.sleep(0.01)
        buf = b""
        end = time.monotonic() + 0.1
        while time.monotonic() < end:
            if select.select([fd], [], [], 0.02)[0]:
                buf += os.read(fd, 65536)
    finally:
        bridge.stop()
        os.close(fd)
    frames = parse_cmds(buf)
    active = [i for i, f in enumerate(frames) if f["mode"] == "active"]
    assert active, frames
    first = active[0]
    # From the first active frame on: never safe again, never a drop to zero,
    # each step within the rate limit.
    tail = frames[first:]
    assert all(f["mode"] == "active" for f in tail), [f["mode"] for f in tail]
    for a, b in zip(tail, tail[1:], strict=False):
        assert all(abs(y - x) <= 10.0 for x, y in zip(a["torques"], b["torques"], strict=True))
    assert tail[-1]["torques"] == (100.0,) * 4


def test_log_write_errors_are_counted() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=5, log_path="/dev/full")
    bridge.start()
    fd = open_raw_peer(bridge.pty_path)
    try:
        time.sleep(0.3)
    finally:
        bridge.stop()
        os.close(fd)
    s = bridge.stats()
    assert s["tx_frames"] > 10
    assert s["log_errors"] >= s["tx_frames"] - 5  # lines queued before the peer: none
    assert s["log_dropped"] == 0


def test_fifo_without_reader_as_log_path_is_refused(tmp_path) -> None:
    fifo = tmp_path / "log.fifo"
    os.mkfifo(fifo)
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=10, log_path=fifo)
    result: list[object] = []

    def go() -> None:
        try:
            bridge.start()
            result.append("started")
        except Exception as e:  # noqa: BLE001
            result.append(e)

    th = threading.Thread(target=go, daemon=True)
    th.start()
    th.join(3)
    if th.is_alive():  # unblock the hanging open so the test can end
        os.close(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK))
        th.join(3)
        pytest.fail("start() blocked on a FIFO without a reader")
    bridge.stop()
    assert isinstance(result[0], can_bridge.ConfigError), result
    assert "log_path" in str(result[0]) and "FIFO" in str(result[0])
    assert not bridge.running


def test_racing_start_and_stop_from_threads_never_hangs() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=2, stop_safe_frames=1)
    end = time.monotonic() + 2.0

    def worker(k: int) -> None:
        i = 0
        while time.monotonic() < end:
            i += 1
            try:
                if (i + k) % 2:
                    bridge.start()
                else:
                    bridge.stop()
            except can_bridge.StateError:
                pass

    ts = [threading.Thread(target=worker, args=(k,), daemon=True) for k in range(4)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(end - time.monotonic() + 5)
    assert not any(t.is_alive() for t in ts), "start()/stop() hung"
    bridge.stop()
    assert not bridge.running
    time.sleep(0.1)
    names = [
        open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")
    ]
    assert not [n for n in names if n.startswith("can_bridge")], names


@pytest.mark.parametrize(
    ("torques", "match"),
    [
        ({0: 1.0, 1: 2.0, 2: 3.0, 3: 4.0}, "torques must be an ordered sequence .*dict"),
        ({1.0, 2.0, 3.0, 4.0}, "torques must be an ordered sequence .*set"),
        ([True, False, True, False], r"torques\[0\] = True is not a real number"),
        ([1.0, 2.0, 3.0, 1j], r"torques\[3\] = 1j is not a real number"),
    ],
)
def test_set_command_refuses_unordered_bool_and_complex_torques(torques, match: str) -> None:
    b = can_bridge.Bridge("slcan-pty:")
    with pytest.raises(can_bridge.CommandError, match=match):
        b.set_command(torques, 1)
    b.set_command((1.0, 2.0, 3.0, 4.0), 1)  # nothing was accepted before


def test_set_command_refuses_numpy_complex_and_bool_and_bool_seq() -> None:
    np = pytest.importorskip("numpy")
    b = can_bridge.Bridge("slcan-pty:")
    with pytest.raises(can_bridge.CommandError, match=r"torques\[0\] .* not a real number"):
        b.set_command(np.array([1, 2, 3, 4], dtype=complex), 1)
    with pytest.raises(can_bridge.CommandError, match=r"torques\[0\] .* not a real number"):
        b.set_command(np.array([1, 2, 3, 4], dtype=np.complex64), 1)
    with pytest.raises(can_bridge.CommandError, match=r"torques\[0\] .* not a real number"):
        b.set_command(np.array([True, False, True, False]), 1)
    for seq in (True, np.bool_(True)):
        with pytest.raises(can_bridge.CommandError, match="seq must be an integer"):
            b.set_command((1.0, 2.0, 3.0, 4.0), seq)
    b.set_command(np.array([1, 2, 3, 4], dtype=np.float32), np.uint64(5))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"period_ms": "50"}, "period_ms must be a real number"),
        ({"period_ms": True}, "period_ms must be a real number"),
        ({"period_ms": 10**400}, r"period_ms = 1000.* is out of range"),
        ({"hold_after_ms": -(10**400)}, r"hold_after_ms = -1000.* is out of range"),
        ({"max_torque_nm": 10**400}, r"max_torque_nm = 1000.* is out of range"),
        ({"max_torque_nm": [1, 2, 3, 10**400]}, r"max_torque_nm\[3\] = 1000.* is out of range"),
        ({"max_rate_nm_per_tick": "x"}, "max_rate_nm_per_tick must be a real number"),
        ({"hold_after_ms": [1]}, "hold_after_ms must be a real number"),
        ({"max_torque_nm": True}, r"max_torque_nm"),
        ({"bitrate": -1}, "bitrate must be an integer in"),
        ({"bitrate": 2**40}, "bitrate must be an integer in"),
        ({"bitrate": 500000.0}, "bitrate must be an integer in"),
        ({"stop_safe_frames": -1}, "stop_safe_frames must be an integer in 0..=100"),
        ({"rx_max_counter_delta": 300}, "rx_max_counter_delta must be an integer in 1..=14"),
        ({"trace_capacity": -1}, "trace_capacity must be an integer in"),
        ({"trace_capacity": 2**70}, "trace_capacity must be an integer in"),
        ({"rt_priority": 2**40}, "rt_priority must be an integer in 1..=99"),
        ({"rt_priority": True}, "rt_priority must be an integer in 1..=99"),
        ({"log_path": 5}, "log_path must be a str or os.PathLike"),
    ],
)
def test_constructor_type_and_range_errors_name_the_argument(kwargs: dict, match: str) -> None:
    with pytest.raises(can_bridge.ConfigError, match=match):
        can_bridge.Bridge("slcan-pty:", **kwargs)


def test_overflowing_torque_is_out_of_range_not_a_type_error() -> None:
    b = can_bridge.Bridge("slcan-pty:")
    with pytest.raises(can_bridge.CommandError, match=r"torques\[2\] = 1000.* is out of range"):
        b.set_command([1.0, 2.0, 10**400, 4.0], 1)
    b.set_command((1.0, 2.0, 3.0, 4.0), 1)  # nothing was accepted before


def test_pty_path_is_none_once_stopped() -> None:
    # The closed /dev/pts/N can be handed to another pty: never report it.
    b = can_bridge.Bridge("slcan-pty:", period_ms=10)
    b.start()
    path = b.pty_path
    assert path is not None and path.startswith("/dev/")
    b.stop()
    assert b.pty_path is None
    with b:
        assert b.pty_path is not None
    assert b.pty_path is None


def test_constructor_still_accepts_the_usual_types(tmp_path) -> None:
    b = can_bridge.Bridge(
        "slcan-pty:",
        20,
        max_torque_nm=[100, 100.0, 50, 50],
        max_rate_nm_per_tick=5,
        hold_after_ms=100,
        safe_after_ms=200.0,
        fault_after_ms=300,
        state_timeout_ms=250,
        log_path=tmp_path / "x.log",
        bitrate=250000,
        stop_safe_frames=0,
        rx_max_counter_delta=3,
        trace_capacity=10,
        rt_priority=None,
    )
    assert b.period_ms == 20.0
    with pytest.raises(can_bridge.ConfigError, match="channel must be a str"):
        can_bridge.Bridge(5)  # type: ignore[arg-type]
