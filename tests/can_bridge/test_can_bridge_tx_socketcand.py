"""Out over socketcand: TCP cannot take back a frame the server's kernel
holds (an abortive close does not help: Linux hands queued bytes to the
reader before the reset, checked below), so the bridge sends only safe
frames there unless told to accept the residual (``socketcand_active``),
and never active frames to a server that gives no sign of reading (no
answer to ``< echo >``). docs/bus-safety.md states the rule, the residual
and its measured bound.

A socketcand server relays between its clients as one bus
(ampc_jax.testing.can_fault_peers.SocketcandBus), stamping each frame as it writes it to the
bus; each frame's age is that stamp against the bridge's candump log.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
from pathlib import Path

import pytest

import can_bridge
from ampc_jax.testing.budget import budget
from ampc_jax.testing.can_fault_peers import SocketcandBus, candump_tx, frame_ages
from ampc_jax.testing.can_peers import CmdChecker

pytestmark = pytest.mark.timeout(60)

PERIOD = 0.05
# a frame of the last period, with room for a loaded machine's scheduling
# (the stalls below are 0.3 s and longer: a stale frame is at least that old)
FRESH = 4 * PERIOD


class Commander:
    """A fresh command every 10 ms: RL ramps through the rear range (every
    frame's bytes unique)."""

    def __init__(self, bridge: can_bridge.Bridge) -> None:
        self.bridge = bridge
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        seq = 0
        while not self.stop.is_set():
            seq += 1
            try:
                self.bridge.set_command((0.0, 0.0, 200.0 + 2.0 * (seq % 600), 0.0), seq)
            except can_bridge.CanBridgeError:
                return
            time.sleep(0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)


def _run(tmp_path: Path, srv: SocketcandBus, during, **kw) -> tuple[list, list, dict, dict]:
    """Run a bridge on ``srv`` for about 1.2 s plus ``during(srv, stats)``;
    returns (frames on the bus decoded, their ages, stats while running,
    stats after)."""
    log = tmp_path / "b.log"
    b = can_bridge.Bridge(f"socketcand:127.0.0.1:{srv.port}/can0", period_ms=50, log_path=log, **kw)
    b.start()
    cmd = Commander(b)
    running: dict = {}
    try:
        time.sleep(0.6)
        during(srv, b)
        time.sleep(0.6)
        running = b.stats()
    finally:
        cmd.close()
        b.stop()
        srv.close()
    chk = CmdChecker()
    frames = [chk.add(ident, False, data) for _, ident, data in srv.frames if ident == 0x101]
    seen = [(t, data) for t, ident, data in srv.frames if ident == 0x101]
    ages = frame_ages(seen, candump_tx(str(log)))
    return frames, list(zip(frames, ages, strict=False)), running, b.stats()


def _stall_after_probe(stall: float):
    def during(srv: SocketcandBus, _b) -> None:
        srv.stall_after_probe()
        end = time.monotonic() + budget(5)
        while srv.reading.is_set() and time.monotonic() < end:
            time.sleep(0.001)
        assert not srv.reading.is_set(), "the server never stalled"
        time.sleep(stall)
        srv.resume()

    return during


@pytest.mark.parametrize("stall", [1.0, 0.3])
def test_tx_socketcand_stall_after_the_probe_reads_no_stale_active_frame(
    tmp_path: Path, stall
) -> None:
    """A server that stops right after answering the probe finds the frame
    written at that deadline when it resumes (TCP cannot recall it). With
    the default configuration every frame is safe (0 Nm), so no active or
    torque-carrying frame is ever older than a period on the bus (before:
    an active frame 0.97-1.0 s old), and stats() says why."""
    frames, aged, running, _ = _run(tmp_path, SocketcandBus(), _stall_after_probe(stall))
    assert frames
    assert all(f["mode"] in ("safe", "fault") for f in frames), {f["mode"] for f in frames}
    assert all(f["torques"] == (0.0,) * 4 for f in frames)
    stale = [(f, a) for f, a in aged if a > FRESH and f["torques"] != (0.0,) * 4]
    assert not stale, stale
    assert running["safety_state"] == "safe_only"
    assert running["tx_safe_only"] > 0
    assert running["transport_state"] == "up"


@pytest.mark.parametrize("active", [False, True])
def test_tx_socketcand_a_server_without_echo_gets_safe_frames_only(
    tmp_path: Path, active: bool
) -> None:
    """A server that never answers ``< echo >`` gives the bridge no way to
    tell what it has read: only safe frames go out, even with
    ``socketcand_active``; ``transport_state`` is "unverified" and
    ``safety_state`` "safe_only" (before: 18 of 56 frames arrived 0.1-0.95 s
    old under load, tx_stale_dropped=0, transport_state "up")."""

    def stall(srv: SocketcandBus, _b) -> None:
        srv.stall()
        time.sleep(0.8)
        srv.resume()

    frames, aged, running, _ = _run(
        tmp_path, SocketcandBus(echo=False), stall, socketcand_active=active
    )
    assert frames
    assert all(f["mode"] == "safe" and f["torques"] == (0.0,) * 4 for f in frames)
    assert running["transport_state"] == "unverified"
    assert running["safety_state"] == "safe_only"
    assert running["tx_safe_only"] > 0


def test_tx_socketcand_active_a_slow_server_gets_no_stale_frame(tmp_path: Path) -> None:
    """With ``socketcand_active``: a server that sleeps up to 30 ms before
    each read gets active frames, each at most a period old when it reaches
    the bus: a frame goes out only once the probe ahead of it is answered."""
    frames, aged, running, _ = _run(
        tmp_path, SocketcandBus(slow=0.03), lambda *_: None, socketcand_active=True
    )
    assert any(f["mode"] == "active" for f in frames)
    assert aged and max(a for _, a in aged) < FRESH, sorted(a for _, a in aged)[-3:]
    assert running["safety_state"] in ("active", "lost")


def test_tx_socketcand_active_residual_is_one_frame_then_a_ramp(tmp_path: Path) -> None:
    """The residual ``socketcand_active`` accepts, as docs/bus-safety.md
    states it: a server that stops right after answering its probe reads the
    one frame written at that deadline when it resumes, and nothing else
    stale; the frames after it ramp from zero (the gap reached the
    actuator's timeout)."""
    frames, aged, _, _ = _run(
        tmp_path, SocketcandBus(), _stall_after_probe(0.5), socketcand_active=True
    )
    stale = [i for i, (_, a) in enumerate(aged) if a > FRESH]
    assert len(stale) <= 1, [aged[i] for i in stale]
    if stale:
        nxt = [f for f, _ in aged[stale[0] + 1 :] if f["mode"] == "active"]
        assert nxt and nxt[0]["torques"][2] <= 500.0, nxt[:2]


def test_tx_socketcand_an_abortive_close_does_not_discard_unread_data() -> None:
    """Why the bridge does not reset a stalled server's connection: on this
    kernel a reader gets the bytes queued before a reset (SO_LINGER 0), then
    the error, so the frame would still reach the bus."""
    srv = socket.create_server(("127.0.0.1", 0))
    c = socket.create_connection(srv.getsockname())
    s, _ = srv.accept()
    try:
        c.sendall(b"< send 101 8 00 11 22 33 44 55 66 77 >")
        time.sleep(0.05)
        c.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        c.close()
        time.sleep(0.05)
        assert s.recv(100) == b"< send 101 8 00 11 22 33 44 55 66 77 >"
        with pytest.raises(ConnectionResetError):
            s.recv(100)
    finally:
        s.close()
        srv.close()
