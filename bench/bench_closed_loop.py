"""Closed-loop solver tuning and metric tables (docs/results.md, "Solver tuning").

Two sub-commands:

``sweep``
    Chooses the per-example defaults of ``SimConfig.rho_scale``,
    ``relaxation`` and ``integrated_rho_scale`` (``simulation.CONTROLLER_DEFAULTS``).
    For every scenario of the example, one closed loop is run with the paper's
    solver (rho* unscaled, no over-relaxation) and its per-step
    :class:`ProblemData` and shadow optimum are logged. The logged steps are
    then replayed in order, each solve warm started from the replay's own
    shifted previous iterate (as in the loop), for every point of a grid:

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

``table DIR [DIR ...]``
    Prints the markdown table of docs/results.md from the ``metrics.json`` of
    ``ampc simulate`` runs (one directory per run; a directory holding run
    directories is expanded).

Run pinned to one core (batched XLA:CPU programs can deadlock on 2 cores)::

    timeout 3000 taskset -c 1 python bench/bench_closed_loop.py sweep
    python bench/bench_closed_loop.py sweep --smoke   # a quick check, 1 s of cruise
    timeout 60 taskset -c 1 python bench/bench_closed_loop.py table results/
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)

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
SMOKE_DURATION = 1.0  # s of closed loop in ``sweep --smoke``


# --------------------------------------------------------------------------- replay
def logged_run(name: str, duration: float | None = None) -> tuple[Any, Any]:
    """Closed loop of ``name`` with the paper's solver; returns (config, log as JAX arrays).

    ``duration``: simulated s (default: the scenario's).
    """
    import jax
    import jax.numpy as jnp

    from ampc_jax.simulation import PAPER_SOLVER_OPTIONS, config_for, simulate

    cfg = config_for(name, **PAPER_SOLVER_OPTIONS)
    res = simulate(name, cfg, duration=duration)
    return cfg, jax.tree.map(jnp.asarray, res.log)


def replay(
    config: Any,
    log: Any,
    scales: np.ndarray,
    relaxation: float,
    integrated: bool,
    tol: float | None = None,
    max_iter: int = 2000,
) -> dict[str, np.ndarray]:
    """Replay the logged steps in order for every row of ``scales`` (vmapped).

    Each step is solved from the replay's own shifted previous iterate (cold
    after a failed step), with rho = scale * rho* of that step. Returns
    ``iterations`` (G, K), ``e_sub`` (G, K * n_u) against the logged shadow
    optimum, and ``status`` (G, K).
    """
    import jax
    import jax.numpy as jnp

    from ampc_jax.formulations import LocalExplicit, cold_state, shift_state
    from ampc_jax.integrated import IntegratedADMM, merged_data, merged_topology
    from ampc_jax.simulation import _input_columns, build_topology

    T, agent_idx, _ = build_topology(config)
    tp = config.tol_primal if tol is None else tol
    td = config.tol_dual if tol is None else tol
    dt = log.data.A.dtype
    kw = dict(max_iter=max_iter, tol_primal=tp, tol_dual=td, relaxation=relaxation)
    if integrated:
        solver = IntegratedADMM(T, **kw)
        inner = solver.inner
        cold = cold_state(merged_topology(T), dt)

        def rho_star(d: Any) -> Any:
            return inner.setup(merged_data(d)).rho

    else:
        solver = LocalExplicit(T, **kw)
        cold = cold_state(T, dt)

        def rho_star(d: Any) -> Any:
            return solver.setup(d).rho

    def run(scale: Any) -> Any:
        def step(warm: Any, d: Any) -> Any:
            res = solver.solve(d, rho=rho_star(d) * scale, warm=warm)
            ok = (res.status <= 1) & jnp.all(jnp.isfinite(res.u0))
            new = jax.tree.map(lambda a, b: jnp.where(ok, a, b), shift_state(res.state), cold)
            if not config.warm_start:
                new = cold
            return new, (res.iterations, res.u0, res.status)

        _, out = jax.lax.scan(step, cold, log.data)
        return out

    it, u0, st = jax.jit(jax.vmap(run))(jnp.asarray(scales, dt))
    cols = _input_columns(config, agent_idx)
    ush = np.asarray(log.u_shadow)[:, cols]
    e = np.abs(np.asarray(u0) - ush[None])
    return {
        "iterations": np.asarray(it),
        "e_sub": e.reshape(e.shape[0], -1),
        "status": np.asarray(st),
        "u0": np.asarray(u0),
    }


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
        "not_solved": int(np.sum(r["status"][g] != 0)),
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


def sweep_example(example: str, args: argparse.Namespace) -> dict[str, Any]:
    names = EXAMPLES[example]
    logs = {}
    for n in names:
        t0 = time.perf_counter()
        logs[n] = logged_run(n, SMOKE_DURATION if args.smoke else None)
        print(f"[{n}: logged closed loop, {time.perf_counter() - t0:.1f} s]", file=sys.stderr)
    le_grid = np.array(list(itertools.product(args.le_grid, args.le_grid)))
    int_grid = np.array([[s] for s in args.int_grid])
    results: dict[str, Any] = {"le": {}, "int": {}}
    for alpha in args.relaxations:
        for kind, grid in (("le", le_grid), ("int", int_grid)):
            per = {
                n: replay(cfg, log, grid, alpha, kind == "int", max_iter=2000)
                for n, (cfg, log) in logs.items()
            }
            rows = []
            for g in range(len(grid)):
                ps = {n: stats(per[n], g) for n in names}
                rows.append((_score(ps), tuple(float(x) for x in grid[g]), ps))
            results[kind][alpha] = rows
            print(f"[{kind} alpha={alpha} done]", file=sys.stderr)

    def best(kind: str, alpha: float) -> Any:
        return min(results[kind][alpha], key=lambda r: r[0])

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
    for kind in ("le", "int"):
        rows = results[kind].get(1.0, [])
        unit = [r for r in rows if all(abs(x - 1.0) < 1e-12 for x in r[1])]
        if unit:
            cells = " | ".join(_fmt_stats(unit[0][2][n]) for n in names)
            label = "Local Explicit" if kind == "le" else "IntegratedADMM"
            print(f"| {label} (paper) | 1 | 1 | {cells} |")

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

    # the chosen settings at looser tolerances and with an iteration budget
    print(f"\n### {example}: chosen Local Explicit settings, tolerance and budget\n")
    print(
        "| eps_r = eps_s (Nm^2) | max_iter | "
        + " | ".join(f"{n}: it p50 / p95 / max, mean, e_sub p95 / max" for n in names)
        + " |"
    )
    print("| --- | --- | " + " | ".join("---" for _ in names) + " |")
    scale_row = np.array([le_best[1]])
    tols = [(1.0, 2000)] if args.smoke else [(1.0, 2000), (3.0, 2000), (10.0, 2000)]
    for tol, cap in tols + [(1.0, max(TARGETS[n] for n in names))]:
        cells = []
        for cfg, log in logs.values():
            r = replay(cfg, log, scale_row, alpha_star, False, tol=tol, max_iter=cap)
            cells.append(_fmt_stats(stats(r, 0)))
        print(f"| {tol:g} | {cap} | " + " | ".join(cells) + " |")

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
    shadow_rows = []
    sgrid = np.array([[s] for s in SHADOW_GRID])
    for alpha in sorted({1.0, alpha_star} if args.smoke else {1.0, alpha_star, 1.8}):
        per = {}
        for n, (cfg, log) in logs.items():
            r = replay(cfg, log, sgrid, alpha, True, tol=1e-8, max_iter=5000)
            per[n] = r
        for g, s in enumerate(SHADOW_GRID):
            cells, worst = [], 0.0
            ok = True
            for n in logs:
                st = stats(per[n], g)
                dev = float(np.nanmax(per[n]["e_sub"][g]))
                ok &= st["not_solved"] == 0
                worst = max(worst, st["p95"])
                cells.append(
                    f"{st['p50']:.0f} / {st['p95']:.0f} / {st['max']:.0f}, "
                    f"{st['not_solved']}, {dev:.1e}"
                )
            shadow_rows.append((not ok, worst, alpha, s))
            print(f"| {alpha:g} | {s:g} | " + " | ".join(cells) + " |")
    sh = min(shadow_rows)
    print(
        f"\nshadow for {example}: relaxation {sh[2]:g}, rho scale {sh[3]:g} "
        f"(worst p95 {sh[1]:.0f} iterations, all solved: {not sh[0]})"
    )
    return {
        "relaxation": alpha_star,
        "rho_scale": le_best[1],
        "integrated_rho_scale": int_best[1][0],
        "shadow_relaxation": sh[2],
        "shadow_rho_scale": sh[3],
    }


def cmd_sweep(args: argparse.Namespace) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.smoke:  # one grid point each unless given
        args.example = args.example or "cruise"
        args.relaxations = args.relaxations or (1.0,)
        args.le_grid = args.le_grid or (1.0,)
        args.int_grid = args.int_grid or (1.0,)
    else:
        args.example = args.example or "all"
        args.relaxations = args.relaxations or RELAXATIONS
        args.le_grid = args.le_grid or LE_GRID
        args.int_grid = args.int_grid or INT_GRID
    chosen = {}
    for ex in ("cruise", "stability") if args.example == "all" else (args.example,):
        chosen[ex] = sweep_example(ex, args)
    print("\nCONTROLLER_DEFAULTS =", json.dumps(chosen, indent=1))
    return 0


# --------------------------------------------------------------------------- table
def _runs(paths: list[str]) -> list[tuple[str, dict[str, Any]]]:
    out = []
    for p in map(Path, paths):
        files = (
            [p / "metrics.json"]
            if (p / "metrics.json").exists()
            else sorted(p.glob("*/metrics.json"))
        )
        for f in files:
            m = json.loads(f.read_text())
            if "LST+YRT" in m:  # ampc demo writes both runs
                out += [(f"{f.parent.name}/{k}", v) for k, v in m.items()]
            else:
                out.append((f.parent.name, m))
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
        objs = "+".join(m["objectives"]) if active else "driver alone"
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
        "--smoke",
        action="store_true",
        help=f"a quick check of the same code: {SMOKE_DURATION:g} s of closed loop, "
        "one grid point (1) per grid and relaxation 1 unless given, cruise unless given; "
        "tolerance 1 only in the budget table, no alpha 1.8 in the shadow table",
    )
    s.set_defaults(func=cmd_sweep)
    t = sub.add_parser("table", help="markdown table from ampc simulate outputs")
    t.add_argument("dirs", nargs="+")
    t.set_defaults(func=cmd_table)
    args = ap.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
