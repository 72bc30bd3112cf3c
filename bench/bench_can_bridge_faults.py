"""Fault-injection figures of can_bridge (issue 21's measurements, re-run).

Each line re-measures one finding with the peers of tests/can_bridge
(python-can's slcan interface over the pty, a socketcand server and an SLCAN
adapter written for the tests, cantools + autosar-e2e):

* stall: a peer stops reading for ``--stall`` s; frames it then finds within
  20 ms of resuming (before: 107 after 5 s on the pty, 80 of 110 over 1 s old
  on a serial adapter, 205 on socketcand), and frames dropped for their age;
* sensors: share of ``latest_state()`` samples judged valid for a frozen
  (repeating) sensor, a counter stepping by 3, two sources on one ID, 90 %
  bad CRC (before: 93 %, 95 %, 97.5 %, 62 %), and for healthy sensors (the
  control: near 100 %). Rule: every message the bridge receives is sent
  each 20 ms, sound, and only VehicleMotion carries the fault; reason: the
  state is valid only while all of them arrive sound, so a missing message
  would make every case 0 % whatever the fault;
* reconnect: a socketcand server killed and restarted after 0.5 s: time
  until frames reach it again (before: none in 6 s);
* flood: a non-reading peer flooding ``V`` for 5 s at 50 ms: ticks, largest
  wake-up gap, lateness_max_ms, stop() time (before: 41 of 100 ticks,
  450-500 ms gaps reported as 0.2-9.7 ms, stop 1.2-3.8 s);
* watchdog: hold / safe / fault after 150 / 500 / 2000 ms, on the peer's
  clock from the last command (before: 50-100 ms late).

Run::

    python bench/bench_can_bridge_faults.py            # about 40 s
    python bench/bench_can_bridge_faults.py --stall 5 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "can_bridge"))

import _meta  # noqa: E402  (bench/_meta.py, beside this script)
import can  # noqa: E402
from cb_fault_peers import (  # noqa: E402
    SerialAdapter,
    SocketcandServer,
    burst_after,
    open_raw_host,
)
from cb_peers import MOTION, CmdChecker, send_sensors, state_message  # noqa: E402

import can_bridge  # noqa: E402


def _bus(path: str) -> can.BusABC:
    return can.Bus(interface="slcan", channel=path, sleep_after_open=0, bitrate=500000)


def stall_pty(stall: float) -> dict:
    b = can_bridge.Bridge("slcan-pty:", period_ms=50)
    b.start()
    bus = _bus(b.pty_path)
    for _ in range(5):
        bus.recv(1)
    time.sleep(stall)
    t0 = time.monotonic()
    times = []
    while time.monotonic() - t0 < 0.3:
        if bus.recv(0.05) is not None:
            times.append(time.monotonic())
    s = b.stats()
    bus.shutdown()
    b.stop()
    return {"burst_20ms": burst_after(times, t0, 0.02), "stale_dropped": s["tx_stale_dropped"]}


def stall_serial(stall: float) -> dict:
    a = SerialAdapter()
    b = can_bridge.Bridge(f"slcan:{a.path}", period_ms=50)
    b.start()
    time.sleep(0.3)
    a.stall()
    time.sleep(stall)
    n0 = len(a.lines)
    t0 = time.monotonic()
    a.resume()
    time.sleep(0.3)
    s = b.stats()
    b.stop()
    a.close()
    times = [t for t, _ in a.lines[n0:]]
    return {"burst_20ms": burst_after(times, t0, 0.02), "stale_dropped": s["tx_stale_dropped"]}


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
            # the other four messages, sound (cb_peers.SENSORS' healthy values)
            send_sensors(bus, k % 15, skip=("VehicleMotion",))
            time.sleep(0.02)
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
    ap.add_argument("--watchdog-trials", type=int, default=3)
    ap.add_argument(
        "--json",
        default=str(_meta.RESULTS / "bench_can_bridge_faults.json"),
        help="the result file, with its metadata "
        "(default bench/results/bench_can_bridge_faults.json)",
    )
    args = ap.parse_args()
    meta = _meta.metadata()
    res = {
        "stall_pty": stall_pty(args.stall),
        "stall_serial": stall_serial(args.stall),
        "stall_socketcand": stall_socketcand(args.stall),
        "sensors_valid_pct": sensors(),
        "reconnect": reconnect(),
        "flood": flood(),
        "watchdog_ms": watchdog(args.watchdog_trials),
    }
    for k, v in res.items():
        print(f"{k:<18} {json.dumps(v)}")
    meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    Path(args.json).write_text(json.dumps({"meta": meta, "results": res}, indent=2))


if __name__ == "__main__":
    main()
