"""Per-case cost of the small batched linear algebra behind the batched-throughput target.

The batched throughput target is 100x a Python loop over OSQP
(docs/benchmarks.md): a few us per case-step per core (the loop's own rate is
measured by ``bench_local_explicit.py``'s throughput part). This prints, per case of a
batch of 4096 on one core in float64, what single 40 x 40 pieces of a Local
Explicit step (N_p = 10, 4 inputs) cost under XLA:CPU: a matrix-vector
product, 30 of them in a loop, the inverse by symmetric sweeps (the algorithm
of ``ampc_jax.admm.linalg.sweep_inverse``), LAPACK's inverse and Cholesky
factorisation, and the Gram matrix Y'Y of a 10 x 40 Y; each in the usual
batch-first layout and, where it applies, batch-last (the cases in the minor,
SIMD, dimension). Pinned to one core, so that the per-case figures are one
core's::

    taskset -c 1 python bench/bench_batched_layout.py
    python bench/bench_batched_layout.py --smoke   # batch 64, 3 repeats; no result file

Result file: ``bench/results/bench_batched_layout.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import _meta  # bench/_meta.py, beside this script
import jax
import jax.numpy as jnp
import numpy as np

import ampc_jax  # noqa: F401  (the package's XLA flags, set before the CPU backend starts)

jax.config.update("jax_enable_x64", True)

STEM = "bench_batched_layout"

B, N = 4096, 40
SMOKE_B, SMOKE_REPS = 64, 3


def per_case_us(f: Callable, *args: Any, reps: int = 20, batch: int = B) -> float:
    """Median wall time of the compiled ``f(*args)`` per case, in us."""
    g = jax.jit(f)
    jax.block_until_ready(g(*args))
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(g(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)) / batch * 1e6


def matvec_first(M: Any, x: Any) -> Any:
    return jnp.einsum("bij,bj->bi", M, x)


def matvec_last(M: Any, x: Any) -> Any:
    return (M * x[None, :, :]).sum(axis=1)


def iterate(matvec: Callable) -> Callable:
    def run(M: Any, x: Any) -> Any:
        return jax.lax.fori_loop(0, 30, lambda _, v: 0.01 * matvec(M, v) + x, x)

    return run


def sweep_inverse_first(A: Any) -> Any:
    """Symmetric sweeps, batch first: after all pivots the matrix is -A^-1."""

    def body(k: Any, A: Any) -> Any:
        p = A[:, k, k]
        r = A[:, k, :] / p[:, None]
        c = A[:, :, k]
        A2 = A - c[:, :, None] * r[:, None, :]
        A2 = A2.at[:, k, :].set(r)
        A2 = A2.at[:, :, k].set(-c / p[:, None])
        return A2.at[:, k, k].set(1.0 / p)

    return jax.lax.fori_loop(0, N, body, A)


def sweep_inverse_last(A: Any) -> Any:
    """The same sweeps with the batch as the last axis."""

    def body(k: Any, A: Any) -> Any:
        p = A[k, k]
        r = A[k] / p
        c = A[:, k]
        A2 = A - c[:, None] * r[None]
        A2 = A2.at[k].set(r)
        A2 = A2.at[:, k].set(-c / p)
        return A2.at[k, k].set(1.0 / p)

    return jax.lax.fori_loop(0, N, body, A)


def gram_first(Y: Any) -> Any:
    return jnp.einsum("bki,bkj->bij", Y, Y)


def gram_last(Y: Any) -> Any:
    return (Y[:, :, None, :] * Y[:, None, :, :]).sum(0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--smoke",
        action="store_true",
        help=f"batch {SMOKE_B}, {SMOKE_REPS} repeats: the same programs, a quick check",
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    run = _meta.Run(_meta.output_path(args, STEM))
    b, reps = (SMOKE_B, SMOKE_REPS) if args.smoke else (B, 20)

    def us(f: Callable, *a: Any) -> float:
        return per_case_us(f, *a, reps=reps, batch=b)

    rng = np.random.default_rng(0)
    M = rng.standard_normal((b, N, N))
    M = M @ M.transpose(0, 2, 1) + N * np.eye(N)  # SPD
    x = rng.standard_normal((b, N))
    Y = rng.standard_normal((b, 10, N))
    first = (jnp.asarray(M), jnp.asarray(x), jnp.asarray(Y))
    last = (
        jnp.asarray(M.transpose(1, 2, 0)),
        jnp.asarray(x.T),
        jnp.asarray(Y.transpose(1, 2, 0)),
    )
    rows = [
        ("matrix-vector product", matvec_first, matvec_last, (0, 1)),
        ("30 of them in a fori_loop", iterate(matvec_first), iterate(matvec_last), (0, 1)),
        ("inverse by symmetric sweeps", sweep_inverse_first, sweep_inverse_last, (0,)),
        ("Gram matrix Y'Y (10 x 40 Y)", gram_first, gram_last, (2,)),
    ]
    print(f"jax {jax.__version__}; us per case, batch {b}, {N} x {N}, float64")
    print(f"{'piece':<32}{'batch first':>12}{'batch last':>12}")
    table = {}
    for name, f_first, f_last, which in rows:
        t_first = us(f_first, *(first[i] for i in which))
        t_last = us(f_last, *(last[i] for i in which))
        table[name] = {"batch_first_us": t_first, "batch_last_us": t_last}
        print(f"{name:<32}{t_first:>12.3f}{t_last:>12.3f}", flush=True)
    for name, f in (("LAPACK inverse", jnp.linalg.inv), ("LAPACK Cholesky", jnp.linalg.cholesky)):
        t = us(f, first[0])
        table[name] = {"batch_first_us": t}
        print(f"{name:<32}{t:>12.3f}", flush=True)
    run.results = {"batch": b, "n": N, "repeats": reps, "dtype": "float64", "us_per_case": table}
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
