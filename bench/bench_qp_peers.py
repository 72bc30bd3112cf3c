"""Local Explicit against general-purpose JAX QP solvers on the closed loop's integrated MPC.

The closed-loop r_time (eq.t_ratio, ``ampc_jax.closed_loop.replay_timing``) compares
Local Explicit with IntegratedADMM: the same explicit ADMM machinery applied
to the undecomposed problem, the tightest peer this package has. The paper's
integrated MPC was solved by a general-purpose QP solver. This script adds
that comparison on the same stack (JAX on XLA:CPU): jaxopt's ``BoxOSQP`` (an
OSQP-style ADMM written in JAX) on the condensed integrated QP of every
logged control step.

For each scenario the closed loop runs once with the example's tuned
defaults (``ampc simulate``'s settings). Its logged per-step problems are then
replayed, in order, through three ahead-of-time compiled single-step
functions, timed interleaved step by step (median of ``--repeats`` calls,
``block_until_ready``), as ``replay_timing`` does:

* Local Explicit with the warm state it had in the loop (the controller);
* IntegratedADMM warm started from its own previous solution (the r_time peer);
  both with their :class:`~ampc_jax.admm.SolverParams` as an argument, as
  ``replay_timing`` calls them;
* ``jaxopt.BoxOSQP`` (dense "lu" linear solves; its default "cg" needed
  4000 iterations at tol 1e-3 on the cruise run), for each ``tol`` of
  ``--osqp-tols``: cold at the first step, then warm started from its own
  previous solution by the loop's rule (shifted one step when the example
  shifts, ``warm_shift``; cold after a non-finite step or without warm start).
  Its u0 is projected on the bounds, like the others'. Its ``tol``
  is on residual norms of the unscaled QP, so its accuracy is read from
  e_sub, not from the number.

e_sub is |u0 - shadow optimum| (Nm), the loop's shadow IntegratedADMM at
1e-8 Nm^2: every time is printed beside its accuracy and iteration counts.
Ratios are medians over the steps of per-step time ratios (the solvers take
turns at every step, so a slower stretch of a shared machine hits all alike).

Needs the ``bench`` extra (``pip install -e '.[bench]'``, which installs
jaxopt). Run pinned to one core::

    timeout 1800 taskset -c 1 python bench/bench_qp_peers.py
    python bench/bench_qp_peers.py --smoke   # 1 s of cruise, tol 1e-3; no result file

Result file: ``bench/results/bench_qp_peers.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import _meta  # bench/_meta.py, beside this script
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)
from ampc_jax.results import usable

STEM = "bench_qp_peers"

METHODS = ("lu",)  # "cg" needed 4000 iterations at tol 1e-3 on the cruise run (3.8 ms a step)
SCENARIOS = ("cruise_lane_change", "stability_launch_brake", "stability_dlc")
SMOKE_DURATION = 1.0  # s of closed loop in a --smoke run


def _timed(fn: Any, *args: Any, repeats: int) -> tuple[float, Any]:
    import jax

    out = jax.block_until_ready(fn(*args))  # warm caches
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def run_scenario(
    name: str, tols: list[float], repeats: int, duration: float | None = None
) -> list[dict[str, Any]]:
    import jax
    import jax.numpy as jnp
    import jaxopt

    from ampc_jax.admm import shift_horizon
    from ampc_jax.closed_loop import controller_for, simulate
    from ampc_jax.formulations import IntegratedADMM, LocalExplicit
    from ampc_jax.problem import condensed_qp

    res = simulate(name, duration=duration)
    cfg, log = res.config, res.log
    ctrl = controller_for(cfg)
    T = ctrl.topology
    shadow = np.asarray(log.u_shadow)[:, ctrl.input_columns]
    K = int(np.shape(log.t)[0])
    step = lambda x, k: jax.device_put(jax.tree.map(lambda a: np.asarray(a[k]), x))  # noqa: E731
    datas = [step(log.data, k) for k in range(K)]
    warms = [step(log.warm, k) for k in range(K)]
    n_u = shadow.shape[1]

    dtype = datas[0].A.dtype
    le = LocalExplicit(T, max_iter=cfg.max_iter, anderson=cfg.anderson)
    p_le = cfg.loop_params(dtype).controller.solver
    ia = IntegratedADMM(T, max_iter=max(cfg.max_iter, 2000), anderson=cfg.anderson)
    p_ia = ia.params(
        rho=cfg.integrated_rho_scale,
        relaxation=cfg.relaxation,
        tol_primal=cfg.tol_primal,
        tol_dual=cfg.tol_dual,
        dtype=dtype,
    )
    shift = cfg.warm_shift
    cold_i = ia.cold_state(dtype)
    f_le = jax.jit(le.solve).lower(datas[0], p_le, warms[0]).compile()
    f_ia = jax.jit(ia.solve).lower(datas[0], p_ia, cold_i).compile()

    def osqp_fn(solver: Any) -> Any:
        def solve(d: Any, init: Any) -> Any:
            qp = condensed_qp(T, d)
            lower = jnp.full_like(qp.h, -jnp.inf)
            sol = solver.run(
                init_params=init,
                params_obj=(qp.H, qp.E),
                params_eq=qp.G,
                params_ineq=(lower, qp.h),
            )
            return sol.params, sol.state.iter_num

        return solve

    peers = {}
    for tol in tols:
        for method in METHODS:
            solver = jaxopt.BoxOSQP(tol=tol, eq_qp_solve=method, maxiter=4000, jit=True)
            fn = osqp_fn(solver)
            first, _ = jax.jit(fn)(datas[0], None)
            peers[f"BoxOSQP {method}, tol {tol:g}"] = (
                jax.jit(fn).lower(datas[0], first).compile(),
                jax.tree.map(jnp.zeros_like, first),  # its cold start
            )

    def shift_params(params: Any) -> Any:
        """The MPC warm start of the other two solvers (jaxopt keeps flat vectors)."""
        return jax.tree.map(
            lambda x: shift_horizon(x.reshape(T.horizon, -1), shift).reshape(-1), params
        )

    rows: dict[str, dict[str, list]] = {}

    def record(label: str, t: float, u0: Any, its: Any) -> None:
        r = rows.setdefault(label, {"t": [], "e": [], "it": []})
        r["t"].append(t)
        r["e"].append(np.abs(np.asarray(u0)[:n_u] - shadow[k]))
        r["it"].append(int(its))

    w_i = cold_i
    osqp_warm = {label: cold for label, (_, cold) in peers.items()}
    for k in range(K):
        t, r = _timed(f_le, datas[k], p_le, warms[k], repeats=repeats)
        record("Local Explicit", t, r.u0, r.iterations)
        t, r = _timed(f_ia, datas[k], p_ia, w_i, repeats=repeats)
        record("IntegratedADMM", t, r.u0, r.iterations)
        ok = usable(int(r.status)) and bool(np.all(np.isfinite(np.asarray(r.u0))))
        w_i = ia.shift(r.state, shift) if (ok and cfg.warm_start) else cold_i
        lb0, ub0 = np.asarray(datas[k].lb[0]), np.asarray(datas[k].ub[0])
        for label, (fn, cold) in peers.items():
            t, (params, its) = _timed(fn, datas[k], osqp_warm[label], repeats=repeats)
            x = np.asarray(params.primal[0])
            # projected on the bounds, as the other two solvers' u0 and the shadow's
            record(label, t, np.clip(x.reshape(T.horizon, -1)[0], lb0, ub0), its)
            ok = bool(np.all(np.isfinite(x)))
            osqp_warm[label] = shift_params(params) if (ok and cfg.warm_start) else cold
        if k % 50 == 0:
            print(f"  [{name}: step {k}/{K}]", file=sys.stderr, flush=True)

    t_le = np.asarray(rows["Local Explicit"]["t"])
    out = []
    for label, r in rows.items():
        t = np.asarray(r["t"])
        e = np.concatenate(r["e"])
        it = np.asarray(r["it"])
        out.append(
            {
                "scenario": name,
                "solver": label,
                "t_median_us": float(np.median(t) * 1e6),
                "le_over_solver": float(np.median(t_le / t)),
                "e_sub_p95": float(np.nanpercentile(e, 95)),
                "e_sub_max": float(np.nanmax(e)),
                "it_p50": float(np.percentile(it, 50)),
                "it_p95": float(np.percentile(it, 95)),
            }
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", help="default: all three (--smoke: the first)")
    ap.add_argument(
        "--osqp-tols", type=float, nargs="+", help="default: 1e-3 1e-4 1e-6 (--smoke: 1e-3)"
    )
    ap.add_argument("--repeats", type=int, help="default: 3 (--smoke: 1)")
    ap.add_argument(
        "--smoke",
        action="store_true",
        help=f"a quick check of the same code: {SMOKE_DURATION:g} s of closed loop, "
        "with the smoke defaults above",
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    if args.scenarios is None:
        args.scenarios = list(SCENARIOS[:1] if args.smoke else SCENARIOS)
    if args.osqp_tols is None:
        args.osqp_tols = [1e-3] if args.smoke else [1e-3, 1e-4, 1e-6]
    if args.repeats is None:
        args.repeats = 1 if args.smoke else 3
    duration = SMOKE_DURATION if args.smoke else None
    try:
        import jaxopt  # noqa: F401
    except ImportError:
        print("bench_qp_peers needs jaxopt: pip install -e '.[bench]'", file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    run = _meta.Run(_meta.output_path(args, STEM))
    print(f"jax {jax.__version__}; one step per call, medians over the logged steps\n")
    print(
        "| scenario | solver | step median (us) | **r_time = t_LE / t_solver** "
        "| e_sub p95 / max (Nm) | iterations p50 / p95 |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    rows = []
    for name in args.scenarios:
        for r in run_scenario(name, args.osqp_tols, args.repeats, duration):
            rows.append(r)
            print(
                f"| {r['scenario']} | {r['solver']} | {r['t_median_us']:.0f} "
                f"| {r['le_over_solver']:.3g} | {r['e_sub_p95']:.3g} / {r['e_sub_max']:.3g} "
                f"| {r['it_p50']:.0f} / {r['it_p95']:.0f} |",
                flush=True,
            )
    run.results = {
        "osqp_tols": args.osqp_tols,
        "repeats": args.repeats,
        "duration_s": duration,
        "rows": rows,
    }
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
