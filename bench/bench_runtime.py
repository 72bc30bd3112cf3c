"""The deployed loop's timing: `ampc run --with-plant` over a pseudo-terminal.

For each scheduling (normal, then SCHED_FIFO with ``--rt-priority 40``
where the machine allows it) and each dtype (float64, then float32) one
continuous closed loop of
``--minutes`` (default 10): the cruise-control lane change driven again and
again (``ampc plant --repeat``: the vehicle and driver restart from the
manoeuvre's initial state every 16 s), the runtime (controller and can_bridge)
in one process, the plant (python-can, cantools, autosar-e2e) in another,
joined by SLCAN on a fresh pty. Reported, from both ends:

* the runtime: per-tick compute of the controller step (median, p99, max),
  wake-up lateness, the margin left before the bridge's deadline, deadline
  misses, ticks that sent nothing and why;
* the bridge: its tick lateness (p99, max) and mean period;
* the plant: the torque frames' period on the plant's clock (median, p1,
  p99, the p99 and max of |period - 50 ms|), frames that failed its checks,
  ticks where it fell behind.

Targets (docs/runtime.md, "Timing"): compute p99 under 5 ms, zero misses, the period
within 1 ms of 50 ms at p99 on the plant's clock. The test suite asserts none
of these (a loaded machine misses deadlines that an idle one does not): they
are measured here.

Before the loops, the start-up of ``ampc run`` in fresh processes, the modes
interleaved: from the command's launch to "controller step ready" (imports,
configuration, the artefact's checks, the channel opened, the step compiled
and, for an artefact, its golden pair checked), in process and from an
``ampc export`` artefact, each with an empty JAX compilation cache and with a
warm one (``JAX_COMPILATION_CACHE_DIR``); and how long a missing device takes
to be refused.

Run::

    python bench/bench_runtime.py                 # start-up, then 4 x 10 min
    python bench/bench_runtime.py --minutes 1 --dtypes float64
    python bench/bench_runtime.py --startup-only --out /tmp/startup.json
    python bench/bench_runtime.py --smoke         # 4 x 6 s, writes nowhere
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _meta  # noqa: E402  (bench/_meta.py, beside this script)
import numpy as np
import pyarrow.parquet as pq

ROOT = Path(__file__).resolve().parents[1]
STEM = "bench_runtime"


def one_run(dtype: str, seconds: float, lead_ms: float, rt: int | None, workdir: Path) -> dict:
    out = workdir / dtype
    cmd = [sys.executable, "-m", "ampc_jax.cli", "run", "--channel", "slcan-pty:"]
    cmd += ["--scenario", "cruise_lane_change", "--duration", f"{seconds:g}", "--with-plant"]
    cmd += ["--lead-ms", f"{lead_ms:g}", "--quiet", "--out", str(out)]
    if dtype == "float32":
        cmd.append("--float32")
    cmd += ["--rt-priority", str(rt or 0)]  # 0: normal scheduling (the default asks for 50)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"ampc run failed ({p.returncode}): {p.stderr[-2000:]}")
    run = json.loads((out / "run.json").read_text())
    plant = json.loads((out / "plant" / "plant.json").read_text())
    ticks = pq.read_table(out / "ticks.parquet").to_pydict()

    def q(name: str, pct: float) -> float:
        a = np.asarray(ticks[name], float)
        a = a[np.isfinite(a)]
        return float(np.percentile(a, pct)) if a.size else float("nan")

    return {
        "dtype": dtype,
        "rt_priority": rt,
        "seconds": seconds,
        "ticks": run["ticks"],
        "sent": run["sent"],
        "misses": run["misses"],
        "skipped": run["skipped"],
        "compute_ms": {
            "median": q("compute_ms", 50),
            "p99": q("compute_ms", 99),
            "max": q("compute_ms", 100),
        },
        "wake_late_ms": {"p99": q("wake_late_ms", 99), "max": q("wake_late_ms", 100)},
        "margin_ms": {"min": q("margin_ms", 0), "p1": q("margin_ms", 1)},
        "iterations": {"median": q("iterations", 50), "max": q("iterations", 100)},
        "bridge": run["bridge"],
        "plant": plant,
    }


STARTUP_MODES = ("in process", "artefact", "in process, warm cache", "artefact, warm cache")


def _env(cache: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["PYTHONPATH"] = str(ROOT)
    if cache is not None:
        env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
    return env


def startup_once(mode: str, artefact: Path, cache: Path, workdir: Path) -> dict:
    """One `ampc run` launched until "controller step ready", then stopped (SIGTERM:
    it is waiting for a vehicle that is not there)."""
    cmd = [sys.executable, "-m", "ampc_jax.cli", "run", "--channel", "slcan-pty:"]
    cmd += ["--scenario", "cruise_lane_change", "--out", str(workdir / "startup")]
    if mode.startswith("artefact"):
        cmd += ["--artefact", str(artefact)]
    warm = mode.endswith("warm cache")
    t0 = time.perf_counter()
    p = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
        env=_env(cache if warm else None),
    )  # fmt: skip
    ready = prepare = None
    assert p.stdout is not None
    for line in p.stdout:
        m = re.match(r"controller step ready \(.*, ([0-9.]+) s\)", line)
        if m:
            ready, prepare = time.perf_counter() - t0, float(m.group(1))
            break
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    if ready is None:
        raise RuntimeError(f"ampc run ({mode}) never got ready: {err[-2000:]}")
    return {"mode": mode, "ready_s": ready, "compile_s": prepare}


def missing_device_once() -> float:
    """Seconds from launch to the refusal of a device that does not exist."""
    cmd = [sys.executable, "-m", "ampc_jax.cli", "run", "--channel", "slcan:/dev/no-such-tty"]
    cmd += ["--scenario", "cruise_lane_change", "--out", tempfile.mkdtemp()]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=_env(None))
    assert p.returncode == 2 and "--channel" in p.stderr, p.stderr
    return time.perf_counter() - t0


def startup(repeats: int) -> dict:
    """The start-up of `ampc run` (module docstring), the modes interleaved."""
    with tempfile.TemporaryDirectory() as tmp:
        work, art, cache = Path(tmp), Path(tmp) / "step.ampc", Path(tmp) / "cache"
        subprocess.run(
            [sys.executable, "-m", "ampc_jax.cli", "export", "--scenario", "cruise_lane_change",
             "--out", str(art)],
            check=True, capture_output=True, cwd=ROOT, env=_env(None),
        )  # fmt: skip
        for mode in STARTUP_MODES[2:]:  # fill the cache: not counted
            startup_once(mode, art, cache, work)
        samples = [
            startup_once(mode, art, cache, work) for _ in range(repeats) for mode in STARTUP_MODES
        ]
        missing = [missing_device_once() for _ in range(repeats)]
    out = {}
    for mode in STARTUP_MODES:
        ready = [x["ready_s"] for x in samples if x["mode"] == mode]
        comp = [x["compile_s"] for x in samples if x["mode"] == mode]
        out[mode] = {
            "ready_s_median": float(np.median(ready)),
            "compile_s_median": float(np.median(comp)),
            "ready_s": ready,
            "compile_s": comp,
        }
    base = out["in process"]["ready_s_median"]
    print(f"{'ampc run start-up':<26} {'to ready (s)':>12} {'compile (s)':>12} {'ratio':>6}")
    for mode, r in out.items():
        print(
            f"{mode:<26} {r['ready_s_median']:>12.2f} {r['compile_s_median']:>12.2f} "
            f"{r['ready_s_median'] / base:>6.2f}"
        )
    print(f"{'missing device refused':<26} {float(np.median(missing)):>12.2f}")
    return {"modes": out, "missing_device_s": missing, "repeats": repeats}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--minutes", type=float, default=10.0, help="per dtype (default 10)")
    ap.add_argument("--dtypes", default="float64,float32", help="(default float64,float32)")
    ap.add_argument("--lead-ms", type=float, default=25.0, help="ampc run --lead-ms (default 25)")
    ap.add_argument(
        "--rt-priority",
        default="none,40",
        help="comma-separated ampc run --rt-priority values, 'none' for normal scheduling "
        "(default none,40: each dtype without and with SCHED_FIFO)",
    )
    ap.add_argument("--smoke", action="store_true", help="6 s per dtype; writes nowhere")
    ap.add_argument("--startup-repeats", type=int, default=3, help="start-ups per mode (default 3)")
    ap.add_argument(
        "--startup-only",
        action="store_true",
        help="measure the start-up alone; writes nowhere unless --out is given",
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args()
    if args.startup_only:
        args.smoke = True  # the default result file holds the loops: not replaced
    run = _meta.Run(_meta.output_path(args, STEM))
    started = None if args.smoke and not args.startup_only else startup(args.startup_repeats)
    if args.startup_only:
        run.results = {"startup": started}
        run.finish()
        return
    seconds = 6.0 if args.smoke else 60.0 * args.minutes
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rt_text in args.rt_priority.split(","):
            rt = None if rt_text == "none" else int(rt_text)
            for dtype in args.dtypes.split(","):
                rows.append(one_run(dtype, seconds, args.lead_ms, rt, Path(tmp) / rt_text))
    head = (
        f"{'dtype':<8} {'rt':>4} {'s':>5} {'ticks':>6} {'miss':>4} {'compute med/p99/max ms':>24} "
        f"{'margin min':>10} {'plant period med':>16} {'|dev| p99/max ms':>17} {'bad':>4}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        c, pl = r["compute_ms"], r["plant"]
        print(
            f"{r['dtype']:<8} {str(r['rt_priority'] or '-'):>4} {r['seconds']:>5.0f} {r['ticks']:>6} {r['misses']:>4} "
            f"{c['median']:>8.2f}/{c['p99']:>6.2f}/{c['max']:>7.2f} "
            f"{r['margin_ms']['min']:>10.2f} {pl['period_ms_median']:>16.3f} "
            f"{pl['period_dev_ms_p99']:>8.3f}/{pl['period_dev_ms_max']:>7.3f} "
            f"{pl['frames_bad']:>4}"
        )
    for r in rows:
        b = r["bridge"]
        print(
            f"  {r['dtype']} rt {r['rt_priority'] or '-'}: bridge lateness p99 {b['lateness_p99_ms']:.3f} ms, max "
            f"{b['lateness_max_ms']:.3f} ms, mean period {b['mean_period_ms']:.4f} ms, "
            f"overruns {b['overruns']}; runtime wake-up late p99 "
            f"{r['wake_late_ms']['p99']:.2f} ms, max {r['wake_late_ms']['max']:.2f} ms; "
            f"skipped {r['skipped'] or 0}; iterations median {r['iterations']['median']:.0f}, "
            f"max {r['iterations']['max']:.0f}; plant fell behind on "
            f"{r['plant']['plant_late_ticks']} ticks (max {r['plant']['plant_late_ms_max']:.1f} ms)"
        )
    run.results = {"startup": started, "runs": rows, "lead_ms": args.lead_ms}
    run.finish()


if __name__ == "__main__":
    main()
