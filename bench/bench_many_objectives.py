"""Convergence with two to four objectives: iterations to tolerance of every formulation.

The paper decomposes into two objectives only and calls more an open question
(paper-notes item 12). For generated problems with J = 2, 3, 4 objectives, shared
agents (``shared="chain"``: an agent between neighbours; ``"both"``: also one
agent shared by all) and active bounds
(``ampc_jax.generate.random_problem(seed, J, shared=...)``), prints per
formulation the plain iteration's (alpha = 1, no Anderson acceleration)
iterations to ``--tol``, how many problems converged within ``--max-iter``, and
the worst first-step error against Clarabel::

    python bench/bench_many_objectives.py [--seeds 10] [--tol 1e-10]
    python bench/bench_many_objectives.py --smoke   # two seeds, J = 2 and 3; no result file

Result file: ``bench/results/bench_many_objectives.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse

import _meta  # bench/_meta.py, beside this script
import jax
import jax.numpy as jnp
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)
from ampc_jax.formulations import formulation
from ampc_jax.generate import random_problem
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

jax.config.update("jax_enable_x64", True)

STEM = "bench_many_objectives"
NAMES = ("local_explicit", "fully_distributed", "virtual_center")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="problems per case (default 10)")
    ap.add_argument("--tol", type=float, default=1e-10, help="eps_r = eps_s (default 1e-10)")
    ap.add_argument("--max-iter", type=int, default=40000, help="iteration cap (default 40000)")
    ap.add_argument("--smoke", action="store_true", help="two seeds, J = 2 and 3 (default off)")
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    seeds = 2 if args.smoke else args.seeds
    cases = [(2, "chain"), (3, "chain")]
    if not args.smoke:
        cases += [(3, "both"), (4, "chain"), (4, "both")]
    run = _meta.Run(_meta.output_path(args, STEM))
    print(
        "| objectives | sharing | formulation | converged | iterations p50 / p95 / max "
        "| worst first-step error (relative) |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    rows = []
    for J, shared in cases:
        problems = [random_problem(s, J, shared=shared) for s in range(seeds)]
        T = problems[0].topology
        data = jax.tree.map(lambda *x: jnp.stack(x), *[p.data() for p in problems])
        refs = [solve_reference(T, p.data()).u[0] for p in problems]
        for name in NAMES:
            f = formulation(name, T, max_iter=args.max_iter)
            q = f.params(tol_primal=args.tol, tol_dual=args.tol)
            res = jax.jit(jax.vmap(f.solve, in_axes=(0, None)))(data, q)
            its = np.asarray(res.iterations)
            ok = np.asarray(res.status) == Status.SOLVED
            u0 = np.asarray(res.u0)
            err = max(
                float(np.max(np.abs(u0[b] - r) / (np.abs(r) + 1e-3))) for b, r in enumerate(refs)
            )
            row = {
                "objectives": J,
                "shared": shared,
                "formulation": name,
                "converged": int(ok.sum()),
                "cases": seeds,
                "iterations": its.tolist(),
                "worst_relative_error": err,
            }
            rows.append(row)
            p50, p95, mx = np.percentile(its, 50), np.percentile(its, 95), its.max()
            print(
                f"| {J} | {shared} | {name} | {ok.sum()} / {seeds} | "
                f"{p50:.0f} / {p95:.0f} / {mx} | {err:.1e} |",
                flush=True,
            )
    run.results = {"tolerance": args.tol, "max_iter": args.max_iter, "rows": rows}
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
