"""Fault-injection figures of can_bridge: issue 21's findings re-measured, and
issue 29's (the bus under attack and faults).

Every case runs a fresh bridge with an independent python-can peer (the
``slcan`` interface on the pty, or the ``socketcand`` interface as a second
client of a socketcand server that relays between its clients as one bus)
that takes every torque frame in python-can's receive thread. Per fault:

* ``framed``: the frames the bridge wrote (``tx_frames``);
* ``stale``: frames older than one period when the peer got them (its
  receive time against the bridge's candump log of write times, the same
  clock), with the oldest one's age;
* ``valid %``: ``latest_state()`` samples (every ms) judged valid;
* ``intruder``: samples judged valid at an intruder's value.

Targets: 0 stale, 0 intruder samples believed. The cases:

* ``socketcand stall`` (issue 29 item 2): the server stops reading for
  ``--stall`` s, ``--trials`` times right after answering the echo behind a
  frame (between two ticks) and as many times at a random phase;
* ``late open`` / ``reopen`` (item 1): the command held fresh at 1500 Nm, the
  peer opens its channel 1 s late, or closes (``C``) and reopens it: the
  first frame's rear torque and what ``safety_state`` said meanwhile;
* intruders (item 3): a real sender at 12 m/s and frames at 20 m/s on the
  same identifier with sound CRCs: one a counter +1 or +2 ahead, three in
  sequence after a jump, an interleaved stream with its own counter, a
  replayed stream with a constant counter offset;
* plausibility (item 4): the speed alternating 12 <-> 85 m/s each frame;
  front wheels at 40 m/s against 12;
* bursts: one sender's VehicleMotion frames back to back, the counter +2 and
  the speed +0.8 m/s each (12 -> 85 m/s), and a counter +1 variant
  (``ampc_jax.testing.can_rx_burst``; the receive side's pace rule);
* bad CRC 1 in 8 (item 13);
* issue 21's: pty, serial adapter and socketcand stalls (frames found within
  20 ms of resuming, frames dropped for age), frozen / stepping / doubled /
  mostly-bad-CRC sensors, socketcand restart, a ``V`` flood, watchdog times;
* the transmit gaps (``--only tx``; docs/bus-safety.md, "Out"): a raw SLCAN
  host stopped inside a torque frame (after byte 1, 9, 20 and 21: the last is
  the stated residual) and between frames for 150-300 ms, python-can's own
  reader stopped inside a frame, with the command held at RL = 1500 Nm and
  the vehicle's actuators (``stale``: E2E-valid frames older than a period;
  ``steps``: frames after a gap of the actuator's timeout that are not a
  ramp from zero; ``cut``: lines ended so that their CRC fails);
  socketcand stalls right after the probe, at random, an echo-less server
  and a slow one, each with and without ``socketcand_active``
  (``stale with torque``: stale frames carrying a torque); a 2 s flood of
  unknown frames on the pty with a log (lines, bytes, suppressed).

Run::

    python bench/bench_can_bridge_faults.py            # about 5 min
    python bench/bench_can_bridge_faults.py --stall 5 --trials 10 --json out.json
    python bench/bench_can_bridge_faults.py --only tx --short --stall 1 --trials 3
"""

from __future__ import annotations

import argparse
import json
import os
import random
import tempfile
import threading
import time
from pathlib import Path

import _meta  # bench/_meta.py, beside this script
import can

import can_bridge
from ampc_jax.testing.can_fault_peers import (
    SerialAdapter,
    SocketcandBus,
    SocketcandServer,
    burst_after,
    candump_tx,
    frame_ages,
    open_raw_host,
    read_all,
)
from ampc_jax.testing.can_peers import MOTION, WHEELS, CmdChecker, send_sensors, state_message
from ampc_jax.testing.can_rx_burst import REPORT, Burst

CYCLE = 0.02  # the sensors' cycle (the DBC's GenMsgCycleTime)


def _bus(path: str) -> can.BusABC:
    return can.Bus(interface="slcan", channel=path, sleep_after_open=0, bitrate=500000)


class Peer:
    """Every torque frame a python-can bus receives, in its receive thread
    (``can.Notifier``), with the host clock at reception."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.seen: list[tuple[float, bytes]] = []
        outer = self

        class Take(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                if msg.arbitration_id == 0x101:
                    outer.seen.append((time.time(), bytes(msg.data)))

            def on_error(self, exc: Exception) -> None:  # the bridge closed: over
                pass

        self.notifier = can.Notifier(bus, [Take()], timeout=0.02)

    def close(self) -> None:
        self.notifier.stop()
        try:
            self.bus.shutdown()
        except can.CanError:
            pass


class Commander:
    """A fresh command every 10 ms: ``torques(seq)``."""

    def __init__(self, bridge: can_bridge.Bridge, torques) -> None:
        self.bridge, self.torques = bridge, torques
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        seq = 0
        while not self.stop.is_set():
            seq += 1
            try:
                self.bridge.set_command(self.torques(seq), seq)
            except can_bridge.CanBridgeError:
                return
            time.sleep(0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)


def _stale(seen: list, log: str, period_s: float) -> dict:
    ages = frame_ages(seen, candump_tx(log))
    old = [a for a in ages if a > period_s]
    return {"stale": len(old), "oldest_s": round(max(ages, default=0.0), 4), "seen": len(ages)}


# ---------------------------------------------------------------- issue 29


def socketcand_stall(
    stall: float,
    trials: int,
    phase: str,
    period_ms: float = 50.0,
    server: dict | None = None,
    **bridge_kw,
) -> dict:
    """The server stops reading for ``stall`` s, ``trials`` times: right after
    answering a frame's echo (``between``), right after answering the probe
    ahead of a deadline (``probe``) or at a random moment (``random``).
    ``server``: SocketcandBus's options (``echo=False``: no echo answered);
    ``bridge_kw``: the bridge's (``socketcand_active``). ``stale``: frames
    older than a period on the bus; ``stale_torque``: of which carrying a
    torque; ``valid``: frames E2E-valid (all of them)."""
    rng = random.Random(29)
    totals = {
        "framed": 0,
        "stale": 0,
        "stale_torque": 0,
        "oldest_s": 0.0,
        "seen": 0,
        "trials": trials,
        "states": set(),
    }
    with tempfile.TemporaryDirectory() as d:
        for k in range(trials):
            srv = SocketcandBus(**(server or {}))
            log = os.path.join(d, f"s{k}.log")
            b = can_bridge.Bridge(
                f"socketcand:127.0.0.1:{srv.port}/can0",
                period_ms=period_ms,
                log_path=log,
                **bridge_kw,
            )
            peer = Peer(
                can.Bus(interface="socketcand", host="127.0.0.1", port=srv.port, channel="can0")
            )
            b.start()
            cmd = Commander(b, lambda seq: (0.0, 0.0, 2.0 * (seq % 700), 0.0))
            time.sleep(0.5 + rng.random() * period_ms / 1e3)
            if phase in ("between", "probe"):
                if phase == "between":
                    srv.stall_after(1)
                else:
                    srv.stall_after_probe()
                end = time.monotonic() + 5
                while srv.reading.is_set() and time.monotonic() < end:
                    time.sleep(0.002)
            else:
                srv.stall()
            time.sleep(stall)
            srv.resume()
            time.sleep(0.5)
            cmd.close()
            s = b.stats()
            b.stop()
            time.sleep(0.1)
            peer.close()
            srv.close()
            r = _stale(peer.seen, log, period_ms / 1e3)
            totals["states"].add(f"{s['transport_state']}/{s['safety_state']}")
            written = candump_tx(log)
            for (t, data), age in zip(peer.seen, frame_ages(peer.seen, written), strict=False):
                del t
                if age > period_ms / 1e3 and data[2:] != bytes(6):
                    totals["stale_torque"] += 1
            totals["framed"] += s["tx_frames"]
            totals["stale"] += r["stale"]
            totals["seen"] += r["seen"]
            totals["oldest_s"] = max(totals["oldest_s"], r["oldest_s"])
    totals["states"] = sorted(totals["states"])
    return totals


def reopen() -> dict:
    """Late open (1 s) and close/reopen with the command held at 1500 Nm."""
    out = {}
    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "late.log")
        b = can_bridge.Bridge("slcan-pty:", period_ms=50, log_path=log)
        b.start()
        # held at 1500 Nm; the front wheel's few Nm make every frame unique
        cmd = Commander(b, lambda seq: (-2.0 * (seq % 700), 0.0, 1500.0, 1500.0))
        time.sleep(1.0)
        state_closed = b.stats()["safety_state"]
        peer = Peer(_bus(b.pty_path))
        time.sleep(0.6)
        cmd.close()
        s = b.stats()
        b.stop()
        peer.close()
        chk = CmdChecker()
        first = chk.add(0x101, False, peer.seen[0][1]) if peer.seen else None
        out["late open"] = {
            "framed": s["tx_frames"],
            **_stale(peer.seen, log, 0.05),
            "safety_state_while_closed": state_closed,
            "first_frame_RL_nm": first["torques"][2] if first else None,
            "first_frame_mode": first["mode"] if first else None,
        }
        log = os.path.join(d, "reopen.log")
        b = can_bridge.Bridge("slcan-pty:", period_ms=50, log_path=log)
        b.start()
        cmd = Commander(b, lambda _: (0.0, 0.0, 1500.0, 1500.0))
        fd = open_raw_host(b.pty_path)
        read_all(fd, 0.6)
        os.write(fd, b"C\r")
        read_all(fd, 0.4)
        state_closed = b.stats()["safety_state"]
        os.write(fd, b"O\r")
        data = read_all(fd, 0.3)
        cmd.close()
        s = b.stats()
        b.stop()
        os.close(fd)
        lines = [x for x in data.split(b"\r") if x.startswith(b"t")]
        first = CmdChecker().add(0x101, False, bytes.fromhex(lines[0][5:21].decode()))
        out["reopen"] = {
            "framed": s["tx_frames"],
            "safety_state_while_closed": state_closed,
            "first_frame_RL_nm": first["torques"][2],
            "ramp_restarts": s["ramp_restarts"],
        }
    return out


REAL = {**MOTION, "LongSpeed": 12.0}
FAKE = {**MOTION, "LongSpeed": 20.0}


def _sensor_case(motion, period_ms: float = 50.0, extra=None) -> dict:
    """Play ``motion(k)`` -> [(dt, values, counter)] for VehicleMotion per cycle
    k (the other four messages sound, ``extra(k)`` overriding some), sample
    the state every ms. Returns framed, stale, valid %, samples at 20 m/s
    and at > 50 m/s believed."""
    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "b.log")
        b = can_bridge.Bridge("slcan-pty:", period_ms=period_ms, log_path=log)
        b.start()
        bus = _bus(b.pty_path)
        peer = Peer(bus)
        # a torque that changes with every command keeps every frame's bytes unique
        cmd = Commander(b, lambda seq: (0.0, 0.0, 2.0 * (seq % 700), 0.0))
        n = 80
        events = []
        for k in range(n):
            for dt, vals, c in motion(k):
                events.append((k * CYCLE + dt, "m", vals, c))
            events.append((k * CYCLE, "rest", None, k))
        events.sort(key=lambda e: e[0])
        done = threading.Event()

        def play() -> None:
            t0 = time.monotonic()
            for t, kind, vals, c in events:
                time.sleep(max(0.0, t0 + t - time.monotonic()))
                if kind == "m":
                    bus.send(state_message("VehicleMotion", vals, c % 15))
                else:
                    skip = ("VehicleMotion",) + tuple(extra(c) if extra else ())
                    send_sensors(bus, c % 15, skip=skip)
                    for name, v in extra(c).items() if extra else ():
                        bus.send(state_message(name, v, c % 15))
            done.set()

        th = threading.Thread(target=play, daemon=True)
        th.start()
        samples = []
        while not done.is_set():
            st = b.latest_state()
            samples.append((st["valid"], st["long_speed_mps"]))
            time.sleep(0.001)
        th.join()
        cmd.close()
        s = b.stats()
        b.stop()
        peer.close()
        r = _stale(peer.seen, log, period_ms / 1e3)
    valid = [v for v, _ in samples]
    return {
        "framed": s["tx_frames"],
        "stale": r["stale"],
        "valid_pct": round(100.0 * sum(valid) / max(1, len(valid)), 1),
        "intruder_believed": sum(
            1 for v, x in samples if v and x is not None and abs(x - 20) < 0.5
        ),
        "over_50_believed": sum(1 for v, x in samples if v and x is not None and x > 50),
        "samples": len(samples),
        "rx_implausible": s["rx_implausible"],
        "rx_discarded": s["rx_discarded"],
    }


def intruders() -> dict:
    k0 = 20

    def real(k):
        return [(0.0, REAL, k)]

    def with_fake(fake):
        return lambda k: real(k) + [(dt, FAKE, c) for (kk, dt, c) in fake if kk == k]

    cases = {
        "intruder +1": [(k0, 0.015, k0 + 1)],
        "intruder +2": [(k0, 0.015, k0 + 2)],
        "three after a jump": [(k0, 0.012 + 0.001 * j, k0 + 7 + j) for j in range(3)],
        "interleaved stream": [(k0 + j, 0.010, k0 + j + 2) for j in range(30)],
        "replay, counter +1": [(k0 + j, 0.010, k0 + j + 1) for j in range(30)],
    }
    return {name: _sensor_case(with_fake(f)) for name, f in cases.items()}


def plausibility() -> dict:
    def jumping(k):
        v = 12.0 if k < 10 or k % 2 == 0 else 85.0
        return [(0.0, {**MOTION, "LongSpeed": v}, k)]

    def fast_wheels(k):
        w = 114.0 if k >= 10 else 12.0 / 0.351
        return {"WheelSpeeds": {n: w for n in WHEELS}}

    return {
        "speed 12 <-> 85": _sensor_case(jumping),
        "wheels 40 vs 12 m/s": _sensor_case(lambda k: [(0.0, REAL, k)], extra=fast_wheels),
    }


def bursts() -> dict:
    """One sender's VehicleMotion frames back to back, each claiming a cycle
    per counter step and within the rate bound for that claim: the report's
    12 -> 85 m/s burst (counter +2, +0.8 m/s) and a counter +1 variant
    (+0.35 m/s). Target: 0 samples over 50 m/s believed."""
    return {
        "burst +2, +0.8 m/s x 90": _sensor_case(Burst(**REPORT).motion()),
        "burst +1, +0.35 m/s x 90": _sensor_case(Burst(n=90, step=1, delta=0.35).motion()),
    }


def bad_crc_1_in_8() -> dict:
    b = can_bridge.Bridge("slcan-pty:", period_ms=50)
    b.start()
    bus = _bus(b.pty_path)
    samples = []
    for k in range(100):
        bus.send(state_message("VehicleMotion", REAL, k % 15, corrupt=k % 8 == 7))
        send_sensors(bus, k % 15, skip=("VehicleMotion",))
        time.sleep(CYCLE)
        if k >= 10:
            samples.append(b.latest_state()["valid"])
    s = b.stats()
    bus.shutdown()
    b.stop()
    return {
        "valid_pct": round(100.0 * sum(samples) / len(samples), 1),
        "rx_crc_errors": s["rx_crc_errors"],
    }


# ------------------------------------------------- transmit gaps (pty, log)

RISE_NM = 500.0  # the vehicle's rise rate, 10,000 Nm/s, over a 50 ms tick
DID = 3073  # WheelTorqueCmd's E2EDataID


def _valid(data: bytes) -> bool:
    import e2e.p01

    return len(data) == 8 and e2e.p01.e2e_p01_check(bytearray(data), DID)


def _rl(data: bytes) -> float:
    raw = (int.from_bytes(data, "little") >> 40) & 0xFFF
    return 2.0 * (raw - 4096 if raw >= 2048 else raw)


def _lines(fd: int, seconds: float, out: list, buf: list) -> None:
    """Read the pty in bulk for ``seconds``; each line stamped on arrival."""
    import select

    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if select.select([fd], [], [], 0.005)[0]:
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                continue
            buf[0] += chunk
            while b"\r" in buf[0]:
                line, buf[0] = buf[0].split(b"\r", 1)
                out.append((time.time(), line))


def _torque_lines(lines: list) -> list[tuple[float, bytes]]:
    return [
        (t, bytes.fromhex(x[5:21].decode()))
        for t, x in lines
        if x.startswith(b"t1018") and len(x) == 21
    ]


def pty_stall(stall: float, k: int | None) -> dict:
    """A raw SLCAN host stops reading for ``stall`` s: after ``k`` bytes of a
    torque frame (``k`` None: between two lines). The command is held at
    RL = 1500 Nm with the vehicle's actuators. ``stale``: valid frames older
    than a period; ``steps``: valid frames after a gap of at least the
    actuator's timeout that are not a ramp from zero; ``cut``: frames that
    fail their CRC (the line the host stopped in)."""
    import select

    from ampc_jax.vehicle.actuators import ACTUATORS, bridge_kwargs

    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "b.log")
        b = can_bridge.Bridge("slcan-pty:", **bridge_kwargs(), log_path=log)
        b.start()
        cmd = Commander(b, lambda seq: (-2.0 * (seq % 500), 0.0, 1500.0, 1500.0))
        fd = open_raw_host(b.pty_path)
        lines: list = []
        buf = [b""]
        _lines(fd, 0.6, lines, buf)
        if k is not None:
            end = time.monotonic() + 5
            while time.monotonic() < end:
                if select.select([fd], [], [], 0.05)[0]:
                    try:
                        buf[0] += os.read(fd, 1)
                    except BlockingIOError:
                        continue
                    if buf[0].endswith(b"\r"):
                        lines.append((time.time(), buf[0][:-1]))
                        buf[0] = b""
                    elif buf[0].startswith(b"t101") and len(buf[0]) >= k:
                        break
        time.sleep(stall)
        _lines(fd, 0.4, lines, buf)
        cmd.close()
        s = b.stats()
        b.stop()
        os.close(fd)
        frames = _torque_lines(lines)
        valid = [(t, x) for t, x in frames if _valid(x)]
        ages = frame_ages(valid, candump_tx(log))
    steps = 0
    for (t0, _), (t1, x) in zip(valid, valid[1:], strict=False):
        if t1 - t0 >= ACTUATORS.timeout_ms / 1e3 and abs(_rl(x)) > RISE_NM:
            steps += 1
    return {
        "framed": s["tx_frames"],
        "stale": sum(a > 0.05 for a in ages),
        "oldest_s": round(max(ages, default=0.0), 4),
        "steps": steps,
        "cut": len(frames) - len(valid),
        "ramp_restarts": s["ramp_restarts"],
    }


def pty_stalls(stalls: list[float], offsets: list[int | None]) -> dict:
    out = {}
    for k in offsets:
        tot = {"framed": 0, "stale": 0, "oldest_s": 0.0, "steps": 0, "cut": 0, "trials": 0}
        for st in stalls:
            r = pty_stall(st, k)
            for key in ("framed", "stale", "steps", "cut"):
                tot[key] += r[key]
            tot["oldest_s"] = max(tot["oldest_s"], r["oldest_s"])
            tot["trials"] += 1
        out["between lines" if k is None else f"after byte {k}"] = tot
    return out


def python_can_stall(stall: float, offsets: list[int]) -> dict:
    """python-can's own slcan reader (one byte a read) stops after ``k``
    bytes of a torque frame for ``stall`` s, once per offset."""
    from ampc_jax.vehicle.actuators import bridge_kwargs

    tot = {"framed": 0, "stale": 0, "oldest_s": 0.0, "cut": 0, "trials": 0, "reader_errors": 0}
    with tempfile.TemporaryDirectory() as d:
        for i, k in enumerate(offsets):
            log = os.path.join(d, f"p{i}.log")
            b = can_bridge.Bridge("slcan-pty:", **bridge_kwargs(), log_path=log)
            b.start()
            cmd = Commander(b, lambda seq: (-2.0 * (seq % 500), 0.0, 1500.0, 1500.0))
            bus = _bus(b.pty_path)
            orig = bus.serialPortOrig.read
            st = {"line": b"", "armed": False, "at": 0.0}

            def read(n: int = 1, st=st, orig=orig, k=k) -> bytes:
                got = orig(n)
                for c in got:
                    st["line"] = b"" if c == 13 else st["line"] + bytes([c])
                if st["armed"] and st["line"].startswith(b"t") and len(st["line"]) == k:
                    st["armed"] = False
                    st["at"] = time.time()
                    time.sleep(stall)
                return got

            bus.serialPortOrig.read = read
            seen = []
            end = time.monotonic() + 0.6
            try:
                while time.monotonic() < end:
                    bus.recv(0.05)
                st["armed"] = True
                end = time.monotonic() + stall + 0.6
                while time.monotonic() < end:
                    m = bus.recv(0.05)
                    if m is not None and m.arbitration_id == 0x101:
                        seen.append((time.time(), bytes(m.data)))
            except can.CanError:
                tot["reader_errors"] += 1
            cmd.close()
            s = b.stats()
            bus.shutdown()
            b.stop()
            valid = [(t, x) for t, x in seen if _valid(x)]
            ages = frame_ages(valid, candump_tx(log))
            tot["framed"] += s["tx_frames"]
            tot["stale"] += sum(a > 0.05 for a in ages)
            tot["oldest_s"] = max(tot["oldest_s"], round(max(ages, default=0.0), 4))
            tot["cut"] += len(seen) - len(valid)
            tot["trials"] += 1
    return tot


def log_flood(seconds: float) -> dict:
    """Unknown-ID frames on the pty as fast as it takes them for ``seconds``
    s, with a log: frames sent, lines and bytes the log took, counters."""
    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "flood.log")
        b = can_bridge.Bridge("slcan-pty:", period_ms=50, log_path=log)
        b.start()
        fd = open_raw_host(b.pty_path)
        read_all(fd, 0.2)
        sent = 0
        chunk = b"t7FF0\r" * 512
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                sent += os.write(fd, chunk) // 6
            except BlockingIOError:
                read_all(fd, 0.001)
        time.sleep(0.3)
        s = b.stats()
        b.stop()
        os.close(fd)
        size = os.path.getsize(log)
        with open(log) as f:
            lines = sum(1 for _ in f)
    return {
        "sent": sent,
        "rx_unknown_id": s["rx_unknown_id"],
        "log_lines": lines,
        "log_bytes": size,
        "log_mb_per_s": round(size / 1e6 / seconds, 3),
        "log_suppressed": s["log_suppressed"],
        "log_dropped": s["log_dropped"],
    }


def tx_gaps(args) -> dict:
    """The transmit side's gaps: every case with its figures."""
    stalls = [args.stall] if args.short else [0.3, args.stall]
    return {
        "pty_mid_frame": pty_stalls(stalls, [1, 9, 20, 21]),
        "pty_between_lines": pty_stalls(
            [0.15, 0.21, 0.24] if args.short else [0.15, 0.19, 0.21, 0.22, 0.24, 0.26, 0.3], [None]
        ),
        "python_can_mid_frame": python_can_stall(min(args.stall, 1.0), [1, 5, 12, 20]),
        "socketcand_probe_default": socketcand_stall(args.stall, args.trials, "probe"),
        "socketcand_probe_active": socketcand_stall(
            args.stall, args.trials, "probe", socketcand_active=True
        ),
        "socketcand_random_active": socketcand_stall(
            args.stall, args.trials, "random", socketcand_active=True
        ),
        "socketcand_no_echo": socketcand_stall(
            args.stall, args.trials, "random", server={"echo": False}
        ),
        "socketcand_no_echo_active": socketcand_stall(
            args.stall, args.trials, "random", server={"echo": False}, socketcand_active=True
        ),
        "socketcand_slow_active": socketcand_stall(
            0.0, args.trials, "random", server={"slow": 0.03}, socketcand_active=True
        ),
        "log_flood": log_flood(2.0),
    }


def print_tx_gaps(r: dict) -> None:
    print("transmit gaps, per fault (target: 0 stale, 0 steps):")
    head = f"{'fault':<36} {'framed':>6} {'stale':>5} {'valid %':>7}   detail"
    print(head)
    print("-" * len(head))
    for group in ("pty_mid_frame", "pty_between_lines"):
        for name, x in r[group].items():
            print(
                f"{'pty, raw host stops ' + name:<36} {x['framed']:>6} {x['stale']:>5} "
                f"{'-':>7}   ({x['trials']} stalls, oldest valid {x['oldest_s']:.3f} s, "
                f"steps after a timeout {x['steps']}, cut lines {x['cut']})"
            )
    x = r["python_can_mid_frame"]
    print(
        f"{'pty, python-can stops inside a frame':<36} {x['framed']:>6} {x['stale']:>5} {'-':>7}"
        f"   ({x['trials']} stalls, oldest valid {x['oldest_s']:.3f} s, cut {x['cut']}, "
        f"reader errors {x['reader_errors']})"
    )
    for key, name in (
        ("socketcand_probe_default", "socketcand, stall after probe"),
        ("socketcand_probe_active", "  the same, socketcand_active"),
        ("socketcand_random_active", "socketcand, random stall, active"),
        ("socketcand_no_echo", "socketcand, no echo"),
        ("socketcand_no_echo_active", "  the same, socketcand_active"),
        ("socketcand_slow_active", "socketcand, slow server, active"),
    ):
        x = r[key]
        print(
            f"{name:<36} {x['framed']:>6} {x['stale']:>5} {'-':>7}   ({x['trials']} runs; "
            f"stale with torque {x['stale_torque']}, oldest {x['oldest_s']:.3f} s; "
            f"{', '.join(x['states'])})"
        )
    x = r["log_flood"]
    print(
        f"{'pty, 2 s flood of unknown frames':<36} {'-':>6} {'-':>5} {'-':>7}   "
        f"({x['sent']} sent, log {x['log_lines']} lines, {x['log_bytes']} B, "
        f"{x['log_mb_per_s']} MB/s; suppressed {x['log_suppressed']}, dropped {x['log_dropped']})"
    )


# ---------------------------------------------------------------- issue 21


def stall_pty(stall: float) -> dict:
    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "b.log")
        b = can_bridge.Bridge("slcan-pty:", period_ms=50, log_path=log)
        b.start()
        cmd = Commander(b, lambda seq: (0.0, 0.0, 2.0 * (seq % 700), 0.0))
        bus = _bus(b.pty_path)
        for _ in range(5):
            bus.recv(1)
        time.sleep(stall)
        t0 = time.monotonic()
        times, seen = [], []
        while time.monotonic() - t0 < 0.3:
            m = bus.recv(0.05)
            if m is not None:
                times.append(time.monotonic())
                seen.append((time.time(), bytes(m.data)))
        cmd.close()
        s = b.stats()
        bus.shutdown()
        b.stop()
        r = _stale(seen, log, 0.05)
    return {
        "burst_20ms": burst_after(times, t0, 0.02),
        "stale_dropped": s["tx_stale_dropped"],
        "stale_seen": r["stale"],
        "oldest_s": r["oldest_s"],
    }


def stall_serial(stall: float) -> dict:
    a = SerialAdapter()
    with tempfile.TemporaryDirectory() as d:
        log = os.path.join(d, "b.log")
        b = can_bridge.Bridge(f"slcan:{a.path}", period_ms=50, log_path=log)
        b.start()
        cmd = Commander(b, lambda seq: (0.0, 0.0, 2.0 * (seq % 700), 0.0))
        time.sleep(0.3)
        a.stall()
        time.sleep(stall)
        n0 = len(a.lines)
        t0 = time.monotonic()
        a.resume()
        time.sleep(0.3)
        cmd.close()
        s = b.stats()
        b.stop()
        a.close()
        times = [t for t, _ in a.lines[n0:]]
        # the adapter stamps time.monotonic(), the log time.time()
        shift = time.time() - time.monotonic()
        seen = [
            (t + shift, bytes.fromhex(x[5:21].decode()))
            for t, x in a.lines
            if x.startswith(b"t101")
        ]
        r = _stale(seen, log, 0.05)
    return {
        "burst_20ms": burst_after(times, t0, 0.02),
        "stale_dropped": s["tx_stale_dropped"],
        "stale_seen": r["stale"],
        "oldest_s": r["oldest_s"],
    }


def stall_socketcand(stall: float) -> dict:
    srv = SocketcandServer()
    b = can_bridge.Bridge(f"socketcand:127.0.0.1:{srv.port}/can0", period_ms=50)
    b.start()
    time.sleep(0.3)
    srv.stall()
    time.sleep(stall)
    n0 = len(srv.sent)
    t0 = time.monotonic()
    srv.resume()
    time.sleep(0.3)
    s = b.stats()
    b.stop()
    srv.kill()
    times = [t for t, *_ in srv.sent[n0:]]
    return {"burst_20ms": burst_after(times, t0, 0.02), "stale_dropped": s["tx_stale_dropped"]}


def sensors() -> dict:
    out = {}
    other = {**MOTION, "LongSpeed": 33.0}
    cases = {
        "healthy": lambda k: [("VehicleMotion", MOTION, k % 15)],
        "frozen": lambda k: [("VehicleMotion", MOTION, 5)],
        "step_3": lambda k: [("VehicleMotion", MOTION, 3 * k % 15)],
        "two_sources": lambda k: [("VehicleMotion", MOTION, k % 15), ("VehicleMotion", other, (k + 7) % 15)],
        "bad_crc_90": lambda k: [("VehicleMotion", MOTION, k % 15, k % 10 != 0)],
    }  # fmt: skip
    for name, frames in cases.items():
        b = can_bridge.Bridge("slcan-pty:", period_ms=50)
        b.start()
        bus = _bus(b.pty_path)
        samples = []
        for k in range(100):
            for f in frames(k):
                bus.send(state_message(f[0], f[1], f[2], corrupt=len(f) > 3 and f[3]))
            # the other four messages, sound (can_peers.SENSORS' healthy values)
            send_sensors(bus, k % 15, skip=("VehicleMotion",))
            time.sleep(CYCLE)
            if k >= 5:
                samples.append(b.latest_state()["valid"])
        out[name] = 100.0 * sum(samples) / len(samples)
        bus.shutdown()
        b.stop()
    return out


def reconnect() -> dict:
    srv = SocketcandServer()
    b = can_bridge.Bridge(f"socketcand:127.0.0.1:{srv.port}/can0", period_ms=50)
    b.start()
    time.sleep(0.3)
    srv.kill()
    t_kill = time.monotonic()
    time.sleep(0.1)
    lost = b.stats()["transport_state"]
    time.sleep(0.4)
    srv.restart()
    t_restart = time.monotonic()
    n0 = len(srv.sent)
    while len(srv.sent) == n0 and time.monotonic() - t_restart < 6:
        time.sleep(0.005)
    back = time.monotonic() - t_restart
    s = b.stats()
    b.stop()
    srv.kill()
    return {
        "state_100ms_after_kill": lost,
        "frames_again_after_restart_s": back if len(srv.sent) > n0 else None,
        "reconnects": s["reconnects"],
        "since_kill_s": t_restart - t_kill,
    }


def flood() -> dict:
    b = can_bridge.Bridge("slcan-pty:", period_ms=50, trace_capacity=1000)
    b.start()
    fd = open_raw_host(b.pty_path)
    n0 = b.stats()["ticks"]
    t0 = time.monotonic()
    while time.monotonic() - t0 < 5.0:
        try:
            os.write(fd, b"V\r" * 256)
        except BlockingIOError:
            time.sleep(0.001)
    s = b.stats()
    trace = b.tick_trace()
    t1 = time.monotonic()
    b.stop()
    stop_s = time.monotonic() - t1
    os.close(fd)
    wakes = [w for _, _, w in trace[3:]]
    gaps = [(y - x) / 1e6 for x, y in zip(wakes, wakes[1:], strict=False)]
    return {
        "ticks_in_5s": s["ticks"] - n0,
        "max_gap_ms": max(gaps),
        "lateness_max_ms": s["lateness_max_ms"],
        "send_max_ms": s["send_max_ms"],
        "replies_dropped": s["replies_dropped"],
        "stop_s": stop_s,
    }


def watchdog(trials: int) -> dict:
    got = {"hold": [], "safe": [], "fault": []}
    for _ in range(trials):
        b = can_bridge.Bridge("slcan-pty:", period_ms=50)
        b.start()
        bus = _bus(b.pty_path)
        for seq in range(1, 4):
            bus.recv(1)
            b.set_command((-10.0, -10.0, 10.0, 10.0), seq)
        t_cmd = time.monotonic()
        chk = CmdChecker()
        for mode in ("hold", "safe", "fault"):
            while True:
                m = bus.recv(1)
                if (
                    m is not None
                    and chk.add(m.arbitration_id, False, bytes(m.data))["mode"] == mode
                ):
                    got[mode].append((time.monotonic() - t_cmd) * 1e3)
                    break
        bus.shutdown()
        b.stop()
    return {k: (min(v), max(v)) for k, v in got.items()}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--stall", type=float, default=2.0, help="stall length, s")
    ap.add_argument("--trials", type=int, default=5, help="socketcand stalls per phase")
    ap.add_argument("--watchdog-trials", type=int, default=3)
    ap.add_argument(
        "--only",
        choices=("all", "tx"),
        default="all",
        help="tx: only the transmit gaps (pty stalls inside a frame and of 150-300 ms, "
        "socketcand stalls after the probe, echo-less and slow servers, a log flood); "
        "default all",
    )
    ap.add_argument("--short", action="store_true", help="fewer stall lengths in the transmit gaps")
    ap.add_argument(
        "--json",
        default=str(_meta.RESULTS / "bench_can_bridge_faults.json"),
        help="the result file, with its metadata "
        "(default bench/results/bench_can_bridge_faults.json)",
    )
    args = ap.parse_args()
    meta = _meta.metadata()
    if args.only == "tx":
        res = {"tx_gaps": tx_gaps(args)}
        print_tx_gaps(res["tx_gaps"])
        meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
        Path(args.json).write_text(json.dumps({"meta": meta, "results": res}, indent=2))
        return
    res: dict = {
        "socketcand_stall_between_ticks": socketcand_stall(args.stall, args.trials, "between"),
        "socketcand_stall_random_phase": socketcand_stall(args.stall, args.trials, "random"),
        "reopen": reopen(),
        "intruders": intruders(),
        "plausibility": plausibility(),
        "bursts": bursts(),
        "bad_crc_1_in_8": bad_crc_1_in_8(),
    }
    print("issue 29, per fault (target: 0 stale, 0 intruder samples believed):")
    head = f"{'fault':<30} {'framed':>6} {'stale':>5} {'valid %':>7} {'intruder':>8} {'>50 m/s':>7}"
    print(head)
    print("-" * len(head))
    for phase in ("between_ticks", "random_phase"):
        r = res[f"socketcand_stall_{phase}"]
        print(
            f"{'socketcand stall, ' + phase.replace('_', ' '):<30} {r['framed']:>6} "
            f"{r['stale']:>5} {'-':>7} {'-':>8} {'-':>7}   ({r['trials']} stalls of "
            f"{args.stall:g} s, oldest frame {r['oldest_s']:.3f} s)"
        )
    for name, r in res["reopen"].items():
        print(
            f"{name:<30} {r['framed']:>6} {r.get('stale', '-'):>5} {'-':>7} {'-':>8} {'-':>7}   "
            f"(first frame RL {r['first_frame_RL_nm']:g} Nm, safety_state while closed "
            f"{r['safety_state_while_closed']})"
        )
    for group in ("intruders", "plausibility", "bursts"):
        for name, r in res[group].items():
            print(
                f"{name:<30} {r['framed']:>6} {r['stale']:>5} {r['valid_pct']:>7.1f} "
                f"{r['intruder_believed']:>8} {r['over_50_believed']:>7}   "
                f"({r['samples']} samples; implausible {r['rx_implausible']}, "
                f"discarded unbelieved {r['rx_discarded']})"
            )
    r = res["bad_crc_1_in_8"]
    print(f"{'bad CRC 1 in 8':<30} {'-':>6} {'-':>5} {r['valid_pct']:>7.1f}")
    res["tx_gaps"] = tx_gaps(args)
    print()
    print_tx_gaps(res["tx_gaps"])
    res.update(
        {
            "stall_pty": stall_pty(args.stall),
            "stall_serial": stall_serial(args.stall),
            "stall_socketcand": stall_socketcand(args.stall),
            "sensors_valid_pct": sensors(),
            "reconnect": reconnect(),
            "flood": flood(),
            "watchdog_ms": watchdog(args.watchdog_trials),
        }
    )
    print()
    print("issue 21's findings:")
    for k in (
        "stall_pty",
        "stall_serial",
        "stall_socketcand",
        "sensors_valid_pct",
        "reconnect",
        "flood",
        "watchdog_ms",
    ):
        print(f"{k:<18} {json.dumps(res[k])}")
    meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    Path(args.json).write_text(json.dumps({"meta": meta, "results": res}, indent=2))


if __name__ == "__main__":
    main()
