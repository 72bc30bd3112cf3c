"""``socketcand:HOST:PORT/BUS`` against a socketcand-protocol test server
written here from the protocol (handshake replies sent one per ``send`` with
TCP_NODELAY, frames as contiguous hex, ``< echo >`` answered as in raw mode)."""

from __future__ import annotations

import re
import socket
import threading
import time

import pytest

import can_bridge
from ampc_jax.testing.can_peers import SENSORS, CmdChecker, db, protect

pytestmark = pytest.mark.timeout(60)

SEND_RE = re.compile(rb"<\s*send\s+([0-9A-Fa-f]+)\s+(\d+)((?:\s+[0-9A-Fa-f]{1,2})*)\s*>")


class Server:
    def __init__(self, bus: str = "can0", refuse: bool = False) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.bus = bus
        self.refuse = refuse
        self.sent: list[tuple[int, bool, bytes]] = []
        self.handshake: list[bytes] = []
        self.errors: list[str] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def _expect(self, conn: socket.socket, word: bytes) -> None:
        buf = b""
        while b">" not in buf:
            chunk = conn.recv(256)
            if not chunk:
                raise ConnectionError("client closed")
            buf += chunk
        self.handshake.append(buf)
        assert word in buf, buf

    def run(self) -> None:
        conn, _ = self.sock.accept()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            conn.sendall(b"< hi >")
            self._expect(conn, b"< open " + self.bus.encode() + b" >")
            if self.refuse:
                conn.sendall(b"< error could not open bus >")
                return
            conn.sendall(b"< ok >")
            self._expect(conn, b"< rawmode >")
            conn.sendall(b"< ok >")
            time.sleep(0.05)
            conn.settimeout(0.02)
            buf = b""
            counter = 0
            next_state = time.monotonic()
            while not self.stop.is_set():
                if time.monotonic() >= next_state:
                    frames = b""
                    for name, vals in SENSORS:
                        fid = db().get_message_by_name(name).frame_id
                        now = time.time()
                        frames += b"< frame %03X %d.%06d %s >" % (
                            fid,
                            int(now),
                            int(now * 1e6) % 1_000_000,
                            protect(name, vals, counter).hex().upper().encode(),
                        )
                    conn.sendall(frames)  # back to back in one segment
                    counter = (counter + 1) % 15
                    next_state += 0.02
                try:
                    chunk = conn.recv(4096)
                except TimeoutError:
                    continue
                if not chunk:
                    break
                buf += chunk
                while b">" in buf:
                    i = buf.find(b">")
                    msg, buf = buf[: i + 1], buf[i + 1 :]
                    if b"echo" in msg:  # answered in raw mode, as socketcand's state_raw.c
                        conn.sendall(b"< echo >")
                        continue
                    m = SEND_RE.search(msg)
                    if not m:
                        continue
                    ident, n, body = m.group(1), int(m.group(2)), m.group(3).split()
                    data = bytes(int(b, 16) for b in body)
                    if len(data) != n:
                        self.errors.append(f"length mismatch in {m.group(0)!r}")
                    self.sent.append((int(ident, 16), len(ident) == 8, data))
        except Exception as e:  # reported by the test
            self.errors.append(repr(e))
        finally:
            conn.close()
            self.sock.close()


def test_socketcand_transport_end_to_end() -> None:
    srv = Server()
    # active frames over TCP only when its residual is accepted (bus-safety.md)
    bridge = can_bridge.Bridge(
        f"socketcand:127.0.0.1:{srv.port}/can0", period_ms=20, socketcand_active=True
    )
    with bridge:
        seq = 0
        end = time.monotonic() + 0.6
        while time.monotonic() < end:
            seq += 1
            bridge.set_command((-4.0, 0.0, 250.0, -250.0), seq=seq)
            time.sleep(0.01)
        st = bridge.latest_state()
    srv.stop.set()
    srv.thread.join(5)
    assert not srv.errors, srv.errors
    assert (
        srv.handshake[0].strip() == b"< open can0 >" and srv.handshake[1].strip() == b"< rawmode >"
    )
    assert len(srv.sent) >= 25
    chk = CmdChecker()
    frames = [chk.add(*s) for s in srv.sent]
    active = [f for f in frames if f["mode"] == "active"]
    assert active[-1]["torques"] == (-4.0, 0.0, 250.0, -250.0)
    # stop: released toward zero at the safe rate (160 Nm per 20 ms tick), then zeros
    assert [f["torques"] for f in frames[-4:]] == [(0.0, 0.0, 90.0, -90.0)] + [(0.0,) * 4] * 3
    assert [f["mode"] for f in frames[-3:]] == ["safe"] * 3
    assert st["valid"] is True
    assert st["yaw_rate_radps"] == pytest.approx(0.123)
    assert st["wheel_speeds_radps"] == pytest.approx((35.1, 35.2, 39.9, 40.3))
    assert st["lat_accel_mps2"] == pytest.approx(7.5)
    assert st["set_speed_mps"] == pytest.approx(17.25)
    s = bridge.stats()
    assert s["rx_crc_errors"] == 0 and s["rx_counter_errors"] == 0 and s["rx_malformed"] == 0


def test_socketcand_refused_open_is_a_clear_error() -> None:
    srv = Server(bus="nope", refuse=True)
    bridge = can_bridge.Bridge(f"socketcand:127.0.0.1:{srv.port}/nope")
    with pytest.raises(can_bridge.TransportError, match="could not open bus"):
        bridge.start()
    srv.thread.join(5)


def test_socketcand_nobody_listening() -> None:
    s = socket.create_server(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    with pytest.raises(can_bridge.TransportError, match="connect"):
        can_bridge.Bridge(f"socketcand:127.0.0.1:{port}/can0").start()
