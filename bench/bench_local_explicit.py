"""Local Explicit speed against OSQP and Clarabel, measured in one run.

Problem: the paper's cruise-control model (3 states; agents DTR, RTV, FDB = 4
inputs; objectives LST, YRT), re-linearised at a different operating point for
every control step (time-varying: the model is rebuilt every step, as in the
vehicle examples), at N_p = 10 and 20.

1. Latency of one full control step (rebuild the model, prediction matrices,
   eq.opt_ro rho*, factorise, iterate to tolerance), compiled ahead of time,
   next to OSQP (update + solve, warm started, on the same integrated QP) and
   Clarabel (setup + solve), as ratios, with each solver's first-step error
   against Clarabel at 1e-9 printed beside its time. The numpy condensing OSQP
   needs for a new model is timed separately. The solvers take turns at every
   step of the drive (Local Explicit warm and cold, OSQP, Clarabel), so a
   slower stretch of a shared machine hits all of them; Local Explicit's time
   is the best of 3 identical calls (the call is pure), OSQP's and Clarabel's
   one call (OSQP's internal warm start makes a repeat an easier solve).
   Medians over the steps.
2. Batched throughput (steps/s) of time-varying steps for batch sizes 1 to
   100,000 (vmapped, chunked to bound memory, ``ampc_jax.batch``) against a
   Python loop over OSQP doing the same (condense + update + solve), on the
   same cores: JAX gets one CPU device per core of this process's affinity.
   The OSQP loop runs once after every batch size (its median is the peer's
   figure), so that both sides sample the same stretch of a shared machine.
3. Compile times, separately.

Solver configurations (``CONFIGS``): one compiled solver per set of static
options (``SOLVERS``: plain ADMM, Anderson memory 3), each configuration a
:class:`~ampc_jax.admm.SolverParams` point of it, an argument of the compiled
step (so the five configurations compile two programs per horizon; the script
prints the counts). "paper": eq.opt_ro's rho* and the plain iteration.
"tuned": rho_j = (1, 0.1) x rho* for (LST, YRT) and over-relaxation 1.6,
chosen by ``--tune`` (a grid on training drives whose seeds differ from the
measured ones; prints the grid). "tuned, eps 1e-3": the same at eps_r = eps_s
= 1e-3 Nm^2, whose first-step error (printed) stays below OSQP's at its eps =
1e-6: a like-for-like accuracy. "+ Anderson 3": with Anderson acceleration of
memory 3.

Run on one core (timings are per core; OSQP is single-threaded)::

    taskset -c 1 python bench/bench_local_explicit.py [--only latency|throughput]
    python bench/bench_local_explicit.py --smoke   # no result file unless --out

``--smoke``: a quick check of the same code (N_p = 10, float64, "tuned", 5
latency steps, batch 1 of 3-step drives, 1 OSQP drive). Result file:
``bench/results/bench_local_explicit.json`` (``--out``; ``bench/_meta.py``); a
partial run (``--only``, ``--horizons``, ``--max-batch``) replaces it too, and
its recorded command line says what it holds. ``--tune`` writes only to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

# One CPU device per core this process may run on (``taskset -c 1``: one), so the
# batched part shards over them (set before JAX starts).
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + " --xla_force_host_platform_device_count="
        + str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
    ).strip()

import _meta  # bench/_meta.py, beside this script
import jax
import jax.numpy as jnp
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)

jax.config.update("jax_enable_x64", True)

from ampc_jax.batch import map_scenarios  # noqa: E402
from ampc_jax.formulations import LocalExplicit  # noqa: E402
from ampc_jax.problem import CondensedQP, Topology, condensed_qp, make_data  # noqa: E402
from ampc_jax.reference import OSQPReference, solve_reference  # noqa: E402
from ampc_jax.vehicle import CRUISE, CruiseSettings, Measurement, VehicleParams  # noqa: E402
from ampc_jax.vehicle.cruise import cruise_control_model  # noqa: E402

STEM = "bench_local_explicit"
PARAMS = VehicleParams()
TOL = 1e-6  # eps_r = eps_s on squared residual norms (Nm^2 scale)
MAX_ITER = 2000

# Static option sets: one compiled program each (per horizon and dtype).
SOLVERS = {"plain": {}, "Anderson 3": {"anderson": 3}}
# Configurations: (static option set, SolverParams point); see the module docstring.
TUNED = {"rho": (1.0, 0.1), "relaxation": 1.6}
CONFIGS = {
    "paper": ("plain", {}),
    "paper + Anderson 3": ("Anderson 3", {}),
    "tuned": ("plain", TUNED),
    "tuned + Anderson 3": ("Anderson 3", TUNED),
    "tuned, eps 1e-3": ("plain", {**TUNED, "tol": 1e-3}),
}


def make_solver(T: Topology, config: str) -> LocalExplicit:
    return LocalExplicit(T, max_iter=MAX_ITER, **SOLVERS[CONFIGS[config][0]])


def make_params(solver: LocalExplicit, config: str, tol: float = TOL, dtype=None):
    opts = dict(CONFIGS[config][1])
    tol = opts.pop("tol", tol)
    return solver.params(**opts, tol_primal=tol, tol_dual=tol, dtype=dtype)


TUNE_SEEDS = range(1000, 1004)
C_ROWS = tuple(jnp.asarray(CRUISE.outputs[o], float) for o in CRUISE.objectives)


# Groups derived from the model (agent i in S_j when C_j A^k B_(i) != 0): when
# cornering (yaw rate and v_y non-zero) RTV also moves v_x, so LST's group is
# {DTR, RTV, FDB}; YRT's is {RTV, FDB} as in the paper. With these groups the
# decomposition is exact and the first-step errors below are solver errors only
# (the paper's S_LST = {DTR, FDB} drops a weak coupling; see docs/results.md).
GROUPS = {"LST": ("DTR", "RTV", "FDB"), "YRT": CRUISE.groups["YRT"]}


def topology(horizon: int) -> Topology:
    agents = CRUISE.agents
    return Topology.build(
        n_x=CRUISE.n_x,
        horizon=horizon,
        agent_names=agents,
        agent_sizes=CRUISE.agent_sizes,
        objective_names=CRUISE.objectives,
        output_sizes=tuple(len(CRUISE.outputs[o]) for o in CRUISE.objectives),
        groups=[tuple(agents.index(a) for a in GROUPS[o]) for o in CRUISE.objectives],
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


def make_data_of(T: Topology, settings: CruiseSettings, **rows):
    """op (one operating point) -> the step's ProblemData (jittable); ``rows``: general
    rows ``G``, ``g`` passed on to make_data (bench_peers.py)."""

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
        data = make_data(
            T,
            A=m.A,
            B=m.B,
            w=m.w,
            x0=m.x0,
            C=C_ROWS,
            Q=settings.Q(),
            ref=m.ref,
            R=settings.R(),
            lb=m.lb,
            ub=m.ub,
            **rows,
        )
        return jax.tree.map(lambda x: jnp.asarray(x, op["v_x"].dtype), data)

    return data_of


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


def latency(horizon: int, n_steps: int, configs: list[str]) -> tuple[list[dict], dict]:
    """One row per configuration; and the compile counts and times of the
    static option sets used (each compiled once for every configuration)."""
    settings = CruiseSettings(horizon=horizon)
    T = topology(horizon)
    data_of = make_data_of(T, settings)
    ops = drive(n_steps, seed=horizon)
    op0 = index(ops, 0)
    data_fn = jax.jit(data_of).lower(op0).compile()
    datas = [data_fn(index(ops, i)) for i in range(n_steps)]
    cond_fn = jax.jit(lambda d: condensed_qp(T, d)).lower(datas[0]).compile()
    qps = [CondensedQP(*(np.asarray(x) for x in cond_fn(d))) for d in datas]
    t_condense = median_time(cond_fn, [(d,) for d in datas])

    programs: dict[str, dict] = {}  # static option set -> its compiled steps

    def program(key: str, solver: LocalExplicit, params) -> dict:
        if key not in programs:
            # the result's duality gap (stats.gap) is left out of the timed step,
            # as from OSQP's: a controller that does not read it does not compute it
            # (XLA drops it), and it costs about 15 us of the 210 us step at N_p = 10
            def cold(op, p):
                return solver.solve(data_of(op), p)._replace(stats=None)

            def warm(op, p, state):
                return solver.solve(data_of(op), p, solver.shift(state))._replace(stats=None)

            # ahead-of-time compiled: every configuration of this option set calls
            # these two programs with its own SolverParams (``programs`` counts them)
            t0 = time.perf_counter()
            cold_c = jax.jit(cold).lower(op0, params).compile()
            compile_s = time.perf_counter() - t0
            first = cold_c(op0, params)
            warm_c = jax.jit(warm).lower(op0, params, first.state).compile()
            programs[key] = {"cold": cold_c, "warm": warm_c, "programs": 2, "compile_s": compile_s}
        return programs[key]

    rows = []
    for config in configs:
        solver = make_solver(T, config)
        params = make_params(solver, config)
        prog = program(CONFIGS[config][0], solver, params)
        cold_c, warm_c = prog["cold"], prog["warm"]
        first = cold_c(op0, params)
        osqp = OSQPReference(T, datas[0], eps=1e-6)
        osqp.solve()
        # The drive in order, every solver in turn at every step: Local Explicit
        # warm started from its previous step's shifted iterate and cold, OSQP
        # (update + solve, warm started internally), Clarabel (setup + solve, the
        # reference optimum)
        states, it_warm, it_cold = [first.state], [], []
        t_warm, t_cold, t_osqp, t_clarabel, err_osqp, err_jax = [], [], [], [], [], []
        for i in range(n_steps):
            op = index(ops, i)
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                r = jax.block_until_ready(warm_c(op, params, states[-1]))
                best = min(best, time.perf_counter() - t0)
            t_warm.append(best)
            it_warm.append(int(r.iterations))
            states.append(r.state)
            best = np.inf
            for _ in range(3):
                t0 = time.perf_counter()
                rc = jax.block_until_ready(cold_c(op, params))
                best = min(best, time.perf_counter() - t0)
            t_cold.append(best)
            it_cold.append(int(rc.iterations))
            t0 = time.perf_counter()
            osqp.update_qp(qps[i])
            res = osqp.solve()
            t_osqp.append(time.perf_counter() - t0)
            ref = solve_reference(T, datas[i], "clarabel")
            t_clarabel.append(ref.stats.solve_time)  # its setup + solve, timed inside
            err_osqp.append(np.max(np.abs(res.u[0] - ref.u[0])))
            err_jax.append(np.max(np.abs(np.asarray(r.u0) - ref.u[0])))
        t_osqp_med = float(np.median(t_osqp))
        t_jax = float(np.median(t_warm))
        rows.append(
            {
                "config": config,
                "solver": CONFIGS[config][0],
                "params": {
                    k: list(v) if isinstance(v, tuple) else v for k, v in CONFIGS[config][1].items()
                },
                "horizon": horizon,
                "steps": n_steps,
                "jax_full_step_warm_us": t_jax * 1e6,
                "jax_full_step_cold_us": float(np.median(t_cold)) * 1e6,
                "jax_iterations_warm_median": float(np.median(it_warm)),
                "jax_iterations_warm_max": int(np.max(it_warm)),
                "jax_iterations_cold_median": float(np.median(it_cold)),
                "jax_compile_s": prog["compile_s"],
                "osqp_update_solve_us": t_osqp_med * 1e6,
                "condense_us": t_condense * 1e6,
                "clarabel_setup_solve_us": float(np.median(t_clarabel)) * 1e6,
                "ratio_jax_over_osqp": t_jax / t_osqp_med,
                "ratio_jax_over_osqp_with_condense": t_jax / (t_osqp_med + t_condense),
                "ratio_jax_over_clarabel": t_jax / float(np.median(t_clarabel)),
                "max_u0_err_jax_Nm": float(np.max(err_jax)),
                "max_u0_err_osqp_Nm": float(np.max(err_osqp)),
            }
        )
    compiles = {
        key: {"programs": p["programs"], "compile_s": p["compile_s"]} for key, p in programs.items()
    }
    return rows, compiles


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
    solver = make_solver(T, config)
    params = make_params(solver, config, tol, dtype=dtype)
    data_of = make_data_of(T, settings)

    def one_drive(case):
        ops, p = case
        first = solver.solve(data_of(index(ops, 0)), p)

        def body(state, op):
            r = solver.solve(data_of(op), p, solver.shift(state))
            return r.state, (r.u0, r.iterations)

        _, (u0, its) = jax.lax.scan(body, first.state, ops)
        return u0, its

    def drives(n: int, seed: int) -> dict[str, np.ndarray]:
        ds = [drive(steps, seed=seed + i) for i in range(n)]
        return {k: np.stack([d[k] for d in ds]).astype(dtype) for k in ds[0]}

    out = {
        "config": config,
        "dtype": dtype,
        "tolerance": tol,
        "horizon": horizon,
        "devices": len(jax.devices()),
        "vmap_chunk": vmap_chunk,
        "chunk": chunk,
        "steps_per_drive": steps,
        "jax_steps_per_s": {},
        "jax_cases_timed": {},
        "compile_s": {},
        "iterations_mean": {},
    }

    def batched(ops, p):
        # chunks of vmap_chunk drives, each chunk stopping at its own slowest case,
        # the batch split over all devices (ampc_jax.batch); the parameters go with
        # every case (broadcast), an argument of the one compiled program
        n = next(iter(ops.values())).shape[0]
        pb = jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *x.shape)), p)
        return map_scenarios(one_drive, (ops, pb), chunk=vmap_chunk)

    # The peer: the same kind of drives through OSQP in a Python loop (new model ->
    # condense -> update -> solve), timed after every batch size, so that its
    # runs spread over the JAX runs' time on a shared machine; median over them
    data_fn = jax.jit(data_of)
    cond = jax.jit(lambda op: condensed_qp(T, data_of(op)))
    osqp_ops = {k: v.astype(np.float64) for k, v in drives(osqp_runs, seed=12345).items()}
    osqp = OSQPReference(T, data_fn(index(index(osqp_ops, 0), 0)), eps=1e-6)
    jax.block_until_ready(cond(index(index(osqp_ops, 0), 0)))

    def osqp_loop() -> tuple[float, float]:
        """(steps/s with condensing, without) of one pass over the OSQP drives."""
        t_with = t_without = 0.0
        for k in range(osqp_runs):
            run = index(osqp_ops, k)
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
        return osqp_runs * steps / t_with, osqp_runs * steps / t_without

    batched_jit = jax.jit(batched)
    compiled = {}  # chunk size b -> its ahead-of-time compiled program
    osqp_passes = []
    for n in sizes:
        b = min(n, chunk)
        ops = drives(b, seed=n)  # one chunk of drives, reused for every chunk
        if b not in compiled:
            t0 = time.perf_counter()
            compiled[b] = batched_jit.lower(ops, params).compile()
            out["compile_s"][b] = time.perf_counter() - t0
        fn = compiled[b]
        _, its = jax.block_until_ready(fn(ops, params))
        calls = max(1, n // b)
        t0 = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(fn(ops, params))
        dt = time.perf_counter() - t0
        out["jax_cases_timed"][n] = calls * b
        out["jax_steps_per_s"][n] = calls * b * (steps + 1) / dt
        out["iterations_mean"][n] = float(np.mean(its))
        osqp_passes.append(osqp_loop())
        print(
            f"  N_p={horizon} {dtype} batch {n:>6}: {out['jax_steps_per_s'][n]:10.0f} steps/s "
            f"(mean iterations {out['iterations_mean'][n]:.0f}); OSQP loop right after: "
            f"{osqp_passes[-1][0]:.0f} steps/s",
            flush=True,
        )
    out["osqp_loop_passes_steps_per_s"] = [p[0] for p in osqp_passes]
    out["osqp_loop_steps_per_s"] = float(np.median([p[0] for p in osqp_passes]))
    out["osqp_loop_steps_per_s_without_condense"] = float(np.median([p[1] for p in osqp_passes]))
    best = max(out["jax_steps_per_s"].values())
    out["ratio_best_jax_over_osqp_loop"] = best / out["osqp_loop_steps_per_s"]
    out["ratio_best_jax_over_osqp_loop_without_condense"] = (
        best / out["osqp_loop_steps_per_s_without_condense"]
    )
    out["programs_compiled"] = len(compiled)  # one per distinct chunk size b
    return out


def tune(horizon: int, n_steps: int = 40) -> dict:
    """Grid over rho (factor per objective) and relaxation on training drives.

    The drives' seeds (``TUNE_SEEDS``) differ from the measured ones, so the
    chosen configuration is not fitted to the benchmark's own data. Every grid
    point is a SolverParams point of one compiled cold and one warm step.
    """
    settings = CruiseSettings(horizon=horizon)
    T = topology(horizon)
    grid = []
    for a in (0.3, 1.0, 3.0):
        for b in (0.03, 0.1, 0.3, 1.0):
            for alpha in (1.0, 1.6):
                grid.append(((a, b), alpha))
    solver = LocalExplicit(T, max_iter=3000)
    data_fn = jax.jit(make_data_of(T, settings))
    datas = [data_fn(index(drive(n_steps, seed=s), i)) for s in TUNE_SEEDS for i in range(n_steps)]
    cold = jax.jit(solver.solve)
    warm = jax.jit(lambda d, p, st: solver.solve(d, p, solver.shift(st)))
    out = {}
    print(f"N_p={horizon}: median warm iterations on training drives (seeds {list(TUNE_SEEDS)})")
    for scale, alpha in grid:
        p = solver.params(rho=scale, relaxation=alpha, tol_primal=TOL, tol_dual=TOL)
        its, state = [], None
        for k, d in enumerate(datas):
            r = cold(d, p) if k % n_steps == 0 else warm(d, p, state)
            state = r.state
            if k % n_steps:
                its.append(int(r.iterations))
        out[f"{scale}, {alpha}"] = float(np.median(its))
        print(f"  rho_scale {scale}, relaxation {alpha}: {np.median(its):.0f}", flush=True)
    best = min(out, key=out.get)
    print(f"  best: {best} ({out[best]:.0f} iterations)")
    print(
        f"  [compiled: cold step {cold._cache_size()}, warm step {warm._cache_size()} "
        f"for {len(grid)} grid points]"
    )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (50 steps, batch <= 1000)")
    ap.add_argument(
        "--smoke",
        action="store_true",
        help="smallest sizes, a quick check of the code (N_p = 10, float64, 'tuned' unless "
        "given; 5 latency steps, batch 1, 3-step drives); no result file unless --out",
    )
    _meta.add_out_argument(ap, STEM)
    ap.add_argument(
        "--chunk", type=int, default=8192, help="drives per compiled call (memory bound)"
    )
    ap.add_argument(
        "--vmap-chunk", type=int, default=32, help="drives vmapped together (ampc_jax.batch)"
    )
    ap.add_argument(
        "--max-batch", type=int, default=100_000, help="largest batch size (default 100,000)"
    )
    ap.add_argument("--tune", action="store_true", help="only run the rho/relaxation grid")
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
        run = _meta.Run(args.out)  # the grid is its own experiment: written only with --out
        run.results = {"tune": {h: tune(h) for h in (10, 20)}}
        run.finish()
        return 0
    run = _meta.Run(_meta.output_path(args, STEM))
    steps = 5 if args.smoke else 50 if args.quick else 200
    if args.smoke:
        sizes = [1]
    elif args.quick:
        sizes = [1, 10, 100, 1000]
    else:
        sizes = [1, 10, 100, 1000, 10_000, 100_000]
    sizes = [n for n in sizes if n <= args.max_batch]
    results = {
        "devices": str(jax.devices()),
        "dispatch": "synchronous" if args.sync_dispatch else "asynchronous (JAX's default)",
        "tolerance": TOL,
        "max_iter": MAX_ITER,
        "solvers": SOLVERS,
        "configs": {k: {"solver": s, **p} for k, (s, p) in CONFIGS.items()},
        "latency": [],
        "latency_compiles": {},
        "throughput": [],
    }
    print(
        f"jax {jax.__version__} on {jax.devices()}; tolerance eps_r = eps_s = {TOL}; "
        f"dispatch {results['dispatch']}"
    )
    print(f"solvers (static options, max_iter {MAX_ITER}): {SOLVERS}")
    print(f"configurations (solver, SolverParams): {CONFIGS}")
    horizons = [int(h) for h in args.horizons.split(",")]
    dtypes = args.dtypes.split(",")
    for horizon in horizons if args.only != "throughput" else ():
        rows, compiles = latency(horizon, steps, configs)
        results["latency"] += rows
        results["latency_compiles"][horizon] = compiles
        for lat in rows:
            config = lat["config"]
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
        print(
            f"N_p={horizon}: compiled "
            + ", ".join(
                f"{c['programs']} programs (cold and warm step) for solver {k!r}"
                for k, c in compiles.items()
            )
            + f" for {len(rows)} configurations",
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
    run.results = results
    run.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
