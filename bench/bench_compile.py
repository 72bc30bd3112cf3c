"""Compile times a user waits for: each README command, cold and then from the cache.

Every command of the README's "Command line" section (and the deployment,
sweep and tuning blocks) runs in a fresh process, first with an empty
compilation cache directory (``AMPC_COMPILATION_CACHE``: cold, every program
compiled), then again with the cache that run filled (warm: what a second
run of the same command costs). For each run the script prints

* the time to the command's first result: the process's exit for a command
  that finishes (``solve``, ``simulate``, ``export``, ``replay``, ``tune``), the
  first chunk file for a sweep (its first results on disk), the first
  progress line of ``ampc run`` (the first ticks sent), after which the
  process is stopped;
* the XLA compile time summed over its programs, their number, and the
  slowest program with its compile time (JAX's monitoring events
  ``/jax/core/compile/backend_compile_duration``, recorded by a listener in
  the child process, ``--child``); warm, the programs loaded from the cache
  (``/jax/compilation_cache/cache_hits``) out of all;

and the targets as PASS / MISS lines: every command's first result within
``TARGET_FIRST_S`` (15 s) cold, no program over ``TARGET_PROGRAM_S`` (60 s).

Commands whose inputs another command writes (``ampc replay`` reads a run,
``--artefact`` an export, ``--params`` a tune) run after it, in one scratch
directory; a problem file is the shipped example. Two commands are bounded
so that the measurement ends: ``ampc run`` gets ``--duration 2`` (its first
result is its first progress line either way), and the sweeps stop at their
first chunk. ``ampc run`` needs the runtime extra and ``can_bridge``; it is
skipped (said so) without them.

Run::

    python bench/bench_compile.py                  # every command, cold and warm (about 12 min)
    python bench/bench_compile.py --only solve,simulate
    python bench/bench_compile.py --smoke          # ampc solve only, cold and warm (about 30 s)

Result file: ``bench/results/bench_compile.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import _meta  # noqa: E402  (bench/_meta.py, beside this script)

STEM = "bench_compile"
ROOT = Path(__file__).resolve().parents[1]
TARGET_FIRST_S = 15.0
TARGET_PROGRAM_S = 60.0
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
TIMEOUT_S = 900.0

# name, argv (after ``ampc``; {w} the scratch directory), first result: "exit",
# ("file", glob under {w}) or ("line", regex on the output); needs: modules
COMMANDS: list[tuple[str, list[str], Any, tuple[str, ...]]] = [
    ("solve", ["solve", "cruise_control", "--json"], "exit", ()),
    (
        "solve integrated osqp",
        ["solve", "{p}", "--formulation", "integrated", "--solver", "osqp"],
        "exit",
        ("osqp",),
    ),
    ("solve fully_distributed", ["solve", "{p}", "--formulation", "fully_distributed"], "exit", ()),
    (
        "solve tuned options",
        ["solve", "{p}", "--rho-scale", "1,0.3", "--relaxation", "1.6", "--anderson", "3"]
        + ["--tol", "1e-8"],
        "exit",
        (),
    ),
    ("simulate", ["simulate", "cruise_lane_change", "--out", "{w}/cruise"], "exit", ()),
    (
        "simulate --compare",
        ["simulate", "stability_launch_brake", "--compare", "--out", "{w}/launch"],
        "exit",
        (),
    ),
    (
        "simulate float32",
        ["simulate", "cruise_lane_change", "--disable", "YRT", "--set", "q_lst=8", "--float32"]
        + ["--out", "{w}/lst"],
        "exit",
        (),
    ),
    (
        "run --with-plant",
        ["run", "--channel", "slcan-pty:", "--scenario", "cruise_lane_change", "--with-plant"]
        + ["--duration", "2", "--out", "{w}/run"],
        ("line", r"^t\s+[\d.]+/"),
        ("can_bridge", "can", "cantools"),
    ),
    (
        "export",
        ["export", "--scenario", "cruise_lane_change", "--out", "{w}/cruise.ampc"],
        "exit",
        ("flatbuffers",),
    ),
    (
        "replay",
        ["replay", "{w}/run", "--rho-scale", "0.5,1,2", "--formulation", "virtual_center"]
        + ["--float32", "--out", "{w}/run/replay"],
        "exit",
        ("can_bridge", "can", "cantools"),
    ),
    (
        "simulate bridge actuators",
        ["simulate", "cruise_lane_change", "--actuators", "bridge", "--out", "{w}/sim"],
        "exit",
        (),
    ),
    (
        "sweep cruise_step",
        ["sweep", "--family", "cruise_step", "--cases", "10000", "--rho", "0.03:30:30"]
        + ["--out", "{w}/sweeps/cruise"],
        ("file", "sweeps/cruise/chunks/chunk_00000*.parquet"),
        ("pyarrow",),
    ),
    (
        "sweep closed loops",
        ["sweep", "--family", "cruise_lane_change", "--cases", "20", "--rho", "0.3:3:5"]
        + ["--out", "{w}/sweeps/loops"],
        ("file", "sweeps/loops/chunks/chunk_00000*.parquet"),
        ("pyarrow",),
    ),
    (
        "tune solver",
        ["tune", "--family", "cruise_step", "--cases", "32", "--steps", "150"]
        + ["--iterations", "10", "--out", "{w}/tuned"],
        "exit",
        (),
    ),
    ("tune weights", ["tune", "--objective", "weights", "--out", "{w}/tuned_weights"], "exit", ()),
    (
        "simulate --params",
        ["simulate", "cruise_lane_change", "--params", "{w}/tuned/params.json", "--out", "{w}/p"],
        "exit",
        (),
    ),
]
SMOKE = ("solve",)


def child(events: str, argv: list[str]) -> int:
    """``ampc argv`` in this process, every XLA compilation appended to ``events``
    (one JSON line each, written as it happens: the parent may stop the process
    at its first result)."""
    import jax.monitoring as mon

    f = open(events, "a", buffering=1)  # noqa: SIM115  (open for the process's life)

    def on_duration(event: str, seconds: float, **kw: Any) -> None:
        if event == COMPILE_EVENT:
            f.write(json.dumps({"s": seconds, "name": str(kw.get("fun_name", ""))}) + "\n")

    def on_event(event: str, **kw: Any) -> None:
        if event == CACHE_HIT_EVENT:
            f.write(json.dumps({"hit": 1}) + "\n")

    mon.register_event_duration_secs_listener(on_duration)
    mon.register_event_listener(on_event)
    from ampc_jax.cli import main

    return main(argv)


def _available(modules: tuple[str, ...]) -> list[str]:
    import importlib.util

    return [m for m in modules if importlib.util.find_spec(m) is None]


def run_one(argv: list[str], first: Any, work: Path, cache: Path) -> dict[str, Any]:
    """One fresh process of ``ampc argv`` with the cache ``cache``: seconds to its first
    result, its exit code, and its compilations."""
    events = Path(tempfile.mkstemp(prefix="compile_", suffix=".jsonl")[1])
    env = dict(os.environ, AMPC_COMPILATION_CACHE=str(cache), PYTHONUNBUFFERED="1")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(events), "--", *argv]
    out_path = work / f"out_{time.monotonic_ns()}.txt"
    t0 = time.perf_counter()
    with open(out_path, "w") as out:
        proc = subprocess.Popen(cmd, cwd=work, env=env, stdout=out, stderr=subprocess.STDOUT)
        first_s = None
        while True:
            rc = proc.poll()
            now = time.perf_counter() - t0
            if isinstance(first, tuple) and first_s is None:
                kind, pattern = first
                if kind == "file" and glob.glob(str(work / pattern)):
                    first_s = now
                elif kind == "line" and re.search(pattern, out_path.read_text(), re.M):
                    first_s = now
                if first_s is not None and rc is None:
                    proc.terminate()
                    proc.wait(timeout=60)
                    rc = 0  # stopped at its first result
                    break
            if rc is not None:
                break
            if now > TIMEOUT_S:
                proc.kill()
                proc.wait()
                rc = -9
                break
            time.sleep(0.05)
    wall = time.perf_counter() - t0
    if first == "exit":
        first_s = wall
    text = out_path.read_text()
    rec = [json.loads(line) for line in events.read_text().splitlines() if line.strip()]
    events.unlink()
    comp = [r for r in rec if "s" in r]
    slow = max(comp, key=lambda c: c["s"], default={"s": 0.0, "name": "-"})
    return {
        "rc": rc,
        "first_s": first_s,
        "wall_s": wall,
        "compile_s": sum(c["s"] for c in comp),
        "programs": len(comp),
        "cache_hits": sum(1 for r in rec if "hit" in r),
        "slowest_s": slow["s"],
        "slowest": slow["name"],
        "tail": text.splitlines()[-3:] if rc not in (0, None) else [],
    }


def fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        rest = argv[argv.index("--") + 1 :]
        return child(argv[1], rest)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", help="comma-separated command names (default: all)")
    ap.add_argument("--smoke", action="store_true", help="ampc solve only")
    ap.add_argument("--no-warm", action="store_true", help="cold runs only")
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    names = [c[0] for c in COMMANDS]
    want = SMOKE if args.smoke else tuple(args.only.split(",")) if args.only else names
    unknown = [n for n in want if n not in names]
    if unknown:
        ap.error(f"--only: unknown command(s) {unknown}; known: {names}")
    run = _meta.Run(_meta.output_path(args, STEM))
    work = Path(tempfile.mkdtemp(prefix="bench_compile_"))
    problem = ROOT / "ampc_jax" / "examples" / "cruise_control.json"
    print(f"load average at the start: {os.getloadavg()[0]:.2f} (2 cores: above 1 is shared)")
    print()
    print(
        "| command | cold: first result (s) | XLA compile (s) | programs | slowest program (s) "
        "| warm: first result (s) | XLA compile (s) | cache hits | rc |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    rows: dict[str, Any] = {}
    try:
        for name, template, first, needs in COMMANDS:
            if name not in want:
                continue
            missing = _available(needs)
            if missing:
                print(f"| {name} | skipped: needs {', '.join(missing)} | | | | | | | |")
                rows[name] = {"skipped": missing}
                continue
            cmd = [a.format(w=work, p=problem) for a in template]
            cache = work / f"cache_{len(rows)}"
            shutil.rmtree(cache, ignore_errors=True)
            cold = run_one(cmd, first, work, cache)
            # the second run writes over the first's --out (refused without --force)
            again = [*cmd, "--force"] if "--out" in cmd else cmd
            warm = None if args.no_warm else run_one(again, first, work, cache)
            # the command as a reader types it (repository-relative, {w}: any scratch folder)
            rel = str(problem.relative_to(ROOT))
            rows[name] = {
                "argv": [a.replace("{p}", rel) for a in template],
                "cold": cold,
                "warm": warm,
            }
            w = warm or {}
            rc = cold["rc"] if not warm else f"{cold['rc']}/{warm['rc']}"
            print(
                f"| {name} | {fmt(cold['first_s'])} | {fmt(cold['compile_s'])} | "
                f"{cold['programs']} | {cold['slowest_s']:.1f} ({cold['slowest']}) | "
                f"{fmt(w.get('first_s'))} | {fmt(w.get('compile_s'))} | "
                f"{w.get('cache_hits', '-')} / {w.get('programs', '-')} | {rc} |",
                flush=True,
            )
            for line in cold["tail"] + (w.get("tail") or []):
                print(f"    {name}: {line}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    ran = {k: v for k, v in rows.items() if "cold" in v}
    print()
    slow_first = {k: v["cold"]["first_s"] for k, v in ran.items()}
    late = {k: s for k, s in slow_first.items() if s is None or s > TARGET_FIRST_S}
    worst_prog = max(
        ((v["cold"]["slowest_s"], f"{k}: {v['cold']['slowest']}") for k, v in ran.items()),
        default=(0.0, "-"),
    )
    failed = [k for k, v in ran.items() if v["cold"]["rc"] != 0]
    verdict_first = "PASS" if not late and ran else "MISS"
    verdict_prog = "PASS" if worst_prog[0] <= TARGET_PROGRAM_S and ran else "MISS"
    print(
        f"{verdict_first} every command's first result within {TARGET_FIRST_S:.0f} s cold"
        + (f" (over: {', '.join(f'{k} {fmt(s)} s' for k, s in late.items())})" if late else "")
    )
    print(
        f"{verdict_prog} no program over {TARGET_PROGRAM_S:.0f} s to compile "
        f"(slowest {worst_prog[0]:.1f} s, {worst_prog[1]})"
    )
    if failed:
        print(f"FAILED (non-zero exit): {', '.join(failed)}")
    run.results = {
        "commands": rows,
        "targets": {
            "first_result_s": TARGET_FIRST_S,
            "program_s": TARGET_PROGRAM_S,
            "first_result": verdict_first,
            "program": verdict_prog,
        },
    }
    run.finish()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
