"""Fault-injecting peers of the CAN bridge's tests and benchmarks: a socketcand
server that can stall, die and come back on the same port; a scripted SLCAN serial adapter on
a pty (answers the handshake, acknowledges frames with ``z``, can stall); a
raw SLCAN host on the bridge's pty. None of them uses the Rust codec: frames
are checked by :mod:`~.can_peers` (cantools + autosar-e2e)."""

from __future__ import annotations

import os
import random
import re
import select
import socket
import threading
import time
import tty

SEND_RE = re.compile(rb"<\s*send\s+([0-9A-Fa-f]+)\s+(\d+)((?:\s+[0-9A-Fa-f]{1,2})*)\s*>")


class SocketcandServer:
    """socketcand raw mode on 127.0.0.1: handshake, ``< echo >`` answered as
    real socketcand does (state_raw.c), ``< send >`` recorded with the arrival
    time. ``stall`` stops reading (and answering) until ``resume``; ``kill``
    closes everything; ``restart`` listens again on the same port."""

    def __init__(self, port: int = 0) -> None:
        self.sent: list[tuple[float, int, bool, bytes]] = []
        self.errors: list[str] = []
        self.reading = threading.Event()
        self.reading.set()
        self.connections = 0
        self._stop = threading.Event()
        self._listen(port)

    def _listen(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", port))
        self.sock.listen(4)
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self._stop.clear()
        self.conn: socket.socket | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, OSError):
                continue
            self.connections += 1
            self.conn = conn
            try:
                self._serve(conn)
            except OSError as e:
                if not self._stop.is_set():
                    self.errors.append(repr(e))
            finally:
                conn.close()
                self.conn = None

    def _serve(self, conn: socket.socket) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(b"< hi >")
        for word in (b"open", b"rawmode"):
            buf = b""
            while b">" not in buf:
                chunk = conn.recv(256)
                if not chunk:
                    return
                buf += chunk
            assert word in buf, buf
            conn.sendall(b"< ok >")
        conn.settimeout(0.01)
        buf = b""
        while not self._stop.is_set():
            if not self.reading.is_set():
                time.sleep(0.005)
                continue
            try:
                chunk = conn.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                return
            now = time.monotonic()
            buf += chunk
            while True:
                i = buf.find(b">")
                if i < 0:
                    break
                msg, buf = buf[: i + 1], buf[i + 1 :]
                if b"echo" in msg:
                    conn.sendall(b"< echo >")
                    continue
                m = SEND_RE.search(msg)
                if m:
                    ident, n = m.group(1), int(m.group(2))
                    data = bytes(int(b, 16) for b in m.group(3).split())
                    if len(data) != n:
                        self.errors.append(f"length mismatch in {msg!r}")
                    self.sent.append((now, int(ident, 16), len(ident) == 8, data))

    def stall(self) -> None:
        self.reading.clear()

    def resume(self) -> None:
        self.reading.set()

    def kill(self) -> None:
        self._stop.set()
        if self.conn is not None:
            try:
                self.conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self.sock.close()
        self.thread.join(2)

    def restart(self) -> None:
        self._listen(self.port)


class SerialAdapter:
    """A Lawicel-style SLCAN adapter on the master side of a pty; the bridge
    opens the slave as ``slcan:PATH``. Answers ``V`` with a version and other
    commands with CR, acknowledges each transmitted frame with ``z\\r``, and
    records frame lines with their arrival time. ``stall`` stops reading."""

    def __init__(self, *, answer: bool = True) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self.answer = answer
        self.lines: list[tuple[float, bytes]] = []
        self.commands: list[bytes] = []
        self.reading = threading.Event()
        self.reading.set()
        self._stall_after: int | None = None
        self._stop = threading.Event()
        self._buf = b""
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.reading.is_set():
                time.sleep(0.005)
                continue
            r, _, _ = select.select([self.master], [], [], 0.01)
            if not r:
                continue
            try:
                chunk = os.read(self.master, 65536)
            except OSError:
                return
            now = time.monotonic()
            self._buf += chunk
            while b"\r" in self._buf and self.reading.is_set():
                line, self._buf = self._buf.split(b"\r", 1)
                self._handle(now, line)

    def _handle(self, now: float, line: bytes) -> None:
        if line[:1] in (b"t", b"T", b"r", b"R"):
            self.lines.append((now, line))
            reply = b"z\r"
        else:
            self.commands.append(line)
            reply = b"V1013\r" if line == b"V" else b"\r"
        if self.answer:
            os.write(self.master, reply)
        if self._stall_after is not None and len(self.lines) >= self._stall_after:
            self._stall_after = None
            self.reading.clear()

    def send_line(self, line: bytes) -> None:
        os.write(self.master, line)

    def stall_after(self, n_more: int) -> None:
        """Stop reading right after acknowledging the n-th frame from now:
        between two of the bridge's ticks."""
        self._stall_after = len(self.lines) + n_more

    def stall(self) -> None:
        self.reading.clear()

    def resume(self) -> None:
        self.reading.set()

    def close(self) -> None:
        self._stop.set()
        self.thread.join(2)
        os.close(self.master)
        os.close(self.slave)


def open_raw_host(path: str, open_cmd: bytes = b"O") -> int:
    """A raw SLCAN host on the bridge's pty slave that opens the channel."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    tty.setraw(fd)
    os.write(fd, b"C\rS6\r" + open_cmd + b"\r")
    return fd


def read_all(fd: int, seconds: float) -> bytes:
    out = b""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if select.select([fd], [], [], 0.02)[0]:
            try:
                out += os.read(fd, 65536)
            except BlockingIOError:
                continue
            except OSError:
                break
    return out


def burst_after(times: list[float], t_resume: float, window: float) -> int:
    """How many frames arrived within ``window`` seconds after ``t_resume``."""
    return sum(1 for t in times if t_resume <= t <= t_resume + window)


class SocketcandBus:
    """A socketcand server on 127.0.0.1 that behaves as one CAN bus for many
    clients (real socketcand serves each client from its own process on the
    same interface): every ``< send >`` read from one client is written to
    the bus, that is, stamped with the server's clock, recorded in
    ``frames`` and relayed to every other client in raw mode as
    ``< frame ID SEC.USEC DATA >`` (python-can's socketcand interface can be
    one of them). ``< echo >`` is answered as socketcand's ``state_raw.c``
    does. ``stall()`` stops reading from every client, as a server that
    stops being scheduled; ``stall_after(n)`` stalls once the n-th frame
    from now is on the bus and the echo behind it answered: between two of
    the bridge's ticks, the phase at which a frame handed to TCP at the
    next tick could only reach the bus when the server resumes;
    ``stall_after_probe()`` stalls right after answering the next tick's
    probe (the echo after the next frame's own), the phase at which the
    frame written at that deadline reaches the server's kernel only.
    ``echo=False``: a server that never answers ``< echo >``; ``slow``: a
    server that sleeps up to that many seconds (uniformly) before each read."""

    def __init__(self, *, echo: bool = True, slow: float = 0.0) -> None:
        self.echo = echo
        self.slow = slow
        self._rng = random.Random(4)
        self._probe_arm = False
        self._echoes_to_stall = 0
        self.frames: list[tuple[float, int, bytes]] = []  # (time.time(), id, data)
        self.errors: list[str] = []
        self.reading = threading.Event()
        self.reading.set()
        self._stall_at: int | None = None
        self._stall_on_echo = False
        self._lock = threading.Lock()
        self._clients: list[socket.socket] = []
        self._stop = threading.Event()
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.thread = threading.Thread(target=self._accept, daemon=True)
        self.thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, OSError):
                continue
            threading.Thread(target=self._serve_safely, args=(conn,), daemon=True).start()

    def _serve_safely(self, conn: socket.socket) -> None:
        try:
            self._serve(conn)
        except OSError as e:
            if not self._stop.is_set():
                self.errors.append(repr(e))
        finally:
            with self._lock:
                if conn in self._clients:
                    self._clients.remove(conn)
            conn.close()

    def _serve(self, conn: socket.socket) -> None:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.sendall(b"< hi >")
        for word in (b"open", b"rawmode"):
            buf = b""
            while b">" not in buf:
                chunk = conn.recv(256)
                if not chunk:
                    return
                buf += chunk
            if word not in buf:
                self.errors.append(f"expected {word!r}, got {buf!r}")
                return
            conn.sendall(b"< ok >")
        with self._lock:
            self._clients.append(conn)
        conn.settimeout(0.01)
        buf = b""
        while not self._stop.is_set():
            if not self.reading.is_set():
                time.sleep(0.002)
                continue
            if self.slow:
                time.sleep(self._rng.random() * self.slow)
            try:
                chunk = conn.recv(65536)
            except TimeoutError:
                continue
            if not chunk:
                return
            buf += chunk
            while b">" in buf and self.reading.is_set():
                i = buf.find(b">")
                msg, buf = buf[: i + 1], buf[i + 1 :]
                if b"echo" in msg:
                    if not self.echo:
                        continue
                    conn.sendall(b"< echo >")
                    if self._stall_on_echo:
                        self._stall_on_echo = False
                        self.reading.clear()
                    if self._echoes_to_stall:
                        self._echoes_to_stall -= 1
                        if not self._echoes_to_stall:
                            self.reading.clear()
                    continue
                m = SEND_RE.search(msg)
                if m:
                    self._write(
                        conn, int(m.group(1), 16), bytes(int(b, 16) for b in m.group(3).split())
                    )

    def _write(self, sender: socket.socket, ident: int, data: bytes) -> None:
        now = time.time()
        with self._lock:
            self.frames.append((now, ident, data))
            out = b"< frame %03X %d.%06d %s >" % (
                ident,
                int(now),
                int(now * 1e6) % 1_000_000,
                data.hex().upper().encode(),
            )
            for c in self._clients:
                if c is not sender:
                    try:
                        c.sendall(out)
                    except OSError:
                        pass
            if self._stall_at is not None and len(self.frames) >= self._stall_at:
                self._stall_at = None
                self._stall_on_echo = True
            if self._probe_arm:
                # this frame's own echo, then the next tick's probe
                self._probe_arm = False
                self._echoes_to_stall = 2

    def stall(self) -> None:
        self.reading.clear()

    def stall_after(self, n_more: int) -> None:
        with self._lock:
            self._stall_at = len(self.frames) + n_more

    def stall_after_probe(self) -> None:
        with self._lock:
            self._probe_arm = True

    def resume(self) -> None:
        self.reading.set()

    def close(self) -> None:
        self._stop.set()
        with self._lock:
            for c in self._clients:
                try:
                    c.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
        self.sock.close()
        self.thread.join(2)


def candump_tx(path: str, frame_id: int = 0x101) -> list[tuple[float, bytes]]:
    """The frames the bridge logged as written (candump ``-l`` format, read by
    python-can): (realtime stamp, data)."""
    import can

    return [
        (m.timestamp, bytes(m.data))
        for m in can.LogReader(path)
        if m.arbitration_id == frame_id and not m.is_rx
    ]


def frame_ages(seen: list[tuple[float, bytes]], written: list[tuple[float, bytes]]) -> list[float]:
    """Age of each frame a peer saw (its receive time minus the time the bridge
    wrote the same bytes: the latest write of those bytes at or before it, with
    20 ms for the bridge's stamp, taken after its write returns). The same
    bytes must not recur within the ages measured: commands that change with
    every tick make them unique."""
    ages = []
    for t, data in seen:
        cands = [w for w, d in written if d == data and w <= t + 0.02]
        if cands:
            ages.append(t - max(cands))
    return ages
