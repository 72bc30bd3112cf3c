"""eq.opt_ro's rho* against a brute-force per-objective grid (iterations to tolerance).

For generated two-objective problems with active bounds
(``ampc_jax.generate.random_problem(seed, 2, shared="all")``), prints the
iterations of Local Explicit at rho* (``params.rho`` = 1 with the default
``rho_method="power"``: a factor on eq.opt_ro's rho*) and at the best point of
a 13 x 13 grid of factors spanning [0.01, 100] per objective, and their ratio.
The grid is one batch of :class:`~ampc_jax.admm.SolverParams` vmapped through
one compiled solve (the parameters are an argument: no recompilation per point)::

    taskset -c 1 python bench/bench_rho.py [--problems 12]
    python bench/bench_rho.py --smoke   # one problem; writes no result file

Result file: ``bench/results/bench_rho.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse

import _meta  # bench/_meta.py, beside this script
import jax
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)
from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem

jax.config.update("jax_enable_x64", True)

STEM = "bench_rho"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", type=int, default=12, help="generated problems (seeds 0..)")
    ap.add_argument("--tol", type=float, default=1e-8, help="eps_r = eps_s (default 1e-8)")
    ap.add_argument("--smoke", action="store_true", help="one problem, a quick check of the code")
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    n_problems = 1 if args.smoke else args.problems
    run = _meta.Run(_meta.output_path(args, STEM))
    grid = np.logspace(-2, 2, 13)
    g1, g2 = np.meshgrid(grid, grid, indexing="ij")
    scales = np.stack([g1.ravel(), g2.ravel()], 1)
    p0 = random_problem(0, 2, shared="all", reference_scale=2.0)
    solver = LocalExplicit(p0.topology, max_iter=3000)
    star_params = solver.params(tol_primal=args.tol, tol_dual=args.tol)
    grid_params = solver.params(rho=scales, tol_primal=args.tol, tol_dual=args.tol)
    star_fn = jax.jit(solver.solve)
    scan_fn = jax.jit(
        jax.vmap(lambda d, p: solver.solve(d, p).iterations, in_axes=(None, 0)),
    )
    rows = []
    print("seed  it(rho*)  best  best scale (per objective)  ratio")
    for seed in range(n_problems):
        d = random_problem(seed, 2, shared="all", reference_scale=2.0).data()
        star = star_fn(d, star_params)
        its = np.asarray(scan_fn(d, grid_params))
        k = int(np.argmin(its))
        ratio = int(star.iterations) / its[k]
        rows.append(
            {
                "seed": seed,
                "iterations_rho_star": int(star.iterations),
                "iterations_best": int(its[k]),
                "best_scale": [float(x) for x in scales[k]],
                "ratio": float(ratio),
            }
        )
        print(f"{seed:4d}  {int(star.iterations):8d}  {its[k]:4d}  {scales[k]}  {ratio:.2f}")
    ratios = [r["ratio"] for r in rows]
    print(f"ratio min {min(ratios):.2f}, median {np.median(ratios):.2f}, max {max(ratios):.2f}")
    compiles = {"rho_star": star_fn._cache_size(), "grid": scan_fn._cache_size()}
    print(
        f"[compiled: rho* solve {compiles['rho_star']}, {len(scales)}-point grid solve "
        f"{compiles['grid']} (one program each for every problem and grid point)]",
        flush=True,
    )
    run.results = {
        "tolerance": args.tol,
        "grid_factors": [float(x) for x in grid],
        "problems": rows,
        "ratio_min": float(min(ratios)),
        "ratio_median": float(np.median(ratios)),
        "ratio_max": float(max(ratios)),
        "compiles": compiles,
    }
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
