"""Tick-timing benchmark of can_bridge (20 Hz, >= 1,200 ticks per condition).

Conditions, each a fresh bridge on ``slcan-pty:`` with an independent peer in
a child process (python-can ``slcan`` + autosar-e2e) draining and checking
every frame:

* ``idle``: the Python main thread sleeps;
* ``jax-compile``: the Python main thread compiles new JAX programs back to
  back (falls back to a busy pure-Python loop, and says so, if ``import jax``
  fails);
* ``jax-compile-rt``: the same, with the transmit thread under SCHED_FIFO
  (``rt_priority=50``; skipped with a message where that is not permitted).

A Python thread hands over a command every 10 ms in every condition (within
the default limits of ``vehicle.toml``: front wheels brake only).

Figures over the first N ticks (default 1,200 = one minute at 50 ms):
mean period, drift = (wake[N-1] - wake[0]) - (N-1) * period, lateness
(wake - deadline) p50/p99/max, overruns.

The period on the plant's (receiving) clock (docs/bus-safety.md): the peer takes
every frame in python-can's receive thread (``can.Notifier``), stamped with
the host clock as it is parsed, and the bridge logs each frame's write time
(candump log, the same clock). Per pair of consecutive frames: the period
error ``|gap - period|`` at the receiver, and split in two, the bridge's part
(the error of the write times) and the rest (the frame's latency from write
to receive: the pty, the peer's scheduling and python-can). Run::

    python bench/bench_can_bridge.py            # three conditions, ~3.5 min
    python bench/bench_can_bridge.py --ticks 200 --conditions idle
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time

import _meta  # bench/_meta.py, beside this script

import can_bridge

PEER = r"""
import json, sys, time
import can, e2e.p01, cantools
import can_bridge
db = cantools.database.load_file(can_bridge.dbc_path())
m = db.get_message_by_name("WheelTorqueCmd")
did = int(m.dbc.attributes["E2EDataID"].value)
bus = can.Bus(interface="slcan", channel=sys.argv[1], sleep_after_open=0, bitrate=500000)
got = []  # (receive-thread timestamp, data), python-can's receive thread
class Take(can.Listener):
    def on_message_received(self, msg):
        if msg.arbitration_id == m.frame_id:
            got.append((msg.timestamp, bytes(msg.data)))
    def on_error(self, exc):  # the bridge closed the pty: the run is over
        pass
notifier = can.Notifier(bus, [Take()], timeout=0.05)
print("open", flush=True)
seen, last = 0, time.monotonic()
while time.monotonic() - last < 2.0:
    time.sleep(0.05)
    if len(got) != seen:
        seen, last = len(got), time.monotonic()
notifier.stop()
try:
    bus.shutdown()
except can.CanError:
    pass
n = bad_crc = gaps = 0
prev = None
for _, data in got:
    n += 1
    if not e2e.p01.e2e_p01_check(bytearray(data), did):
        bad_crc += 1
    c = data[1] & 0x0F
    if prev is not None and c != (prev + 1) % 15:
        gaps += 1
    prev = c
print(json.dumps({"frames": n, "bad_crc": bad_crc, "counter_gaps": gaps,
                  "received": [(t, d.hex()) for t, d in got]}), flush=True)
"""


def _pct(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))] if xs else float("nan")


def receive_clock(received: list, written: list, period_ms: float) -> dict:
    """Period errors on the receiver's clock, the bridge's part and the rest.

    ``received``: (receive time, data hex) at the peer; ``written``: (write
    time, data) from the bridge's log. Frames are matched by their bytes, to
    the write nearest in time (the same bytes recur only after 15 counter
    values, 750 ms at 50 ms); pairs of consecutive counters only (a frame the
    age rule dropped breaks a pair)."""
    w = {}
    for t, d in written:
        w.setdefault(d.hex(), []).append(t)
    rows = []  # (receive time, write time, counter)
    for t, hx in received:
        cands = w.get(hx, [])
        if cands:
            rows.append((t, min(cands, key=lambda x: abs(x - t)), int(hx[3], 16)))
    p = period_ms / 1e3
    rx_err, tx_err, lat = [], [], [r[0] - r[1] for r in rows]
    for a, b in zip(rows, rows[1:], strict=False):
        if b[2] == (a[2] + 1) % 15:
            rx_err.append(abs((b[0] - a[0]) - p) * 1e3)
            tx_err.append(abs((b[1] - a[1]) - p) * 1e3)
    lat_ms = [x * 1e3 for x in lat]
    return {
        "pairs": len(rx_err),
        "rx_period_err_p50_ms": _pct(rx_err, 0.5),
        "rx_period_err_p99_ms": _pct(rx_err, 0.99),
        "rx_period_err_max_ms": max(rx_err, default=float("nan")),
        "bridge_period_err_p50_ms": _pct(tx_err, 0.5),
        "bridge_period_err_p99_ms": _pct(tx_err, 0.99),
        "bridge_period_err_max_ms": max(tx_err, default=float("nan")),
        "latency_p50_ms": _pct(lat_ms, 0.5),
        "latency_p99_ms": _pct(lat_ms, 0.99),
        "latency_max_ms": max(lat_ms, default=float("nan")),
    }


def busy_python(stop_at_ticks: int, bridge: can_bridge.Bridge) -> str:
    x = 0
    while bridge.stats()["ticks"] < stop_at_ticks:
        for i in range(200_000):
            x += i * i % 7
    return "busy pure-Python loop (import jax failed)"


def jax_compiles(stop_at_ticks: int, bridge: can_bridge.Bridge) -> str:
    try:
        import jax
        import jax.numpy as jnp
    except ImportError:
        return busy_python(stop_at_ticks, bridge)
    n = 0
    t_compile = 0.0
    while bridge.stats()["ticks"] < stop_at_ticks:
        k = n

        def f(x, k=k):
            for j in range(40):
                x = jnp.tanh(x @ x.T)[:, : x.shape[1]] * (j + k % 5) + jnp.sin(x)
            return jnp.linalg.norm(x)

        t0 = time.perf_counter()
        jax.jit(f).lower(jnp.ones((32 + n % 32, 32))).compile()
        t_compile += time.perf_counter() - t0
        n += 1
    return f"JAX {jax.__version__}: {n} programs compiled, {t_compile:.1f} s compiling"


def run(condition: str, ticks: int, period_ms: float, log_dir: str) -> dict | None:
    rt = 50 if condition.endswith("-rt") else None
    log = os.path.join(log_dir, f"{condition}.log")
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=period_ms,
        trace_capacity=ticks + 400,
        rt_priority=rt,
        log_path=log,
        log_overwrite=True,
    )
    try:
        bridge.start()
    except can_bridge.ConfigError as e:
        print(f"skipping {condition}: {e}")
        return None
    peer = subprocess.Popen(
        [sys.executable, "-c", PEER, bridge.pty_path], stdout=subprocess.PIPE, text=True
    )
    assert peer.stdout is not None
    peer.stdout.readline()  # "open": the peer has opened the channel
    time.sleep(0.2)
    first_tick = bridge.stats()["ticks"]
    stop_at = first_tick + ticks + 1
    done = threading.Event()

    def commander() -> None:
        seq = 0
        while not done.is_set():
            seq += 1
            bridge.set_command((-20.0, -20.0, 26.0, 26.0), seq)
            time.sleep(0.01)

    th = threading.Thread(target=commander, daemon=True)
    th.start()
    if condition == "idle":
        note = "main thread sleeping"
        while bridge.stats()["ticks"] < stop_at:
            time.sleep(0.2)
    else:
        note = jax_compiles(stop_at, bridge)
    done.set()
    th.join()
    stats = bridge.stats()
    trace = bridge.tick_trace()
    bridge.stop()
    peer_out = json.loads(peer.communicate(timeout=60)[0].strip().splitlines()[-1])
    import can

    written = [(m.timestamp, bytes(m.data)) for m in can.LogReader(log) if not m.is_rx]
    clock = receive_clock(peer_out.pop("received"), written, period_ms)
    window = trace[first_tick : first_tick + ticks]
    period_ns = period_ms * 1e6
    wakes = [w for _, _, w in window]
    late_ms = sorted((w - d) / 1e6 for _, d, w in window)
    idx = [i for i, _, _ in window]
    mean_period = (wakes[-1] - wakes[0]) / (len(wakes) - 1) / 1e6
    drift = (wakes[-1] - wakes[0] - (idx[-1] - idx[0]) * period_ns) / 1e6
    return {
        "condition": condition,
        "note": note,
        "ticks": len(window),
        "mean_period_ms": mean_period,
        "drift_ms": drift,
        "lateness_mean_ms": statistics.fmean(late_ms),
        "lateness_p50_ms": late_ms[len(late_ms) // 2],
        "lateness_p99_ms": late_ms[min(len(late_ms) - 1, int(0.99 * len(late_ms)))],
        "lateness_max_ms": late_ms[-1],
        "overruns": stats["overruns"],
        "skipped_ticks": stats["skipped_ticks"],
        "skipped_in_window": idx[-1] - idx[0] - (len(idx) - 1),
        "tx_errors": stats["tx_errors"],
        "tx_stale_dropped": stats["tx_stale_dropped"],
        "send_max_ms": stats["send_max_ms"],
        "transport_state_at_end": stats["transport_state"],
        "safety_state_at_end": stats["safety_state"],
        "peer": peer_out,
        "receive_clock": clock,
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--ticks", type=int, default=1200)
    ap.add_argument("--period-ms", type=float, default=50.0)
    ap.add_argument("--conditions", default="idle,jax-compile,jax-compile-rt")
    ap.add_argument(
        "--json",
        default=str(_meta.RESULTS / "bench_can_bridge.json"),
        help="the result file, with its metadata (default bench/results/bench_can_bridge.json)",
    )
    args = ap.parse_args()
    meta = _meta.metadata()
    import tempfile

    with tempfile.TemporaryDirectory() as log_dir:
        results = [
            r
            for c in args.conditions.split(",")
            if (r := run(c, args.ticks, args.period_ms, log_dir))
        ]
    head = f"{'condition':<15} {'ticks':>5} {'mean period ms':>14} {'drift ms':>9} {'late p50':>9} {'p99':>7} {'max':>7} {'overruns':>8} {'peer frames/crc/gaps':>21}"
    print(head)
    print("-" * len(head))
    for r in results:
        p = r["peer"]
        print(
            f"{r['condition']:<15} {r['ticks']:>5} {r['mean_period_ms']:>14.4f} {r['drift_ms']:>9.3f} "
            f"{r['lateness_p50_ms']:>9.3f} {r['lateness_p99_ms']:>7.3f} {r['lateness_max_ms']:>7.3f} "
            f"{r['overruns']:>8} {p['frames']:>9}/{p['bad_crc']}/{p['counter_gaps']}"
        )
    for r in results:
        print(
            f"  {r['condition']}: {r['note']}; lateness mean {r['lateness_mean_ms']:.3f} ms; "
            f"tx errors {r['tx_errors']}; frames dropped for age {r['tx_stale_dropped']}; "
            f"longest send {r['send_max_ms']:.3f} ms; safety state at end {r['safety_state_at_end']}"
        )
    print()
    print("period on the receiver's clock (python-can's receive thread), |gap - period| in ms:")
    head2 = f"{'condition':<15} {'pairs':>5} {'receiver p50/p99/max':>22} {'bridge part p50/p99/max':>25} {'latency p50/p99/max':>22}"
    print(head2)
    print("-" * len(head2))
    for r in results:
        c = r["receive_clock"]
        print(
            f"{r['condition']:<15} {c['pairs']:>5} "
            f"{c['rx_period_err_p50_ms']:>8.3f}/{c['rx_period_err_p99_ms']:.3f}/{c['rx_period_err_max_ms']:.3f} "
            f"{c['bridge_period_err_p50_ms']:>10.3f}/{c['bridge_period_err_p99_ms']:.3f}/{c['bridge_period_err_max_ms']:.3f} "
            f"{c['latency_p50_ms']:>9.3f}/{c['latency_p99_ms']:.3f}/{c['latency_max_ms']:.3f}"
        )
    meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    with open(args.json, "w") as fh:
        json.dump({"meta": meta, "results": results}, fh, indent=2)


if __name__ == "__main__":
    main()
