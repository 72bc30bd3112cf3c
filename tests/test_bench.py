"""Smoke runs of the benchmark scripts (``bench/*.py``), which CI runs nowhere else.

Each test runs one script end to end on its smallest sizes (``--smoke`` or the
script's own small options) in a subprocess from the repository root, checks
the exit code and that the output has the table the full run prints (the
README's "Measured" section and docs/results.md quote those tables). The
numbers are not checked: these are not timing tests. Nothing may be written
into ``bench/`` (its result files under ``bench/results/`` included): a
``--smoke`` run writes no result file unless ``--out`` names one, which the
tests put in ``tmp_path``.

Each script's smoke run takes 4 to 23 s, most of it compiling. The default run
smokes the scripts whose smoke run is short; the scripts that only time what
other tests check (sweeps on two devices, the peers, the KKT strategies, call
overhead, layouts, the thunk graph, gradients, the learned start) run with
``-m slow``. The bench_qp_peers test is skipped without jaxopt (the bench
extra).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ampc_jax
from ampc_jax.testing.budget import budget

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"


def _bench_files() -> dict[str, tuple[int, int]]:
    """(size, mtime) of every file under bench/ (Python's byte-code caches aside)."""
    return {
        str(p.relative_to(BENCH)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in BENCH.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    }


def _shell_env() -> dict[str, str]:
    """This environment without the XLA flags that this process's ``import ampc_jax``
    appended (conftest.py), so that a script sets JAX up as it does from a shell
    (bench_can_bridge.py's compile load does not import ampc_jax)."""
    ours = set(ampc_jax.XLA_WORKAROUND_FLAGS).union(*ampc_jax.XLA_PERFORMANCE_FLAGS.values())
    env = dict(os.environ)
    flags = [f for f in env.pop("XLA_FLAGS", "").split() if f not in ours]
    if flags:
        env["XLA_FLAGS"] = " ".join(flags)
    return env


def run_bench(script: str, *args: str, timeout: float) -> str:
    """``python bench/<script> <args>`` from the repository root; its stdout."""
    before = _bench_files()
    r = subprocess.run(
        [sys.executable, str(BENCH / script), *args],
        cwd=ROOT,
        env=_shell_env(),
        capture_output=True,
        text=True,
        timeout=budget(timeout),
    )
    assert r.returncode == 0, (
        f"{script} {' '.join(args)} exited {r.returncode}\n"
        f"--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-5000:]}"
    )
    assert "Traceback" not in r.stderr, r.stderr[-5000:]
    after = _bench_files()
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
    assert not changed, f"{script} wrote into bench/: {changed}"
    return r.stdout


def _rows(out: str, first_cell: str) -> list[list[str]]:
    """The cells of the markdown table rows whose first cell starts with ``first_cell``."""
    return [
        [c.strip() for c in line.strip().strip("|").split("|")]
        for line in out.splitlines()
        if line.startswith(f"| {first_cell}")
    ]


@pytest.mark.slow  # timing of layouts; the batched solve's results are tests/batch's
@pytest.mark.timeout(90)
def test_bench_batched_layout():
    out = run_bench("bench_batched_layout.py", "--smoke", timeout=80)
    assert "us per case, batch 64, 40 x 40, float64" in out, out
    lines = out.splitlines()
    assert lines[1].split() == ["piece", "batch", "first", "batch", "last"], out
    for piece in (
        "matrix-vector product",
        "30 of them in a fori_loop",
        "inverse by symmetric sweeps",
        "Gram matrix Y'Y (10 x 40 Y)",
    ):
        row = next(line for line in lines if line.startswith(piece))
        assert len(row[32:].split()) == 2, row  # batch first, batch last
    for piece in ("LAPACK inverse", "LAPACK Cholesky"):
        row = next(line for line in lines if line.startswith(piece))
        float(row[32:])
    assert "smoke run: no result file written" in out, out


@pytest.mark.slow  # timing of calls; the calls' results are tests/admm's and tests/batch's
@pytest.mark.timeout(120)
def test_bench_call_overhead():
    out = run_bench("bench_call_overhead.py", "--smoke", timeout=110)
    assert (
        "| scenario | LE full / no-op / packed (us) | int. full / no-op / packed (us) "
        "| r_time full | packed | full minus no-op |"
    ) in out, out
    (row,) = _rows(out, "cruise_lane_change")
    assert len(row) == 6, row
    assert all(len(row[i].split(" / ")) == 3 for i in (1, 2)), row
    for ratio in row[3:]:
        assert float(ratio) > 0, row


@pytest.mark.timeout(90)
def test_bench_can_bridge(tmp_path):
    pytest.importorskip("can_bridge")
    for peer_module in ("can", "cantools", "e2e"):  # the peer process's (test extra)
        pytest.importorskip(peer_module)
    path = tmp_path / "can_bridge.json"
    out = run_bench(
        "bench_can_bridge.py",
        "--ticks",
        "100",
        "--period-ms",
        "10",
        "--json",
        str(path),
        timeout=80,
    )
    assert out.splitlines()[0].split() == [
        "condition", "ticks", "mean", "period", "ms", "drift", "ms",
        "late", "p50", "p99", "max", "overruns", "peer", "frames/crc/gaps",
    ], out  # fmt: skip
    written = json.loads(path.read_text())
    assert {"commit", "date_utc", "jax", "cpu_model", "command"} <= set(written["meta"])
    results = {r["condition"]: r for r in written["results"]}
    # jax-compile-rt is skipped (with a message) where SCHED_FIFO is not permitted
    assert {"idle", "jax-compile"} <= set(results) <= {"idle", "jax-compile", "jax-compile-rt"}
    for name, r in results.items():
        assert any(line.startswith(f"{name} ") for line in out.splitlines()), out
        assert r["ticks"] == 100, r
        # a line the peer has not drained within one period is cut on purpose, so
        # that its CRC fails, and counted (docs/bus-safety.md, "No frame older
        # than one period"): a peer starved by the compiles may see those; any
        # other bad CRC is a fault
        assert r["peer"]["frames"] > 0 and r["peer"]["bad_crc"] <= r["tx_stale_dropped"], r
    assert results["jax-compile"]["note"].startswith("JAX "), results["jax-compile"]


@pytest.mark.slow  # a closed-loop sweep's timing; the loop's results are tests/closed_loop's
@pytest.mark.timeout(120)
def test_bench_closed_loop_sweep():
    out = run_bench("bench_closed_loop.py", "sweep", "--smoke", timeout=110)
    for heading in (
        "### cruise: best rho scale per relaxation",
        "### cruise: chosen Local Explicit settings, tolerance and budget",
        "### cruise: shadow IntegratedADMM at 1e-8 Nm^2",
        "chosen for cruise: relaxation 1, rho_scale (1.0, 1.0), integrated_rho_scale 1",
        "shadow for cruise: relaxation",
    ):
        assert heading in out, out
    assert [r[0] for r in _rows(out, "Local Explicit")] == [
        "Local Explicit",
        "Local Explicit (paper)",
    ]
    # one compiled replay per solver (LE and IntegratedADMM at the sweep's cap, LE at
    # the iteration budget, the shadow), whatever the number of parameter points
    assert (
        "through 4 compiled replays (Local Explicit max_iter 2000: 1, IntegratedADMM "
        "max_iter 2000: 1, Local Explicit max_iter 15: 1, IntegratedADMM max_iter 5000: 1)"
    ) in out, out
    defaults, _ = json.JSONDecoder().raw_decode(out.split("solver_defaults =", 1)[1].lstrip())
    assert set(defaults["cruise"]) == {
        "relaxation",
        "rho_scale",
        "integrated_rho_scale",
        "shadow_relaxation",
        "shadow_rho_scale",
    }
    assert "smoke run: no result file written" in out, out


@pytest.mark.timeout(60)
def test_bench_closed_loop_table(tmp_path):
    """``table`` on the folders ``ampc simulate --compare`` writes (``DIR/metrics.json``,
    ``DIR/baseline/metrics.json``) and on a run without MPC (hand-made metrics:
    a real ``ampc simulate`` run would cost about 10 s)."""
    m = {
        "formulation": "local_explicit",
        "objectives": ["LST", "YRT"],
        "tol_primal": 1.0,
        "relaxation": 1.5,
        "rho_scale": [1.0, 0.5],
        "integrated_rho_scale": 0.3,
        "anderson": 3,
        "e_sub_p95": 0.342,
        "e_sub_max": 0.645,
        "iterations_p50": 6,
        "iterations_p95": 9.85,
        "iterations_max": 13,
        "r_time_median": 1.04,
        "r_time_p95": 1.27,
        "t_distributed_median_us": 68.2,
        "t_integrated_median_us": 66.0,
        "yaw_rms": 0.0,
        "yaw_rms_focus": None,
        "rear_slip_abs_max": 0.00119,
        "rear_slip_abs_p95": 0.00119,
        "realtime_factor": 281.0,
    }
    (tmp_path / "cruise" / "baseline").mkdir(parents=True)
    (tmp_path / "cruise" / "metrics.json").write_text(json.dumps(m))
    lst = {**m, "objectives": ["LST"]}
    (tmp_path / "cruise" / "baseline" / "metrics.json").write_text(json.dumps(lst))
    (tmp_path / "dlc").mkdir()
    none = {"formulation": "none", "objectives": [], "no_mpc": "driver alone"}
    (tmp_path / "dlc" / "metrics.json").write_text(json.dumps(none))
    out = run_bench("bench_closed_loop.py", "table", str(tmp_path), timeout=50)
    assert out.startswith("| run | objectives | tol | alpha / rho scale"), out
    rows = {r[0]: r for r in _rows(out, "`")}
    assert set(rows) == {"`cruise`", "`cruise/baseline`", "`dlc`"}, out
    assert rows["`cruise`"][1:6] == [
        "LST+YRT",
        "1",
        "1.5 / [1.0, 0.5]; 0.3 / 3",
        "0.342 / 0.645",
        "6 / 9.85 / 13",
    ], rows
    assert rows["`cruise/baseline`"][1] == "LST", rows
    assert rows["`dlc`"][1] == "driver alone", rows


@pytest.mark.slow  # the KKT strategies' timing; their results are tests/formulations/test_local_explicit.py's
@pytest.mark.timeout(120)
def test_bench_local_explicit(tmp_path):
    path = tmp_path / "local_explicit.json"
    out = run_bench("bench_local_explicit.py", "--smoke", "--out", str(path), timeout=110)
    assert "N_p=10 [tuned]: full step warm" in out, out
    assert "ratio JAX/OSQP" in out and "JAX/Clarabel" in out, out
    assert "N_p=10: compiled 2 programs (cold and warm step) for solver 'plain'" in out, out
    assert "N_p=10 float64 batch      1:" in out, out
    assert "N_p=10 float64 [tuned]: OSQP Python loop" in out, out
    assert "best JAX batch / OSQP loop =" in out, out
    doc = json.loads(path.read_text())
    assert {"commit", "date_utc", "jax", "jaxlib", "numpy", "cpu_model", "cpu_affinity"} <= set(
        doc["meta"]
    ), doc["meta"]
    assert {"loadavg_start", "loadavg_end", "command"} <= set(doc["meta"]), doc["meta"]
    assert "--smoke" in doc["meta"]["command"], doc["meta"]
    assert any(line.startswith("N_p=10 [tuned]: full step warm") for line in doc["printed"])
    results = doc["results"]
    (lat,) = results["latency"]
    (thr,) = results["throughput"]
    assert lat["horizon"] == 10 and lat["steps"] == 5 and lat["ratio_jax_over_osqp"] > 0, lat
    assert thr["ratio_best_jax_over_osqp_loop"] > 0, thr


@pytest.mark.timeout(120)
def test_bench_qp_peers():
    pytest.importorskip("jaxopt")  # in the test extra too, so CI runs it
    out = run_bench("bench_qp_peers.py", "--smoke", timeout=110)
    assert (
        "| scenario | solver | step median (us) | **r_time = t_LE / t_solver** "
        "| e_sub p95 / max (Nm) | iterations p50 / p95 |"
    ) in out, out
    rows = _rows(out, "cruise_lane_change")
    assert [r[1] for r in rows] == [
        "Local Explicit",
        "IntegratedADMM",
        "BoxOSQP lu, tol 0.001",
    ], out
    assert all(len(r) == 6 for r in rows), rows
    assert float(rows[0][3]) == 1.0, rows  # Local Explicit against itself
    assert "smoke run: no result file written" in out, out


@pytest.mark.slow  # the formulations against Clarabel are tests/formulations' in the default run
@pytest.mark.timeout(120)
def test_bench_formulations(tmp_path):
    """1 s of cruise (each formulation at its default and one grid point) and two
    generated problems: 35 to 50 s on the shared 2-core machine, mostly compiling."""
    figure = tmp_path / "formulations.png"
    out = run_bench("bench_formulations.py", "--smoke", "--out-figure", str(figure), timeout=110)
    assert (
        "| scenario / family | formulation | setting | e_sub p50 / p95 / max (Nm) "
        "| r_time p50 / p95 | iterations p50 / p95 / max |"
    ) in out, out
    table = out.split("### closed-loop grid", 1)[0]
    closed = _rows(table, "cruise_lane_change")
    family = _rows(table, "random 2 objectives")
    for rows in (closed, family):
        assert all(len(r) == 6 for r in rows), rows
    names = ["Local Explicit (F3)", "Fully Distributed (F1)", "Virtual Center (F2)"]
    # each formulation at its default and its best setting, then the family's rows
    assert [r[1] for r in closed] == [n for n in names for _ in range(2)], out
    assert [r[1] for r in family] == [*names, "IntegratedADMM"], out
    assert "Rule for 'best': best = the grid point with the smallest iterations max" in out
    assert out.count("  verdict: ") == 4, out
    assert 0 < figure.stat().st_size < 150_000
    assert "smoke run: no result file written" in out, out


@pytest.mark.timeout(60)
def test_bench_rho():
    out = run_bench("bench_rho.py", "--smoke", timeout=50)
    lines = out.splitlines()
    assert lines[0] == "seed  it(rho*)  best  best scale (per objective)  ratio", out
    assert lines[1].split()[0] == "0" and float(lines[1].split()[-1]) > 0, out
    assert lines[2].startswith("ratio min "), out
    # the grid is a batch of SolverParams through one compiled solve
    assert "[compiled: rho* solve 1, 169-point grid solve 1" in out, out


@pytest.mark.slow  # a compile-and-time script; the batched step's results are tests/batch's
@pytest.mark.timeout(120)
def test_bench_thunk_graph():
    out = run_bench("bench_thunk_graph.py", "--smoke", timeout=110)
    lines = out.splitlines()
    assert lines[0].split() == [
        "scenario",
        "solver",
        "thunks",
        "sources",
        "max",
        "waiting",
        "verdict",
    ]
    rows = [line.split() for line in lines[1:] if line.startswith("cruise_lane_change")]
    assert lines[-1].startswith("smoke run: no result file written"), out
    assert [r[:2] for r in rows] == [["cruise_lane_change", "LE"], ["cruise_lane_change", "IA"]]
    for r in rows:
        n, sources, worst = map(int, r[2:5])
        assert 0 < sources <= n and 0 <= worst < n, r
        assert r[5] in ("inline", "splits"), r


@pytest.mark.slow  # the formulations' own tests cover 2 to 4 objectives in the default run
@pytest.mark.timeout(120)
def test_bench_many_objectives():
    """Two generated problems with 2 and 3 objectives, every decomposed formulation
    (about 25 s, mostly compiling)."""
    out = run_bench("bench_many_objectives.py", "--smoke", timeout=110)
    assert "| objectives | sharing | formulation | converged |" in out, out
    for name in ("local_explicit", "fully_distributed", "virtual_center"):
        rows = [r for r in _rows(out, "3") if r[2] == name]
        assert rows and rows[0][3] == "2 / 2", out
    assert "smoke run: no result file written" in out, out


@pytest.mark.slow  # two devices, two processes and a pinned peer for minutes; the sweep's results are tests/sweep's
@pytest.mark.both_cores  # two XLA devices and two DAQP processes
@pytest.mark.timeout(150)
def test_bench_sweep(tmp_path):
    """Every section on tiny sizes: 4 cruise cases x 4 rho points against DAQP and qpax."""
    pytest.importorskip("daqp")
    pytest.importorskip("qpax")
    path = tmp_path / "sweep.json"
    out = run_bench("bench_sweep.py", "--smoke", "--devices", "2", "--out", str(path), timeout=140)
    assert "| contender | worst error (Nm) | median error (Nm) |" in out, out
    (row,) = _rows(out, "4 |")
    assert len(row) == 9 and float(row[7].replace(",", "")) > 0, row  # LE / DAQP
    assert "| family | runner | computed / needed | wall (ms) | speed-up |" in out, out
    assert len(_rows(out, "generated (N_p")) == 2, out  # vmap while_loop, compaction
    assert "| jax.grad (reverse mode) |" in out and "| forward solve_fixed |" in out, out
    assert _rows(out, "generated (woodbury") or _rows(out, "generated (dense"), out
    doc = json.loads(path.read_text())
    assert "--smoke" in doc["meta"]["command"], doc["meta"]
    assert set(doc["results"]) == {"throughput", "waste", "grad", "pencil"}, doc["results"]
    assert doc["results"]["grad"]["grad_over_forward"] > 0, doc["results"]["grad"]


@pytest.mark.slow  # the peers' throughput and latency runs; the formulations against Clarabel are tests/formulations'
@pytest.mark.both_cores  # two XLA devices, two pinned peer processes, a pinned latency child
@pytest.mark.timeout(150)
def test_bench_peers(tmp_path):
    """Both sections on the smallest sizes: N_p = 10, float64, the KKT solve "auto" picks,
    one 6-step latency drive, batches of 1 and 10 drives of 3 steps, each peer once
    (about 50 s on the shared 2-core machine, mostly compiling). proxsuite and qpax are
    not required (the script skips a missing peer)."""
    pytest.importorskip("daqp")
    path = tmp_path / "peers.json"
    out = run_bench("bench_peers.py", "--smoke", "--out", str(path), timeout=140)
    assert "a general row is active at the reference solution in" in out, out
    assert "| LE | tol (Nm^2) | worst error (Nm) | median error (Nm) |" in out, out
    # latency: Local Explicit's full step and its parts, the condensing, DAQP alone and with it
    assert (
        "| contender | setting | median (us) | p99 (us) | worst error (Nm) | median error (Nm) "
        "| iterations median / max |"
    ) in out, out
    lat = {r[0]: r for r in _rows(out, "") if len(r) == 7 and r[0] != "contender"}
    full = [k for k in lat if k.startswith("LE ") and k.endswith("full step")]
    assert len(full) == 1, out
    for name in (
        *full,
        full[0].replace("full step", "setup alone"),
        full[0].replace("full step", "iterations alone"),
        "condensing (jitted condensed_qp, to numpy)",
        "DAQP update + solve",
        "DAQP + condensing (one call)",
    ):
        assert float(lat[name][2]) > 0 and float(lat[name][3]) > 0, lat.get(name, out)
    assert float(lat["DAQP update + solve"][4]) < 1e-2, lat  # worst error (Nm)
    assert any(
        line.startswith(("PASS latency N_p=10", "MISS latency N_p=10")) for line in out.splitlines()
    )
    # throughput: steps/s of every contender, ratios to DAQP's solve alone
    assert "| cases | contender | steps/s | / DAQP solve | / (DAQP + condensing) |" in out, out
    thr = {(r[0], r[1]): r for r in _rows(out, "1") if len(r) == 5}
    for B in ("1", "10"):
        assert thr[B, "DAQP solve"][3] == "1.00", thr
        le = [k for k in thr if k[0] == B and k[1].startswith("LE ") and "setup" not in k[1]]
        assert len(le) == 1 and float(thr[le[0]][2].replace(",", "")) > 0, thr
    assert "| contender | data + setup | full step | setup share | iterations mean |" in out, out
    assert "| contender | cases | XLA flops a call | GFLOP/s (XLA) | % of peak |" in out, out
    assert "NOT RUN throughput N_p=10, 1,000 cases" in out, out
    doc = json.loads(path.read_text())
    assert "--smoke" in doc["meta"]["command"], doc["meta"]
    res = doc["results"]
    assert {"calibration", "latency", "throughput"} <= set(res), set(res)
    assert res["latency"]["10"]["target"]["verdict"] in ("PASS", "MISS"), res["latency"]
    assert res["throughput"]["10"]["accuracy"]["DAQP"]["err_max"] < 1e-2, res["throughput"]
    assert res["throughput"]["peak_flops"]["float64"] > 0, res["throughput"]


@pytest.mark.timeout(150)
def test_bench_compile(tmp_path):
    """ampc solve cold (an empty cache directory) and warm in two fresh processes: the
    command's default compilation cache (AMPC_COMPILATION_CACHE) is filled by the first
    run and every program of the second is loaded from it (JAX's cache-hit events)."""
    path = tmp_path / "compile.json"
    out = run_bench("bench_compile.py", "--smoke", "--out", str(path), timeout=140)
    assert "| command | cold: first result (s) | XLA compile (s) | programs |" in out, out
    (row,) = _rows(out, "solve |")
    assert row[-1] == "0/0", row  # both runs exited 0
    doc = json.loads(path.read_text())
    solve = doc["results"]["commands"]["solve"]
    assert solve["cold"]["programs"] > 0 and solve["cold"]["cache_hits"] == 0, solve
    assert solve["warm"]["cache_hits"] == solve["warm"]["programs"] > 0, solve
    assert doc["results"]["targets"]["program"] in ("PASS", "MISS"), doc["results"]


@pytest.mark.slow  # two minutes of compiling on 2 cores; the gradients' accuracy is tests/admm/test_implicit.py's
@pytest.mark.timeout(300)
def test_bench_grad(tmp_path):
    """The gradient's cost against the forward pass (16 cases, K = 3, woodbury_factored):
    the unrolled gradient and the implicit one, each within 1e-5 of central differences
    of its own forward function; the implicit one's rho and alpha entries vanish."""
    path = tmp_path / "grad.json"
    out = run_bench("bench_grad.py", "--smoke", "--out", str(path), timeout=280)
    assert (
        "| KKT | contender | forward (ms) | value_and_grad (ms) | ratio | temp MB fwd / grad "
        "| gradient error vs fd |"
    ) in out, out
    doc = json.loads(path.read_text())
    rows = doc["results"]["rows"]
    assert set(rows) == {"woodbury_factored"}, rows
    c = rows["woodbury_factored"]["contenders"]
    assert set(c) == {"unrolled vmap", "implicit 1e-06"}, c
    for r in c.values():
        assert r["forward_ms"] > 0 and r["grad_ms"] > 0 and r["ratio"] > 0, r
        assert r["fd_error"] < 1e-5, r
    g = np.abs(c["implicit 1e-06"]["gradient"])
    assert np.all(g[:3] < 1e-6 * g.max()), g  # log rho (2), alpha: the solution ignores them
    for label in ("unrolled", "implicit"):
        assert any(
            line.startswith((f"PASS woodbury_factored {label}", f"MISS woodbury_factored {label}"))
            for line in out.splitlines()
        ), out


@pytest.mark.slow  # trains a network; the learned start is tests/tuning/test_warm_start.py's
@pytest.mark.timeout(400)
def test_bench_warm_start(tmp_path):
    path = tmp_path / "warm_start.json"
    out = run_bench("bench_warm_start.py", "--smoke", "--out", str(path), timeout=380)
    assert "cruise_step: StartModel(kind='step', sizes=[122, 4, 8]" in out, out
    assert "validation after 0 unrolled steps" in out, out
    doc = json.loads(path.read_text())
    hist = doc["results"]["history"]
    assert sum(h["phase"] == "pretrain" for h in hist) == 30
    assert sum(h["phase"] == "unrolled" for h in hist) == 2
    assert path.with_suffix(".png").stat().st_size > 0
