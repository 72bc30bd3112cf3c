"""Local Explicit speed against OSQP and Clarabel, measured in one run.

Problem: the paper's cruise-control model (3 states; agents DTR, RTV, FDB = 4
inputs; objectives LST, YRT), re-linearised at a different operating point for
every control step (time-varying: the model is rebuilt every step, as in the
vehicle examples), at N_p = 10 and 20.

1. Latency of one full control step (rebuild the model, prediction matrices,
   eq.opt_ro rho*, factorise, iterate to tolerance), compiled ahead of time,
   next to OSQP (update + solve, warm started, on the same integrated QP) and
   Clarabel (setup + solve), as ratios. The numpy condensing OSQP needs for a
   new model is timed separately.
2. Batched throughput (steps/s) of time-varying steps for batch sizes 1 to
   100,000 (vmapped, chunked to bound memory) against a Python loop over OSQP
   doing the same (condense + update + solve).
3. Compile times, separately.

Run: ``python bench/bench_local_explicit.py [--quick]``. Prints a table; also
writes ``bench/results_local_explicit.json`` (or ``--out``).
``--smoke``: a quick check of the same code (N_p = 10, float64, "tuned", 5
latency steps, batch 1 of 3-step drives, 1 OSQP drive); writes only to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

# One CPU device per core, so the batched part shards over both (set before JAX starts).
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + f" --xla_force_host_platform_device_count={os.cpu_count() or 1}"
    ).strip()

import jax
import jax.numpy as jnp
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)

jax.config.update("jax_enable_x64", True)

from ampc_jax.batch import map_scenarios  # noqa: E402
from ampc_jax.formulations import LocalExplicit, shift_state  # noqa: E402
from ampc_jax.integrated import (  # noqa: E402
    CondensedQP,
    OSQPReference,
    condensed_qp,
    solve_reference,
)
from ampc_jax.topology import Topology, make_data  # noqa: E402
from ampc_jax.vehicle import (  # noqa: E402
    CRUISE_AGENTS,
    CRUISE_C,
    CRUISE_GROUPS,
    CRUISE_OBJECTIVES,
    CruiseSettings,
    Measurement,
    VehicleParams,
    cruise_control_model,
)

PARAMS = VehicleParams()
TOL = 1e-6  # eps_r = eps_s on squared residual norms (Nm^2 scale)

# Solver configurations measured side by side. "paper": eq.opt_ro's rho* and
# the plain iteration. "tuned": rho_j = (1, 0.1) x rho* for (LST, YRT) and
# over-relaxation 1.6, chosen by ``--tune`` (a grid on training drives whose
# seeds differ from the measured ones; prints the grid).
# "tuned, eps 1e-3": the same at eps_r = eps_s = 1e-3 Nm^2, whose first-step
# error (printed) stays below OSQP's at its eps = 1e-6: a like-for-like accuracy.
# "+ Anderson 3": the same with Anderson acceleration of memory 3
# (``LocalExplicit.anderson``); "paper + Anderson 3" keeps eq.opt_ro's rho*.
CONFIGS = {
    "paper": {},
    "paper + Anderson 3": {"anderson": 3},
    "tuned": {"rho_scale": (1.0, 0.1), "relaxation": 1.6},
    "tuned + Anderson 3": {"rho_scale": (1.0, 0.1), "relaxation": 1.6, "anderson": 3},
    "tuned, eps 1e-3": {"rho_scale": (1.0, 0.1), "relaxation": 1.6, "tol": 1e-3},
}


def make_solver(T: Topology, config: str, tol: float = TOL) -> LocalExplicit:
    opts = dict(CONFIGS[config])
    tol = opts.pop("tol", tol)
    return LocalExplicit(T, max_iter=2000, tol_primal=tol, tol_dual=tol, **opts)


TUNE_SEEDS = range(1000, 1004)


# Groups derived from the model (agent i in S_j when C_j A^k B_(i) != 0): when
# cornering (yaw rate and v_y non-zero) RTV also moves v_x, so LST's group is
# {DTR, RTV, FDB}; YRT's is {RTV, FDB} as in the paper. With these groups the
# decomposition is exact and the first-step errors below are solver errors only
# (the paper's S_LST = {DTR, FDB} drops a weak coupling; see docs/results.md).
GROUPS = {"LST": ("DTR", "RTV", "FDB"), "YRT": CRUISE_GROUPS["YRT"]}


def topology(horizon: int) -> Topology:
    return Topology.build(
        n_x=3,
        horizon=horizon,
        agent_names=CRUISE_AGENTS,
        agent_sizes=(1, 1, 2),
        objective_names=CRUISE_OBJECTIVES,
        output_sizes=(1, 1),
        groups=[tuple(CRUISE_AGENTS.index(a) for a in GROUPS[o]) for o in CRUISE_OBJECTIVES],
    )


def drive(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A smooth sequence of operating points at 20 Hz (lane changes while the
    speed target moves): consecutive control steps are close, as in closed loop."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.05
    ph = rng.uniform(0, 2 * np.pi, 4)
    v = 15.0 + 4.0 * np.sin(0.3 * t + ph[0])
    steer = 0.05 * np.sin(1.2 * t + ph[1])
    r = v * steer / 2.85 / (1 + 0.0025 * v**2)
    return {
        "v_x": v,
        "v_y": -0.3 * np.sin(1.2 * t + ph[1]),
        "r": r,
        "steer": steer,
        "F_y": np.outer(2000.0 * np.sin(1.2 * t + ph[1]), np.ones(4)),
        "v_ref": v + 1.0 * np.sin(0.5 * t + ph[2]),
    }


def operating_points(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Random but plausible measurements (v_x 8..25 m/s, cornering), independent cases."""
    rng = np.random.default_rng(seed)
    return {
        "v_x": rng.uniform(8.0, 25.0, n),
        "v_y": rng.uniform(-0.5, 0.5, n),
        "r": rng.uniform(-0.4, 0.4, n),
        "steer": rng.uniform(-0.08, 0.08, n),
        "F_y": rng.uniform(-4000.0, 4000.0, (n, 4)),
        "v_ref": rng.uniform(8.0, 25.0, n),
    }


def make_step(solver: LocalExplicit, settings: CruiseSettings):
    T = solver.topology

    def data_of(op):
        z4 = jnp.zeros(4)
        meas = Measurement(
            v_x=op["v_x"],
            v_y=op["v_y"],
            yaw_rate=op["r"],
            omega=z4,
            F_x=z4,
            F_y=op["F_y"],
            F_z=z4,
            slip=z4,
            slip_angle=z4,
            a_x=0.0 * op["v_x"],
            a_y=0.0 * op["v_x"],
        )
        m = cruise_control_model(meas, op["steer"], op["v_ref"], 1.0, PARAMS, settings)
        C = tuple(jnp.asarray(CRUISE_C[o], float) for o in CRUISE_OBJECTIVES)
        data = make_data(
            T,
            A=m.A,
            B=m.B,
            w=m.w,
            x0=m.x0,
            C=C,
            Q=settings.Q(),
            ref=m.ref,
            R=settings.R(),
            lb=m.lb,
            ub=m.ub,
        )
        return jax.tree.map(lambda x: jnp.asarray(x, op["v_x"].dtype), data)

    def full(op):
        res = solver.solve(data_of(op))
        return res.u0, res.iterations

    return data_of, full


def index(ops, i):
    return {k: v[i] for k, v in ops.items()}


def median_time(fn, args_list, repeats=3):
    times = []
    for args in args_list:
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*args))
            best = min(best, time.perf_counter() - t0)
        times.append(best)
    return float(np.median(times))


def latency(horizon: int, n_steps: int, config: str = "tuned") -> dict:
    settings = CruiseSettings(horizon=horizon)
    T = topology(horizon)
    solver = make_solver(T, config)
    data_of, _ = make_step(solver, settings)
    ops = drive(n_steps, seed=horizon)
    op0 = index(ops, 0)

    def cold(op):
        return solver.solve(data_of(op))

    def warm(op, state):
        return solver.solve(data_of(op), None, shift_state(state))

    t0 = time.perf_counter()
    cold_c = jax.jit(cold).lower(op0).compile()
    compile_s = time.perf_counter() - t0
    first = cold_c(op0)
    warm_c = jax.jit(warm).lower(op0, first.state).compile()
    data_fn = jax.jit(data_of).lower(op0).compile()

    # Warm-started sequence (each step starts from the previous step's shifted iterate)
    states, res_warm, t_warm = [first.state], [], []
    for i in range(n_steps):
        op = index(ops, i)
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            r = jax.block_until_ready(warm_c(op, states[-1]))
            best = min(best, time.perf_counter() - t0)
        t_warm.append(best)
        res_warm.append(r)
        states.append(r.state)
    t_cold = median_time(cold_c, [(index(ops, i),) for i in range(n_steps)])
    it_cold = [int(cold_c(index(ops, i)).iterations) for i in range(n_steps)]
    it_warm = [int(r.iterations) for r in res_warm]

    datas = [data_fn(index(ops, i)) for i in range(n_steps)]
    cond_fn = jax.jit(lambda d: condensed_qp(T, d)).lower(datas[0]).compile()
    qps = [CondensedQP(*(np.asarray(x) for x in cond_fn(d))) for d in datas]
    t_condense = median_time(cond_fn, [(d,) for d in datas])
    ref = [solve_reference(T, d, "clarabel") for d in datas]
    t_clarabel = float(np.median([r.state for r in ref]))

    osqp = OSQPReference(T, datas[0], eps=1e-6)
    osqp.solve()
    t_osqp, err_osqp, err_jax = [], [], []
    for i in range(n_steps):
        t0 = time.perf_counter()
        osqp.update_qp(qps[i])
        res = osqp.solve()
        t_osqp.append(time.perf_counter() - t0)
        err_osqp.append(np.max(np.abs(res.u[0] - ref[i].u[0])))
        err_jax.append(np.max(np.abs(np.asarray(res_warm[i].u0) - ref[i].u[0])))
    t_osqp = float(np.median(t_osqp))
    t_jax = float(np.median(t_warm))
    return {
        "config": config,
        "horizon": horizon,
        "steps": n_steps,
        "jax_full_step_warm_us": t_jax * 1e6,
        "jax_full_step_cold_us": t_cold * 1e6,
        "jax_iterations_warm_median": float(np.median(it_warm)),
        "jax_iterations_warm_max": int(np.max(it_warm)),
        "jax_iterations_cold_median": float(np.median(it_cold)),
        "jax_compile_s": compile_s,
        "osqp_update_solve_us": t_osqp * 1e6,
        "condense_us": t_condense * 1e6,
        "clarabel_setup_solve_us": t_clarabel * 1e6,
        "ratio_jax_over_osqp": t_jax / t_osqp,
        "ratio_jax_over_osqp_with_condense": t_jax / (t_osqp + t_condense),
        "ratio_jax_over_clarabel": t_jax / t_clarabel,
        "max_u0_err_jax_Nm": float(np.max(err_jax)),
        "max_u0_err_osqp_Nm": float(np.max(err_osqp)),
    }


def throughput(
    horizon: int,
    sizes: list[int],
    chunk: int,
    osqp_runs: int,
    steps: int,
    config: str = "tuned",
    dtype: str = "float64",
    vmap_chunk: int = 32,
) -> dict:
    """B independent drives of ``steps`` control steps each (warm-started along
    each drive, model rebuilt every step), vmapped over B and scanned over steps;
    the peer runs the same drives through OSQP in a Python loop."""
    settings = CruiseSettings(horizon=horizon)
    T = topology(horizon)
    tol = TOL if dtype == "float64" else 1e-4  # float32 resolves about 1e-2 Nm
    solver = make_solver(T, config, tol)
    data_of, _ = make_step(solver, settings)

    def one_drive(ops):
        first = solver.solve(data_of(index(ops, 0)))

        def body(state, op):
            r = solver.solve(data_of(op), None, shift_state(state))
            return r.state, (r.u0, r.iterations)

        _, (u0, its) = jax.lax.scan(body, first.state, ops)
        return u0, its

    def drives(n: int, seed: int) -> dict[str, np.ndarray]:
        ds = [drive(steps, seed=seed + i) for i in range(n)]
        return {k: np.stack([d[k] for d in ds]).astype(dtype) for k in ds[0]}

    out = {
        "config": config,
        "dtype": dtype,
        "horizon": horizon,
        "devices": len(jax.devices()),
        "vmap_chunk": vmap_chunk,
        "chunk": chunk,
        "steps_per_drive": steps,
        "jax_steps_per_s": {},
        "compile_s": {},
        "iterations_mean": {},
    }

    def batched(ops):
        # chunks of vmap_chunk drives, each chunk stopping at its own slowest case,
        # the batch split over all devices (ampc_jax.batch)
        return map_scenarios(one_drive, ops, chunk=vmap_chunk)

    compiled = {}
    for n in sizes:
        b = min(n, chunk)
        ops = drives(min(n, chunk), seed=n)  # one chunk of drives, reused for every chunk
        if b not in compiled:
            t0 = time.perf_counter()
            compiled[b] = jax.jit(batched).lower(ops).compile()
            out["compile_s"][b] = time.perf_counter() - t0
        fn = compiled[b]
        _, its = jax.block_until_ready(fn(ops))
        t0 = time.perf_counter()
        for _ in range(max(1, n // b)):
            jax.block_until_ready(fn(ops))
        dt = time.perf_counter() - t0
        out["jax_steps_per_s"][n] = max(1, n // b) * b * (steps + 1) / dt
        out["iterations_mean"][n] = float(np.mean(its))
        print(
            f"  N_p={horizon} {dtype} batch {n:>6}: {out['jax_steps_per_s'][n]:10.0f} steps/s "
            f"(mean iterations {out['iterations_mean'][n]:.0f})",
            flush=True,
        )

    # The same drives through OSQP in a Python loop: new model -> condense -> update -> solve
    data_fn = jax.jit(data_of)
    cond = jax.jit(lambda op: condensed_qp(T, data_of(op)))
    ops = {k: v.astype(np.float64) for k, v in drives(osqp_runs, seed=12345).items()}
    osqp = OSQPReference(T, data_fn(index(index(ops, 0), 0)), eps=1e-6)
    jax.block_until_ready(cond(index(index(ops, 0), 0)))
    t_with = t_without = 0.0
    for k in range(osqp_runs):
        run = index(ops, k)
        qps = []
        t0 = time.perf_counter()
        for i in range(steps):
            qp = CondensedQP(*(np.asarray(x) for x in cond(index(run, i))))
            qps.append(qp)
            osqp.update_qp(qp)
            osqp.solve()
        t_with += time.perf_counter() - t0
        t0 = time.perf_counter()
        for qp in qps:
            osqp.update_qp(qp)
            osqp.solve()
        t_without += time.perf_counter() - t0
    out["osqp_loop_steps_per_s"] = osqp_runs * steps / t_with
    out["osqp_loop_steps_per_s_without_condense"] = osqp_runs * steps / t_without
    best = max(out["jax_steps_per_s"].values())
    out["ratio_best_jax_over_osqp_loop"] = best / out["osqp_loop_steps_per_s"]
    out["ratio_best_jax_over_osqp_loop_without_condense"] = (
        best / out["osqp_loop_steps_per_s_without_condense"]
    )
    return out


def tune(horizon: int, n_steps: int = 40) -> dict:
    """Grid over rho_scale (per objective) and relaxation on training drives.

    The drives' seeds (``TUNE_SEEDS``) differ from the measured ones, so the
    chosen configuration is not fitted to the benchmark's own data.
    """
    settings = CruiseSettings(horizon=horizon)
    T = topology(horizon)
    grid = []
    for a in (0.3, 1.0, 3.0):
        for b in (0.03, 0.1, 0.3, 1.0):
            for alpha in (1.0, 1.6):
                grid.append(((a, b), alpha))
    base = LocalExplicit(T, max_iter=3000, tol_primal=TOL, tol_dual=TOL)
    data_of, _ = make_step(base, settings)
    data_fn = jax.jit(data_of)
    datas = [data_fn(index(drive(n_steps, seed=s), i)) for s in TUNE_SEEDS for i in range(n_steps)]
    out = {}
    print(f"N_p={horizon}: median warm iterations on training drives (seeds {list(TUNE_SEEDS)})")
    for scale, alpha in grid:
        solver = LocalExplicit(
            T, max_iter=3000, tol_primal=TOL, tol_dual=TOL, rho_scale=scale, relaxation=alpha
        )
        cold = jax.jit(solver.solve)
        warm = jax.jit(lambda d, st, solver=solver: solver.solve(d, None, shift_state(st)))
        its, state = [], None
        for k, d in enumerate(datas):
            r = cold(d) if k % n_steps == 0 else warm(d, state)
            state = r.state
            if k % n_steps:
                its.append(int(r.iterations))
        out[f"{scale}, {alpha}"] = float(np.median(its))
        print(f"  rho_scale {scale}, relaxation {alpha}: {np.median(its):.0f}", flush=True)
    best = min(out, key=out.get)
    print(f"  best: {best} ({out[best]:.0f} iterations)")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke run)")
    ap.add_argument(
        "--smoke",
        action="store_true",
        help="smallest sizes, a quick check of the code (N_p = 10, float64, 'tuned' unless "
        "given; 5 latency steps, batch 1, 3-step drives); writes JSON only with --out",
    )
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="the results JSON (default bench/results_local_explicit[_SUFFIX].json)",
    )
    ap.add_argument(
        "--chunk", type=int, default=8192, help="drives per compiled call (memory bound)"
    )
    ap.add_argument(
        "--vmap-chunk", type=int, default=32, help="drives vmapped together (ampc_jax.batch)"
    )
    ap.add_argument(
        "--max-batch", type=int, default=100_000, help="largest batch size (default 100,000)"
    )
    ap.add_argument("--tune", action="store_true", help="only run the rho_scale/relaxation grid")
    ap.add_argument("--only", choices=("latency", "throughput"), help="run one of the two parts")
    ap.add_argument(
        "--horizons", default=None, help="comma-separated N_p values (default 10,20; --smoke 10)"
    )
    ap.add_argument(
        "--dtypes",
        default=None,
        help="throughput dtypes (default float64,float32; --smoke float64)",
    )
    ap.add_argument(
        "--configs",
        default=None,
        help="comma-separated names from CONFIGS for the latency part "
        "(default: all; --smoke: tuned)",
    )
    ap.add_argument(
        "--sync-dispatch",
        action="store_true",
        help="run JAX's CPU client synchronously (jax_cpu_enable_async_dispatch=False), "
        "as a single-device controller can; the latency part only",
    )
    ap.add_argument(
        "--throughput-config",
        default="tuned",
        choices=list(CONFIGS),
        help="the configuration of the throughput part",
    )
    args = ap.parse_args(argv)
    if args.horizons is None:
        args.horizons = "10" if args.smoke else "10,20"
    if args.dtypes is None:
        args.dtypes = "float64" if args.smoke else "float64,float32"
    if args.configs is None and args.smoke:
        args.configs = "tuned"
    if args.sync_dispatch:
        if args.only != "latency":
            ap.error(
                "--sync-dispatch: with --only latency (it would serialise the sharded batches)"
            )
        # read when JAX creates its CPU client, so before the first computation
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    configs = list(CONFIGS) if args.configs is None else args.configs.split(",")
    for name in configs:
        if name not in CONFIGS:
            ap.error(f"--configs: unknown configuration {name!r}; expected one of {list(CONFIGS)}")
    if args.tune:
        for horizon in (10, 20):
            tune(horizon)
        return 0
    steps = 5 if args.smoke else 50 if args.quick else 200
    if args.smoke:
        sizes = [1]
    elif args.quick:
        sizes = [1, 10, 100, 1000]
    else:
        sizes = [1, 10, 100, 1000, 10_000, 100_000]
    sizes = [n for n in sizes if n <= args.max_batch]
    results = {
        "jax": jax.__version__,
        "devices": str(jax.devices()),
        "dispatch": "synchronous" if args.sync_dispatch else "asynchronous (JAX's default)",
        "configs": {k: {kk: str(v) for kk, v in c.items()} for k, c in CONFIGS.items()},
        "latency": [],
        "throughput": [],
    }
    print(
        f"jax {jax.__version__} on {jax.devices()}; tolerance eps_r = eps_s = {TOL}; "
        f"dispatch {results['dispatch']}"
    )
    print(f"configurations: {CONFIGS}")
    horizons = [int(h) for h in args.horizons.split(",")]
    dtypes = args.dtypes.split(",")
    for horizon in horizons if args.only != "throughput" else ():
        for config in configs:
            lat = latency(horizon, steps, config)
            results["latency"].append(lat)
            print(
                f"N_p={horizon} [{config}]: full step warm {lat['jax_full_step_warm_us']:.0f} us "
                f"(iterations median {lat['jax_iterations_warm_median']:.0f}, max {lat['jax_iterations_warm_max']}), "
                f"cold {lat['jax_full_step_cold_us']:.0f} us ({lat['jax_iterations_cold_median']:.0f} it.), "
                f"OSQP update+solve {lat['osqp_update_solve_us']:.0f} us "
                f"(+ condense {lat['condense_us']:.0f} us), Clarabel {lat['clarabel_setup_solve_us']:.0f} us"
            )
            print(
                f"        ratio JAX/OSQP {lat['ratio_jax_over_osqp']:.2f} "
                f"(vs OSQP incl. condensing {lat['ratio_jax_over_osqp_with_condense']:.2f}), "
                f"JAX/Clarabel {lat['ratio_jax_over_clarabel']:.2f}; "
                f"max |u0 - Clarabel|: JAX {lat['max_u0_err_jax_Nm']:.2e} Nm, "
                f"OSQP {lat['max_u0_err_osqp_Nm']:.2e} Nm; compile {lat['jax_compile_s']:.2f} s",
                flush=True,
            )
    for dtype in dtypes if args.only != "latency" else ():
        for horizon in horizons:
            thr = throughput(
                horizon,
                sizes,
                args.chunk,
                1 if args.smoke else 5 if args.quick else 20,
                3 if args.smoke else 9,
                config=args.throughput_config,
                dtype=dtype,
                vmap_chunk=args.vmap_chunk,
            )
            results["throughput"].append(thr)
            print(
                f"N_p={horizon} {dtype} [{args.throughput_config}]: OSQP Python loop {thr['osqp_loop_steps_per_s']:.0f} steps/s "
                f"({thr['osqp_loop_steps_per_s_without_condense']:.0f} without condensing); "
                f"best JAX batch / OSQP loop = {thr['ratio_best_jax_over_osqp_loop']:.1f}x "
                f"({thr['ratio_best_jax_over_osqp_loop_without_condense']:.1f}x without condensing); "
                f"compile {thr['compile_s']}",
                flush=True,
            )
    suffix = f"_{args.only}" if args.only else ""
    if args.horizons != "10,20" or args.dtypes != "float64,float32":
        suffix += "_" + args.horizons.replace(",", "-") + "_" + args.dtypes.replace(",", "-")
    if args.throughput_config != "tuned" and args.only != "latency":
        suffix += "_" + args.throughput_config.replace(" + ", "_").replace(" ", "_")
    path = args.out or Path(__file__).with_name(f"results_local_explicit{suffix}.json")
    if args.smoke and args.out is None:
        print("smoke run: results not written (--out PATH writes them)")
        return 0
    path.write_text(json.dumps(results, indent=1, default=str))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
