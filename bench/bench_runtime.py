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

Targets (issue "Deploy"): compute p99 under 5 ms, zero misses, the period
within 1 ms of 50 ms at p99 on the plant's clock.

Run::

    python bench/bench_runtime.py                 # 4 x 10 min
    python bench/bench_runtime.py --minutes 1 --dtypes float64
    python bench/bench_runtime.py --smoke         # 4 x 6 s, writes nowhere
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
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
    if rt is not None:
        cmd += ["--rt-priority", str(rt)]
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
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args()
    run = _meta.Run(_meta.output_path(args, STEM))
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
    run.results = {"runs": rows, "lead_ms": args.lead_ms}
    run.finish()


if __name__ == "__main__":
    main()
