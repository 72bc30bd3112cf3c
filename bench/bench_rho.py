"""eq.opt_ro's rho* against a brute-force per-objective grid (iterations to tolerance).

Run: ``python bench/bench_rho.py [--problems 12]``. For generated two-objective
problems with active bounds, prints the iterations at rho* and at the best
point of a 13 x 13 grid spanning [0.01, 100] rho* per objective, and the ratio.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)
from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem

jax.config.update("jax_enable_x64", True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", type=int, default=12)
    ap.add_argument("--tol", type=float, default=1e-8)
    args = ap.parse_args()
    grid = np.logspace(-2, 2, 13)
    g1, g2 = np.meshgrid(grid, grid, indexing="ij")
    scales = np.stack([g1.ravel(), g2.ravel()], 1)
    p0 = random_problem(0, 2, shared="all", reference_scale=2.0)
    solver = LocalExplicit(p0.topology, max_iter=3000, tol_primal=args.tol, tol_dual=args.tol)
    star_fn = jax.jit(solver.solve)
    scan_fn = jax.jit(jax.vmap(lambda d, r: solver.solve(d, r).iterations, in_axes=(None, 0)))
    ratios = []
    print("seed  it(rho*)  best  best scale (per objective)  ratio")
    for seed in range(args.problems):
        d = random_problem(seed, 2, shared="all", reference_scale=2.0).data()
        star = star_fn(d)
        its = np.asarray(scan_fn(d, jnp.asarray(scales * np.asarray(star.rho))))
        k = int(np.argmin(its))
        ratios.append(int(star.iterations) / its[k])
        print(f"{seed:4d}  {int(star.iterations):8d}  {its[k]:4d}  {scales[k]}  {ratios[-1]:.2f}")
    print(f"ratio min {min(ratios):.2f}, median {np.median(ratios):.2f}, max {max(ratios):.2f}")


if __name__ == "__main__":
    main()
