"""Where a control step's time goes: JAX's per-call overhead against the solve.

For each closed-loop scenario this runs the closed loop once (to log every
step's ProblemData and Local Explicit warm start, as ``replay_timing`` does),
then times, interleaved on the logged steps (median per step, then the median
over the steps), for Local Explicit and for IntegratedADMM (the r_time peer,
warm started from its own previous solution), each with its
:class:`~ampc_jax.admm.SolverParams` as an argument as in ``replay_timing``:

* ``full``: ``jax.jit(solver.solve)(data, params, warm)``, the call
  ``replay_timing`` times (the whole SolveResult comes back: 13 arrays for
  either solver, the state in the solver's stacked layout);
* ``no-op``: a jitted function with the same arguments and the same output
  structure that does no solving (sums its inputs into the outputs): JAX's
  cost of the call itself (argument handling, output buffers, dispatch);
* ``packed``: the call a deployed controller needs, with the warm state packed
  into one vector (``jax.flatten_util.ravel_pytree``) in and out and only u0,
  the next warm state and (status, iterations) returned.

The three calls of both solvers are interleaved at every step, so that a
slower stretch of a shared machine hits all six alike. Usage::

    taskset -c 1 python bench/bench_call_overhead.py [SCENARIO ...]
    python bench/bench_call_overhead.py --smoke   # no result file

(default: the three closed-loop scenarios). ``--smoke``: a quick check of the
same code on the first scenario (or the ones named), 1 s of closed loop and 3
interleaved calls per step, without the loop's shadow solver (unused here).
Result file: ``bench/results/bench_call_overhead.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import _meta  # bench/_meta.py, beside this script
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import ampc_jax  # noqa: F401  (its XLA flags; JAX starts its backend later)
from ampc_jax.closed_loop import config_for, controller_for, simulate
from ampc_jax.formulations import IntegratedADMM, LocalExplicit
from ampc_jax.results import USABLE_STATUS

jax.config.update("jax_enable_x64", True)

STEM = "bench_call_overhead"

SCENARIOS = ("cruise_lane_change", "stability_launch_brake", "stability_dlc")
REPEATS = 25
SMOKE_DURATION, SMOKE_REPEATS = 1.0, 3  # s of closed loop, calls per step


def _noop_like(solver: Any, d: Any, p: Any, w: Any) -> Any:
    shape = jax.eval_shape(lambda: solver.solve(d, p, w))

    def f(d: Any, p: Any, w: Any) -> Any:
        s = sum(jnp.sum(x).astype(jnp.float64) for x in jax.tree.leaves((d, p, w)) if x.size)
        return jax.tree.map(lambda t: jnp.full(t.shape, s).astype(t.dtype), shape)

    return f


def _packed(solver: Any, template: Any, shift: int) -> Any:
    _, unravel = ravel_pytree(template)

    def f(d: Any, params: Any, packed: Any) -> Any:
        r = solver.solve(d, params, unravel(packed))
        nxt = ravel_pytree(solver.shift(r.state, shift))[0]
        return r.u[0], nxt, jnp.stack([r.status, r.iterations])

    return f


def run(name: str, repeats: int = REPEATS, duration: float | None = None) -> dict[str, float]:
    # a smoke run (``duration`` given) skips the loop's shadow solver, which is not used here
    cfg = config_for(name) if duration is None else config_for(name, shadow=False)
    res = simulate(name, cfg, duration=duration)
    log = res.log
    T = controller_for(cfg).topology
    le = LocalExplicit(T, max_iter=cfg.max_iter, anderson=cfg.anderson)
    ia = IntegratedADMM(T, max_iter=max(cfg.max_iter, 2000), anderson=cfg.anderson)
    p_le = cfg.loop_params().controller.solver
    p_ia = ia.params(
        rho=cfg.integrated_rho_scale,
        relaxation=cfg.relaxation,
        tol_primal=cfg.tol_primal,
        tol_dual=cfg.tol_dual,
    )
    K = len(log.t)
    ds = [jax.device_put(jax.tree.map(lambda x, k=k: x[k], log.data)) for k in range(K)]
    ws = [jax.device_put(jax.tree.map(lambda x, k=k: x[k], log.warm)) for k in range(K)]
    cold = ia.cold_state(jnp.float64)
    # the peer's warm chain, as in replay_timing
    full_i = jax.jit(ia.solve).lower(ds[0], p_ia, cold).compile()
    wis = [cold]
    for k in range(K - 1):
        r = full_i(ds[k], p_ia, wis[-1])
        ok = int(r.status) in USABLE_STATUS and bool(np.all(np.isfinite(np.asarray(r.u))))
        wis.append(ia.shift(r.state, cfg.warm_shift) if ok else cold)
    fns = {
        ("LE", "full"): (jax.jit(le.solve).lower(ds[0], p_le, ws[0]).compile(), "le3"),
        ("int", "full"): (full_i, "ia3"),
        ("LE", "no-op"): (
            jax.jit(_noop_like(le, ds[0], p_le, ws[0])).lower(ds[0], p_le, ws[0]).compile(),
            "le3",
        ),
        ("int", "no-op"): (
            jax.jit(_noop_like(ia, ds[0], p_ia, cold)).lower(ds[0], p_ia, cold).compile(),
            "ia3",
        ),
        ("LE", "packed"): (
            jax.jit(_packed(le, ws[0], cfg.warm_shift))
            .lower(ds[0], p_le, ravel_pytree(ws[0])[0])
            .compile(),
            "le2",
        ),
        ("int", "packed"): (
            jax.jit(_packed(ia, cold, cfg.warm_shift))
            .lower(ds[0], p_ia, ravel_pytree(cold)[0])
            .compile(),
            "ia2",
        ),
    }
    pl = [ravel_pytree(w)[0] for w in ws]
    pi = [ravel_pytree(w)[0] for w in wis]

    def args(kind: str, k: int) -> tuple:
        return {
            "le3": (ds[k], p_le, ws[k]),
            "ia3": (ds[k], p_ia, wis[k]),
            "le2": (ds[k], p_le, pl[k]),
            "ia2": (ds[k], p_ia, pi[k]),
        }[kind]

    per: dict[tuple, list] = {key: [] for key in fns}
    for k in range(0, K, 2):
        acc: dict[tuple, list] = {key: [] for key in fns}
        for f, kind in fns.values():
            jax.block_until_ready(f(*args(kind, k)))
        for _ in range(repeats):
            for key, (f, kind) in fns.items():
                a = args(kind, k)
                t0 = time.perf_counter()
                jax.block_until_ready(f(*a))
                acc[key].append(time.perf_counter() - t0)
        for key in fns:
            per[key].append(np.median(acc[key]) * 1e6)
    t = {key: np.asarray(v) for key, v in per.items()}
    out = {f"{s} {kind}": float(np.median(t[(s, kind)])) for s, kind in fns}
    for kind in ("full", "packed"):
        out[f"r_time {kind}"] = float(np.median(t[("LE", kind)] / t[("int", kind)]))
    out["r_time full minus no-op"] = float(
        np.median(
            (t[("LE", "full")] - t[("LE", "no-op")]) / (t[("int", "full")] - t[("int", "no-op")])
        )
    )
    out["steps"] = K
    out["timed_steps"] = len(range(0, K, 2))
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="*", metavar="SCENARIO", help="default: all three")
    ap.add_argument(
        "--smoke",
        action="store_true",
        help=f"{SMOKE_DURATION:g} s of closed loop, {SMOKE_REPEATS} calls per step, "
        "the first scenario unless named",
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    run_ = _meta.Run(_meta.output_path(args, STEM))
    names = args.scenarios or list(SCENARIOS[:1] if args.smoke else SCENARIOS)
    repeats = SMOKE_REPEATS if args.smoke else REPEATS
    duration = SMOKE_DURATION if args.smoke else None
    print(
        f"jax {jax.__version__}; medians over every other logged step, {repeats} interleaved calls each"
    )
    print(
        "| scenario | LE full / no-op / packed (us) | int. full / no-op / packed (us) | r_time full | packed | full minus no-op |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    rows = {}
    for name in names:
        o = run(name, repeats, duration)
        rows[name] = o
        print(
            f"| {name} | {o['LE full']:.1f} / {o['LE no-op']:.1f} / {o['LE packed']:.1f} | "
            f"{o['int full']:.1f} / {o['int no-op']:.1f} / {o['int packed']:.1f} | "
            f"{o['r_time full']:.3f} | {o['r_time packed']:.3f} | {o['r_time full minus no-op']:.3f} |",
            flush=True,
        )
    run_.results = {
        "repeats": repeats,
        "duration_s": duration,
        "unit": "us per call (median over the timed steps of per-step medians)",
        "scenarios": rows,
    }
    run_.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
