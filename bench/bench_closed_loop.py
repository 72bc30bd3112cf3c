"""Closed-loop solver tuning and metric tables (docs/results.md, "Solver tuning").

Two sub-commands:

``sweep``
    Chooses each vehicle example's solver defaults
    (``VehicleExample.solver_defaults``: the ``SimConfig`` fields ``rho_scale``,
    ``relaxation``, ``integrated_rho_scale``, ``shadow_rho_scale`` and
    ``shadow_relaxation``). For every scenario of the example, one closed loop
    is run with the paper's solver (``PAPER_SOLVER_OPTIONS``: rho* unscaled, no
    over-relaxation, no acceleration) and its per-step :class:`ProblemData`
    and shadow optimum are logged. The logged steps are then replayed in
    order, each solve warm started from the replay's own shifted previous
    iterate (as in the loop), for every point of a grid:

    * Local Explicit: rho_j = s_j rho_j* with (s_1, s_2) on a 7 x 7 grid, for
      each relaxation alpha;
    * IntegratedADMM: rho = s rho* with s on a 13-point grid, same alphas,

    at the controller's tolerance (eps_r = eps_s = 1 Nm^2). e_sub is measured
    against the logged shadow optimum. The *same* rule picks both solvers'
    settings: among the points whose e_sub p95 is below 5 Nm on every scenario
    of the example, the smallest worst-case ratio "iterations p95 / target"
    (15 for cruise and launch/brake, 25 for the DLC), ties broken by the mean
    iteration count. alpha is chosen for Local Explicit; IntegratedADMM gets
    the same alpha and its own best rho scale at that alpha (its best over all
    alphas is printed too, to show it is not handicapped). The shadow's
    settings are chosen by iterations at its tight tolerance.

    Every grid point is a :class:`~ampc_jax.admm.SolverParams` point, an
    argument of the compiled replay: each solver (a set of static options:
    formulation and iteration cap) is compiled once per logged run length,
    and the points go through that one program ``--chunk`` at a time
    (vmapped). The script prints the number of compiled programs
    (``_cache_size()`` of each jitted replay): one per solver and run length
    whatever the number of points. The whole sweep takes under a minute on one
    core, most of it compiling; the chunk size hardly matters (chunks of 1, 8
    and 32 take about the same time and choose the same settings).

``table DIR [DIR ...]``
    Prints the markdown table of docs/results.md from the ``metrics.json`` of
    ``ampc simulate`` runs (one directory per run, with its ``baseline/`` when
    it has one; a directory holding run directories is expanded). It formats
    existing runs and writes no result file.

Run pinned to one core (batched XLA:CPU programs can deadlock on 2 cores,
docs/known-issues.md)::

    timeout 600 taskset -c 1 python bench/bench_closed_loop.py sweep   # under a minute
    python bench/bench_closed_loop.py sweep --smoke   # 1 s of cruise; no result file
    timeout 60 taskset -c 1 python bench/bench_closed_loop.py table runs/

Result file of ``sweep``: ``bench/results/bench_closed_loop.json`` (``--out``;
``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

import _meta  # bench/_meta.py, beside this script
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)
from ampc_jax.results import Status, usable

STEM = "bench_closed_loop"
EXAMPLES = {
    "cruise": ("cruise_lane_change",),
    "stability": ("stability_launch_brake", "stability_dlc"),
}
TARGETS = {"cruise_lane_change": 15, "stability_launch_brake": 15, "stability_dlc": 25}
E_SUB_LIMIT = 5.0  # Nm, e_sub p95 target
LE_GRID = (0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0)
INT_GRID = (0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.7, 0.85, 1.0, 1.2, 1.5, 2.0)
RELAXATIONS = (1.0, 1.2, 1.4, 1.5, 1.6, 1.7, 1.8)
SHADOW_GRID = (0.3, 0.5, 1.0, 2.0)
SHADOW_TOL, SHADOW_MAX_ITER = 1e-8, 5000  # the loop's shadow (SimConfig defaults)
SWEEP_MAX_ITER = 2000  # the replays' cap: high enough that the cap itself picks nothing
CHUNK = 8  # parameter points vmapped together in one call of a compiled replay (docstring)
SMOKE_DURATION = 1.0  # s of closed loop in ``sweep --smoke``
SMOKE_CHUNK = 2  # few points in a smoke run: still two chunks and a padded one


# --------------------------------------------------------------------------- replay
def logged_run(name: str, duration: float | None = None) -> tuple[Any, Any]:
    """Closed loop of ``name`` with the paper's solver; returns (config, log as JAX arrays).

    ``duration``: simulated s (default: the scenario's).
    """
    import jax
    import jax.numpy as jnp

    from ampc_jax.closed_loop import PAPER_SOLVER_OPTIONS, config_for, simulate

    cfg = config_for(name, **PAPER_SOLVER_OPTIONS)
    res = simulate(name, cfg, duration=duration)
    return cfg, jax.tree.map(jnp.asarray, res.log)


class Replay:
    """The logged steps of a closed loop replayed in order through one solver,
    for a batch of :class:`~ampc_jax.admm.SolverParams` points.

    One jitted program (``fn``) per solver: it takes the run's ProblemData
    (steps on the leading axis) and ``chunk`` parameter points, so every
    scenario of the same length and every point reuse it. Each step is solved
    from the replay's own shifted previous iterate (cold after a failed step,
    or at every step without warm start).
    """

    def __init__(self, solver: Any, warm_start: bool, warm_shift: int, chunk: int) -> None:
        import jax
        import jax.numpy as jnp

        self.solver, self.chunk = solver, chunk

        def one(data: Any, p: Any) -> Any:
            cold = solver.cold_state(data.A.dtype)

            def step(warm: Any, d: Any) -> Any:
                res = solver.solve(d, p, warm)
                ok = usable(res.status) & jnp.all(jnp.isfinite(res.u0))
                shifted = solver.shift(res.state, warm_shift)
                new = jax.tree.map(lambda a, b: jnp.where(ok, a, b), shifted, cold)
                return (new if warm_start else cold), (res.iterations, res.u0, res.status)

            return jax.lax.scan(step, cold, data)[1]

        self.fn = jax.jit(jax.vmap(one, in_axes=(None, 0)))

    def compiles(self) -> int:
        """Programs compiled so far (one per distinct logged run length)."""
        return int(self.fn._cache_size())

    def __call__(self, data: Any, params: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(iterations (P, K), u0 (P, K, n_u), status (P, K)) for P points ``params``
        (leading axis P on every leaf), ``chunk`` points per call (the last chunk
        padded with copies of the last point)."""
        import jax
        import jax.numpy as jnp

        P = int(np.shape(params.relaxation)[0])
        pad = (-P) % self.chunk
        padded = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, 0)]), params)
        outs = []
        for c in range(0, P + pad, self.chunk):
            part = jax.tree.map(lambda x, c=c: x[c : c + self.chunk], padded)
            outs.append(jax.device_get(self.fn(data, part)))
        it, u0, st = (np.concatenate(x)[:P] for x in zip(*outs, strict=True))
        return it, u0, st


class Replays:
    """The compiled replays of one example, one per solver (kind, iteration cap)."""

    def __init__(self, config: Any, chunk: int) -> None:
        from ampc_jax.closed_loop import controller_for

        self.config, self.chunk = config, chunk
        self.topology = controller_for(config).topology
        self.cols = controller_for(config).input_columns
        self.replays: dict[tuple[str, int], Replay] = {}
        self.points = 0

    def get(self, kind: str, max_iter: int) -> Replay:
        from ampc_jax.formulations import IntegratedADMM, LocalExplicit

        if (kind, max_iter) not in self.replays:
            cls = IntegratedADMM if kind == "int" else LocalExplicit
            solver = cls(self.topology, max_iter=max_iter)
            self.replays[kind, max_iter] = Replay(
                solver, self.config.warm_start, self.config.warm_shift, self.chunk
            )
        return self.replays[kind, max_iter]

    def run(
        self,
        log: Any,
        kind: str,
        scales: np.ndarray,
        relaxations: np.ndarray,
        tols: np.ndarray,
        max_iter: int,
    ) -> dict[str, np.ndarray]:
        """Replay ``log`` for P points: ``scales`` (P, n_rho) factors on rho*,
        ``relaxations`` (P,), ``tols`` (P,) for eps_r = eps_s. Returns
        ``iterations`` (P, K), ``e_sub`` (P, K * n_u) against the logged shadow
        optimum, ``status`` (P, K) and ``u0`` (P, K, n_u)."""
        replay = self.get(kind, max_iter)
        dt = log.data.A.dtype
        params = replay.solver.params(
            rho=np.asarray(scales, float),
            relaxation=np.asarray(relaxations, float),
            tol_primal=np.asarray(tols, float),
            tol_dual=np.asarray(tols, float),
            dtype=dt,
        )
        it, u0, st = replay(log.data, params)
        self.points += len(relaxations)
        ush = np.asarray(log.u_shadow)[:, self.cols]
        e = np.abs(u0 - ush[None])
        return {
            "iterations": it,
            "e_sub": e.reshape(e.shape[0], -1),
            "status": st,
            "u0": u0,
        }

    def compiles(self) -> dict[str, int]:
        label = {"le": "Local Explicit", "int": "IntegratedADMM"}
        return {f"{label[k]} max_iter {m}": r.compiles() for (k, m), r in self.replays.items()}


def stats(r: dict[str, np.ndarray], g: int) -> dict[str, float]:
    it = r["iterations"][g].astype(float)
    e = r["e_sub"][g]
    return {
        "p50": float(np.percentile(it, 50)),
        "p95": float(np.percentile(it, 95)),
        "max": float(it.max()),
        "mean": float(it.mean()),
        "e95": float(np.percentile(e, 95)),
        "emax": float(e.max()),
        "not_solved": int(np.sum(r["status"][g] != Status.SOLVED)),
    }


def _score(per_scenario: dict[str, dict[str, float]]) -> tuple[float, float]:
    """The selection rule: (worst p95 / target, total mean); inf if e_sub p95 >= 5 Nm."""
    if any(s["e95"] >= E_SUB_LIMIT for s in per_scenario.values()):
        return (np.inf, np.inf)
    worst = max(s["p95"] / TARGETS[n] for n, s in per_scenario.items())
    return (worst, sum(s["mean"] for s in per_scenario.values()))


def _fmt_stats(s: dict[str, float]) -> str:
    return (
        f"{s['p50']:.0f} / {s['p95']:.1f} / {s['max']:.0f}, {s['mean']:.1f}, "
        f"{s['e95']:.2f} / {s['emax']:.2f}"
    )


def _grid_points(grid: np.ndarray, relaxations: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Every (scale row, alpha): scales (A * G, n_rho) and alphas (A * G,), alpha-major."""
    scales = np.concatenate([grid] * len(relaxations))
    alphas = np.repeat(np.asarray(relaxations, float), len(grid))
    return scales, alphas


def sweep_example(example: str, args: argparse.Namespace) -> dict[str, Any]:
    names = EXAMPLES[example]
    logs = {}
    for n in names:
        t0 = time.perf_counter()
        logs[n] = logged_run(n, SMOKE_DURATION if args.smoke else None)
        print(f"[{n}: logged closed loop, {time.perf_counter() - t0:.1f} s]", file=sys.stderr)
    cfg0 = next(iter(logs.values()))[0]
    replays = Replays(cfg0, args.chunk)
    tol = cfg0.tol_primal  # the controller's eps_r = eps_s
    le_grid = np.array(list(itertools.product(args.le_grid, args.le_grid)))
    int_grid = np.array([[s] for s in args.int_grid])
    results: dict[str, Any] = {"le": {}, "int": {}}
    for kind, grid in (("le", le_grid), ("int", int_grid)):
        t0 = time.perf_counter()
        scales, alphas = _grid_points(grid, args.relaxations)
        per = {
            n: replays.run(log, kind, scales, alphas, np.full(len(alphas), tol), SWEEP_MAX_ITER)
            for n, (_, log) in logs.items()
        }
        for a, alpha in enumerate(args.relaxations):
            rows = []
            for g in range(len(grid)):
                ps = {n: stats(per[n], a * len(grid) + g) for n in names}
                rows.append((_score(ps), tuple(float(x) for x in grid[g]), ps))
            results[kind][alpha] = rows
        print(
            f"[{kind}: {len(alphas)} points x {len(names)} scenarios, "
            f"{time.perf_counter() - t0:.1f} s]",
            file=sys.stderr,
        )

    def best(kind: str, alpha: float) -> Any:
        return min(results[kind][alpha], key=lambda r: r[0])

    out: dict[str, Any] = {
        "scenarios": list(names),
        "steps": {n: int(np.shape(log.t)[0]) for n, (_, log) in logs.items()},
        "relaxations": list(args.relaxations),
        "le_grid": list(args.le_grid),
        "int_grid": list(args.int_grid),
        "best_per_relaxation": [],
        "paper": [],
    }
    head = " | ".join(f"{n}: it p50 / p95 / max, mean, e_sub p95 / max (Nm)" for n in names)
    print(f"\n### {example}: best rho scale per relaxation (tolerance 1 Nm^2, warm start)\n")
    print(f"| solver | alpha | rho scale | {head} |")
    print("| --- | --- | --- | " + " | ".join("---" for _ in names) + " |")
    for kind in ("le", "int"):
        for alpha in args.relaxations:
            sc, scale, ps = best(kind, alpha)
            label = "Local Explicit" if kind == "le" else "IntegratedADMM"
            cells = " | ".join(_fmt_stats(ps[n]) for n in names)
            print(f"| {label} | {alpha:g} | {scale} | {cells} |")
            out["best_per_relaxation"].append(
                {"solver": label, "alpha": alpha, "rho_scale": scale, "score": sc, "stats": ps}
            )
    for kind in ("le", "int"):
        rows = results[kind].get(1.0, [])
        unit = [r for r in rows if all(abs(x - 1.0) < 1e-12 for x in r[1])]
        if unit:
            cells = " | ".join(_fmt_stats(unit[0][2][n]) for n in names)
            label = "Local Explicit" if kind == "le" else "IntegratedADMM"
            print(f"| {label} (paper) | 1 | 1 | {cells} |")
            out["paper"].append({"solver": label, "score": unit[0][0], "stats": unit[0][2]})

    alpha_star = min(args.relaxations, key=lambda a: best("le", a)[0])
    le_best = best("le", alpha_star)
    int_best = best("int", alpha_star)
    int_any = min(((a, best("int", a)) for a in args.relaxations), key=lambda t: t[1][0])
    print(
        f"\nchosen for {example}: relaxation {alpha_star:g}, rho_scale {le_best[1]}, "
        f"integrated_rho_scale {int_best[1][0]:g}"
    )
    print(f"  Local Explicit score (worst p95/target, sum of means) {le_best[0]}")
    print(
        f"  IntegratedADMM score at alpha {alpha_star:g}: {int_best[0]}; its best over all "
        f"alphas: alpha {int_any[0]:g}, scale {int_any[1][1][0]:g}, score {int_any[1][0]}"
    )
    out["scores"] = {
        "local_explicit": le_best[0],
        "integrated_at_chosen_alpha": int_best[0],
        "integrated_best_any_alpha": {
            "alpha": int_any[0],
            "rho_scale": int_any[1][1][0],
            "score": int_any[1][0],
        },
    }

    # the chosen settings at looser tolerances and with an iteration budget
    print(f"\n### {example}: chosen Local Explicit settings, tolerance and budget\n")
    print(
        "| eps_r = eps_s (Nm^2) | max_iter | "
        + " | ".join(f"{n}: it p50 / p95 / max, mean, e_sub p95 / max" for n in names)
        + " |"
    )
    print("| --- | --- | " + " | ".join("---" for _ in names) + " |")
    tols = [1.0] if args.smoke else [1.0, 3.0, 10.0]
    cap = max(TARGETS[n] for n in names)
    scale = np.array([le_best[1]])
    budget = {}
    for n, (_, log) in logs.items():
        budget[n] = (
            replays.run(
                log,
                "le",
                np.repeat(scale, len(tols), 0),
                np.full(len(tols), alpha_star),
                np.asarray(tols),
                SWEEP_MAX_ITER,
            ),
            replays.run(log, "le", scale, np.array([alpha_star]), np.array([1.0]), cap),
        )
    out["budget"] = []
    for i, (t, m) in enumerate([(t, SWEEP_MAX_ITER) for t in tols] + [(1.0, cap)]):
        which, g = (0, i) if i < len(tols) else (1, 0)
        ps = {n: stats(budget[n][which], g) for n in names}
        print(f"| {t:g} | {m} | " + " | ".join(_fmt_stats(ps[n]) for n in names) + " |")
        out["budget"].append({"tol": t, "max_iter": m, "stats": ps})

    # the shadow: iterations to its tight tolerance
    print(f"\n### {example}: shadow IntegratedADMM at 1e-8 Nm^2\n")
    print(
        "| alpha | rho scale | "
        + " | ".join(
            f"{n}: it p50 / p95 / max, not solved, max deviation from the logged shadow (Nm)"
            for n in names
        )
        + " |"
    )
    print("| --- | --- | " + " | ".join("---" for _ in names) + " |")
    sh_alphas = sorted({1.0, alpha_star} if args.smoke else {1.0, alpha_star, 1.8})
    sgrid = np.array([[s] for s in SHADOW_GRID])
    scales, alphas = _grid_points(sgrid, tuple(sh_alphas))
    per = {
        n: replays.run(
            log, "int", scales, alphas, np.full(len(alphas), SHADOW_TOL), SHADOW_MAX_ITER
        )
        for n, (_, log) in logs.items()
    }
    shadow_rows = []
    out["shadow"] = []
    for g, (s, alpha) in enumerate(zip(scales[:, 0], alphas, strict=True)):
        cells, worst = [], 0.0
        ok = True
        cell_stats = {}
        for n in logs:
            st = stats(per[n], g)
            dev = float(np.nanmax(per[n]["e_sub"][g]))
            ok &= st["not_solved"] == 0
            worst = max(worst, st["p95"])
            cell_stats[n] = {**st, "max_deviation": dev}
            cells.append(
                f"{st['p50']:.0f} / {st['p95']:.0f} / {st['max']:.0f}, "
                f"{st['not_solved']}, {dev:.1e}"
            )
        shadow_rows.append((not ok, worst, float(alpha), float(s)))
        print(f"| {alpha:g} | {s:g} | " + " | ".join(cells) + " |")
        out["shadow"].append({"alpha": float(alpha), "rho_scale": float(s), "stats": cell_stats})
    sh = min(shadow_rows)
    print(
        f"\nshadow for {example}: relaxation {sh[2]:g}, rho scale {sh[3]:g} "
        f"(worst p95 {sh[1]:.0f} iterations, all solved: {not sh[0]})"
    )
    compiles = replays.compiles()
    print(
        f"\n[{example}: {replays.points // len(names)} parameter points x {len(names)} "
        f"scenario(s) replayed through "
        f"{sum(compiles.values())} compiled replays ("
        + ", ".join(f"{k}: {v}" for k, v in compiles.items())
        + ")]",
        flush=True,
    )
    out["compiles"] = compiles
    out["points_replayed_per_scenario"] = replays.points // len(names)
    chosen = {
        "relaxation": alpha_star,
        "rho_scale": le_best[1],
        "integrated_rho_scale": int_best[1][0],
        "shadow_relaxation": sh[2],
        "shadow_rho_scale": sh[3],
    }
    out["chosen"] = chosen
    return out


def cmd_sweep(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.smoke:  # one grid point each unless given
        args.chunk = SMOKE_CHUNK if args.chunk is None else args.chunk
        args.example = args.example or "cruise"
        args.relaxations = args.relaxations or (1.0,)
        args.le_grid = args.le_grid or (1.0,)
        args.int_grid = args.int_grid or (1.0,)
    else:
        args.chunk = CHUNK if args.chunk is None else args.chunk
        args.example = args.example or "all"
        args.relaxations = args.relaxations or RELAXATIONS
        args.le_grid = args.le_grid or LE_GRID
        args.int_grid = args.int_grid or INT_GRID
    args.relaxations = tuple(float(a) for a in args.relaxations)
    run = _meta.Run(_meta.output_path(args, STEM))
    chosen, per_example = {}, {}
    for ex in ("cruise", "stability") if args.example == "all" else (args.example,):
        per_example[ex] = sweep_example(ex, args)
        chosen[ex] = per_example[ex]["chosen"]
    print("\nsolver_defaults =", json.dumps(chosen, indent=1))
    run.results = {
        "smoke": args.smoke,
        "duration_s": SMOKE_DURATION if args.smoke else "each scenario's",
        "chunk": args.chunk,
        "examples": per_example,
        "solver_defaults": chosen,
    }
    run.finish()
    return 0


# --------------------------------------------------------------------------- table
def _runs(paths: list[str]) -> list[tuple[str, dict[str, Any]]]:
    """(name, metrics) of every run under ``paths``: ``DIR/metrics.json`` named
    ``DIR``, its ``DIR/baseline/metrics.json`` (``ampc simulate --compare``,
    ``ampc demo``) named ``DIR/baseline``; a directory without ``metrics.json``
    is expanded to its run directories."""
    out = []
    for p in map(Path, paths):
        runs = (
            [p]
            if (p / "metrics.json").exists()
            else sorted(q.parent for q in p.glob("*/metrics.json"))
        )
        for r in runs:
            out.append((r.name, json.loads((r / "metrics.json").read_text())))
            base = r / "baseline" / "metrics.json"
            if base.exists():
                out.append((f"{r.name}/baseline", json.loads(base.read_text())))
    return out


def _g(m: dict[str, Any], key: str, fmt: str = ".3g") -> str:
    v = m.get(key)
    return "-" if v is None else format(v, fmt)


def cmd_table(args: argparse.Namespace) -> int:
    runs = _runs(args.dirs)
    if not runs:
        print("no metrics.json found", file=sys.stderr)
        return 1
    print(
        "| run | objectives | tol | alpha / rho scale (LE; int.) / Anderson m | e_sub p95 / max (Nm) | "
        "iterations p50 / p95 / max | r_time median / p95 | t_LE / t_int median (us) | "
        "yaw rms whole / focus (rad/s) | rear abs slip max / p95 | x real time |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name, m in runs:
        active = m["formulation"] != "none"
        objs = "+".join(m["objectives"]) if active else m.get("no_mpc", "no MPC")
        solver = (
            f"{_g(m, 'relaxation', 'g')} / {m.get('rho_scale')}; "
            f"{_g(m, 'integrated_rho_scale', 'g')} / {m.get('anderson', 0)}"
            if active
            else "-"
        )
        print(
            f"| `{name}` | {objs} | {_g(m, 'tol_primal', 'g') if active else '-'} | {solver} | "
            f"{_g(m, 'e_sub_p95')} / {_g(m, 'e_sub_max')} | "
            f"{_g(m, 'iterations_p50', 'g')} / {_g(m, 'iterations_p95', 'g')} / "
            f"{_g(m, 'iterations_max', 'g')} | "
            f"{_g(m, 'r_time_median')} / {_g(m, 'r_time_p95')} | "
            f"{_g(m, 't_distributed_median_us', '.0f')} / {_g(m, 't_integrated_median_us', '.0f')} | "
            f"{_g(m, 'yaw_rms', '.4f')} / {_g(m, 'yaw_rms_focus', '.4f')} | "
            f"{_g(m, 'rear_slip_abs_max')} / {_g(m, 'rear_slip_abs_p95')} | "
            f"{_g(m, 'realtime_factor', '.0f')} |"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("sweep", help="choose rho_scale / relaxation per example")
    s.add_argument(
        "--example", choices=("cruise", "stability", "all"), help="default: all (--smoke: cruise)"
    )
    s.add_argument("--relaxations", type=float, nargs="+", help=f"default: {RELAXATIONS}")
    s.add_argument("--le-grid", type=float, nargs="+", help=f"default: {LE_GRID}")
    s.add_argument("--int-grid", type=float, nargs="+", help=f"default: {INT_GRID}")
    s.add_argument(
        "--chunk",
        type=int,
        help=f"parameter points vmapped together per call of a compiled replay "
        f"(default {CHUNK}; --smoke: {SMOKE_CHUNK})",
    )
    s.add_argument(
        "--smoke",
        action="store_true",
        help=f"a quick check of the same code: {SMOKE_DURATION:g} s of closed loop, "
        "one grid point (1) per grid and relaxation 1 unless given, cruise unless given; "
        "tolerance 1 only in the budget table, no alpha 1.8 in the shadow table; "
        "no result file unless --out",
    )
    _meta.add_out_argument(s, STEM)
    s.set_defaults(func=cmd_sweep)
    t = sub.add_parser("table", help="markdown table from ampc simulate outputs")
    t.add_argument("dirs", nargs="+")
    t.set_defaults(func=cmd_table)
    args = ap.parse_args(argv)
    if getattr(args, "chunk", None) is not None and args.chunk < 1:
        ap.error(f"--chunk: expected a positive integer, got {args.chunk}")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
