"""Regression tests for reviewed defects: limits enforced on the wire value,
a slow peer under the age rule, reset_fault without a fault, log write
errors, a FIFO as log_path, start/stop racing, argument type errors."""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import pytest

import can_bridge
from ampc_jax.testing.can_peers import CmdChecker, recv_until, slcan_peer

pytestmark = pytest.mark.timeout(60)


def open_raw_peer(path: str) -> int:
    """A raw SLCAN host on the pty slave that opens the channel."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    os.write(fd, b"C\rS6\rO\r")
    return fd


def parse_cmds(buf: bytes) -> list[dict]:
    chk = CmdChecker(continuous=False)
    for line in buf.split(b"\r"):
        if line.startswith(b"t"):
            ident = int(line[1:4], 16)
            dlc = int(line[4:5])
            chk.add(ident, False, bytes.fromhex(line[5 : 5 + 2 * dlc].decode()))
    return chk.frames


@pytest.mark.parametrize(
    ("max_torque", "rise"),
    [
        (300.3, 1e5),
        ((100.9, 50.0, 2.7, 999.9), 1e5),
        (300.0, 450.0),
        ((10.0, 2.9, 3.1, 1.2), 700.0),
    ],
)
def test_torque_and_step_on_the_wire_never_exceed_the_limits(max_torque, rise) -> None:
    limits = max_torque if isinstance(max_torque, tuple) else (max_torque,) * 4
    period = 0.005
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=period * 1e3,
        torque_min_nm=tuple(-x for x in limits),
        torque_max_nm=limits,
        rise_nm_per_s=rise,
        release_nm_per_s=rise,
        hold_after_ms=1000,
        safe_after_ms=3000,
        fault_after_ms=4000,
    )
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        seq = 0

        def fresh(f: dict) -> bool:
            nonlocal seq
            seq += 1
            bridge.set_command((4000.0, -4000.0, 4000.0, -4000.0), seq)
            return f["torques"] == want

        # Limits round toward zero onto the 2 Nm grid: 300.3 -> 300, 2.7 -> 2, ...
        want = tuple(s * (int(lim / 2) * 2) for s, lim in zip((1, -1, 1, -1), limits, strict=True))
        frames = recv_until(bus, chk, fresh, timeout=20)
    active = [f for f in frames if f["mode"] == "active"]
    assert active
    for f in frames:
        assert all(abs(t) <= lim for t, lim in zip(f["torques"], limits, strict=True)), f
    prev = (0.0,) * 4
    for f in active:
        steps = [abs(b - a) for a, b in zip(prev, f["torques"], strict=True)]
        assert all(d <= rise * period + 1e-9 for d in steps), (prev, f)
        prev = f["torques"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"rise_nm_per_s": 30.0}, r"rise_nm_per_s\[FL\] = 30 Nm/s moves less than one 2 Nm step"),
        ({"release_nm_per_s": (100.0, 100.0, 10.0, 100.0)}, r"release_nm_per_s\[RL\] = 10 "),
        ({"safe_release_nm_per_s": 1.0}, "safe_release_nm_per_s = 1 Nm/s moves less"),
        ({"torque_max_nm": -1.0}, r"torque_max_nm\[FL\] = -1 must be in \[0, 4094\]"),
        (
            {"torque_min_nm": (0.0, 0.0, 5.0, 0.0)},
            r"torque_min_nm\[RL\] = 5 must be in \[-4096, 0\]",
        ),
    ],
)
def test_limits_below_the_wire_resolution_or_range_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(can_bridge.ConfigError, match=match):
        can_bridge.Bridge("slcan-pty:", **kwargs)


def test_a_peer_reading_only_every_150_ms_gets_fresh_frames_and_the_last_stop_frame() -> None:
    """Under the age rule a slow reader gets the newest frame each time, never
    a backlog, and the stop sequence's last (zero) frame before the close."""
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=20, stop_safe_frames=3)
    bridge.start()
    fd = open_raw_peer(bridge.pty_path)
    buf = bytearray()
    reads: list[int] = []

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
            reads.append(d.count(b"\r"))
            buf.extend(d)

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        for i in range(25):
            bridge.set_command((-50.0,) * 4, i + 1)
            time.sleep(0.02)
        bridge.stop()  # stops, not hangs (the test's timeout catches a hang)
        th.join(3)
    finally:
        os.close(fd)
    frames = parse_cmds(bytes(buf))
    assert any(f["mode"] == "active" for f in frames)
    assert frames[-1]["mode"] == "safe" and frames[-1]["torques"] == (0.0,) * 4
    assert max(reads) <= 4, reads  # a line or two per read (plus replies), not a backlog


def test_reset_fault_without_a_fault_is_a_no_op() -> None:
    bridge = can_bridge.Bridge(
        "slcan-pty:", period_ms=10, rise_nm_per_s=1000.0, release_nm_per_s=1000.0
    )
    bridge.start()
    fd = open_raw_peer(bridge.pty_path)
    try:
        seq = 0
        buf = b""

        def command_and_read() -> None:
            nonlocal seq, buf
            seq += 1
            bridge.set_command((-100.0,) * 4, seq)
            # the peer keeps reading (a peer that does not is dropped by the age rule)
            if select.select([fd], [], [], 0.01)[0]:
                buf += os.read(fd, 65536)

        for _ in range(20):
            command_and_read()
        bridge.reset_fault()
        for _ in range(5):
            command_and_read()
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
    assert tail[-1]["torques"] == (-100.0,) * 4


def test_log_write_errors_are_counted() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=5, log_path="/dev/full", log_overwrite=True)
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
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=10, log_path=fifo, log_overwrite=True)
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
    with can_bridge.Bridge("slcan-pty:") as b:
        with pytest.raises(can_bridge.CommandError, match=match):
            b.set_command(torques, 1)
        b.set_command((1.0, 2.0, 3.0, 4.0), 1)  # nothing was accepted before


def test_set_command_refuses_numpy_complex_and_bool_and_bool_seq() -> None:
    np = pytest.importorskip("numpy")
    b = can_bridge.Bridge("slcan-pty:")
    b.start()
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
    b.stop()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"period_ms": "50"}, "period_ms must be a real number"),
        ({"period_ms": True}, "period_ms must be a real number"),
        ({"period_ms": 10**400}, r"period_ms = 1000.* is out of range"),
        ({"hold_after_ms": -(10**400)}, r"hold_after_ms = -1000.* is out of range"),
        ({"torque_max_nm": 10**400}, r"torque_max_nm = 1000.* is out of range"),
        ({"torque_max_nm": [1, 2, 3, 10**400]}, r"torque_max_nm\[3\] = 1000.* is out of range"),
        ({"rise_nm_per_s": "x"}, "rise_nm_per_s must be 4 numbers"),
        ({"hold_after_ms": [1]}, "hold_after_ms must be a real number"),
        ({"torque_max_nm": True}, r"torque_max_nm"),
        ({"limit_rule": "maybe"}, 'limit_rule = "maybe" must be "clamp" or "refuse"'),
        ({"on_transport_loss": 1}, "on_transport_loss must be"),
        ({"log_overwrite": 1}, "log_overwrite must be a bool"),
        ({"config": 5}, "config must be a str or os.PathLike"),
        ({"bitrate": -1}, "bitrate must be an integer in"),
        ({"bitrate": 2**40}, "bitrate must be an integer in"),
        ({"bitrate": 500000.0}, "bitrate must be an integer in"),
        ({"stop_safe_frames": -1}, "stop_safe_frames must be an integer in 1..=100"),
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
    with can_bridge.Bridge("slcan-pty:") as b:
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
        config=can_bridge.default_config_path(),
        torque_min_nm=[-100, -100.0, -50, -50],
        torque_max_nm=[0, 0.0, 50, 50],
        rise_nm_per_s=500,
        release_nm_per_s=(1000, 1000, 500.0, 500),
        safe_release_nm_per_s=400,
        limit_rule="refuse",
        transport_timeout_ms=100,
        on_transport_loss="raise",
        log_overwrite=False,
        hold_after_ms=100,
        safe_after_ms=200.0,
        fault_after_ms=300,
        state_timeout_ms=250,
        log_path=tmp_path / "x.log",
        bitrate=250000,
        stop_safe_frames=1,
        rx_max_counter_delta=3,
        rx_sync_frames=1,
        rx_max_strikes=0,
        trace_capacity=10,
        rt_priority=None,
    )
    assert b.period_ms == 20.0
    with pytest.raises(can_bridge.ConfigError, match="channel must be a str"):
        can_bridge.Bridge(5)  # type: ignore[arg-type]
