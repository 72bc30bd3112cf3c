"""The cost of a gradient of a solve against its forward pass: unrolled and implicit.

What tuning pays (:mod:`ampc_jax.tuning`): ``jax.value_and_grad`` of a loss of
Local Explicit's result with respect to theta = (log rho_j per objective, the
relaxation alpha, log of a factor on the input weights R), over a batch of
cases, against the same loss's forward pass. The cases are single
time-varying steps of ``bench_peers.py``'s cruise problem with its general
rows (N_p = 10 by default), the settings its "tuned" point (rho (1, 0.1) x
rho*, relaxation 1.6), the loss the mean of |u0|^2. Per KKT form (``--kkt``)
the contenders, each timed forward and with the gradient (median of
``--repeats`` calls after a warm-up, one XLA device, float64):

* ``unrolled vmap``: K unrolled iterations (``solve_fixed``, ``lax.scan``), one
  ``jax.vmap`` over every case (what ``ampc tune`` runs);
* ``unrolled chunks``: the same, ``jax.lax.map`` over chunks of ``--chunk``
  cases, each vmapped, ``value_and_grad`` inside the map;
* ``unrolled checkpoint``: ``unrolled vmap`` with each iteration under
  ``jax.checkpoint`` (the backward pass recomputes an iteration instead of
  reading its stored intermediates);
* ``implicit <tol>``: the solve to tolerance (``--tol``, its ``while_loop``, cap
  ``--max-iter``; Anderson memory ``--anderson``) forward, and
  :func:`~ampc_jax.admm.implicit.solve_implicit` (the adjoint of the ADMM map at
  the fixed point, to the relative tolerance ``<tol>``, one contender for each
  of ``--adjoint-tol``) for the gradient.

Printed: milliseconds, each gradient / its own forward pass, the program's
temporary memory (XLA's ``memory_analysis``), and its accuracy: the largest
error of the gradient against central differences of its own forward
function (step ``--fd-step`` on every entry of theta), relative to the largest
difference. The implicit gradient's rho and alpha entries are zero: the solution
does not depend on them (:mod:`ampc_jax.admm.implicit`). Target:
value_and_grad <= 2x the forward pass for woodbury_factored and riccati at
K = 10, 1,000 cases, judged for the unrolled gradient on the fastest unrolled
gradient against the fastest unrolled forward pass, and for the implicit one
against the solve to tolerance.

Run::

    taskset -c 1 python bench/bench_grad.py                 # 1,000 cases, K = 10
    taskset -c 1 python bench/bench_grad.py --batchings "" --anderson 3   # implicit only
    python bench/bench_grad.py --smoke                      # 16 cases, K = 3, woodbury_factored

Result file: ``bench/results/bench_grad.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__":  # one XLA device, before JAX starts
    _flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in _flags:
        os.environ["XLA_FLAGS"] = f"{_flags} --xla_force_host_platform_device_count=1".strip()

import argparse  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import _meta  # noqa: E402  (bench/_meta.py, beside this script)
import bench_peers as bp  # noqa: E402  (the cruise problem with general rows, beside this script)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.flatten_util import ravel_pytree  # noqa: E402

from ampc_jax.admm.implicit import solve_implicit  # noqa: E402
from ampc_jax.formulations import LocalExplicit  # noqa: E402

STEM = "bench_grad"
TARGET = 2.0
UNROLLED = ("unrolled vmap", "unrolled chunks", "unrolled checkpoint")


def timed(fn: Any, arg: Any, repeats: int) -> float:
    """Median seconds of ``repeats`` calls after one warm-up."""
    jax.block_until_ready(fn(arg))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(arg))
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def temp_mb(compiled: Any) -> float:
    """XLA's temporary buffer size of a compiled program (MB; nan when not reported)."""
    try:
        return float(compiled.memory_analysis().temp_size_in_bytes) / 1e6
    except Exception:  # noqa: BLE001  (a backend without the analysis)
        return float("nan")


def fixed_checkpointed(solver: LocalExplicit, d: Any, K: int, p: Any) -> Any:
    """``solver.solve_fixed(d, K, p)`` (plain ADMM) with each iteration under ``jax.checkpoint``."""
    setup = solver.setup(d, p)
    step = jax.checkpoint(lambda st: solver.step(setup, st))
    st, _ = jax.lax.scan(lambda c, _: (step(c), None), solver.init(setup), None, length=K)
    return solver.result(setup, st)


def programs(
    solver: LocalExplicit, solver_tol: LocalExplicit, datas: Any, args: Any
) -> tuple[dict[str, Any], dict[str, Any], Any]:
    """The compiled programs of theta: per contender its forward and value_and_grad,
    and the forward passes at theta +- h e_i (central differences, one batched program)."""
    K, chunk, B = args.iterations, args.chunk, int(datas.A.shape[0])
    p0 = solver.params(
        rho=bp.TUNED["rho"],
        relaxation=bp.TUNED["relaxation"],
        tol_primal=args.tol,
        tol_dual=args.tol,
    )

    def inputs(theta: Any, d: Any) -> tuple[Any, Any]:
        p = p0._replace(rho=jnp.exp(theta[0]), relaxation=theta[1])
        return d._replace(R=d.R * jnp.exp(theta[2])), p

    def unrolled(theta: Any, d: Any) -> Any:
        dd, p = inputs(theta, d)
        return jnp.sum(solver.solve_fixed(dd, K, p).u0 ** 2)

    def checkpointed(theta: Any, d: Any) -> Any:
        dd, p = inputs(theta, d)
        return jnp.sum(fixed_checkpointed(solver, dd, K, p).u0 ** 2)

    def solved(theta: Any, d: Any) -> Any:
        return jnp.sum(solver_tol.solve(*inputs(theta, d)).u0 ** 2)

    def implicit(adjoint_tol: float) -> Any:
        def loss(theta: Any, d: Any) -> Any:
            res = solve_implicit(solver_tol, *inputs(theta, d), adjoint_tol=adjoint_tol)
            return jnp.sum(res.u0**2)

        return loss

    def mean_of(loss: Any) -> Any:
        return lambda theta, ds: jnp.mean(jax.vmap(loss, in_axes=(None, 0))(theta, ds))

    chunks = jax.tree.map(lambda x: x.reshape(B // chunk, chunk, *x.shape[1:]), datas)
    mean_unrolled = mean_of(unrolled)

    def fwd_chunks(theta: Any) -> Any:
        return jnp.mean(jax.lax.map(lambda d: mean_unrolled(theta, d), chunks))

    def grad_chunks(theta: Any) -> Any:
        v, g = jax.lax.map(lambda d: jax.value_and_grad(mean_unrolled)(theta, d), chunks)
        return jnp.mean(v), jax.tree.map(lambda x: jnp.mean(x, 0), g)

    def over(loss: Any) -> Any:
        return lambda th: mean_of(loss)(th, datas)

    theta = (jnp.log(jnp.asarray(p0.rho)), jnp.asarray(p0.relaxation), jnp.zeros(()))
    flat, unravel = ravel_pytree(theta)
    E = np.eye(flat.size) * args.fd_step
    points = jnp.concatenate([flat + E, flat - E])

    def differences(loss: Any) -> Any:  # (n,) central differences of loss at theta
        def f(_: Any) -> Any:
            v = jax.vmap(lambda x: over(loss)(unravel(x)))(points)
            return (v[: flat.size] - v[flat.size :]) / (2 * args.fd_step)

        return f

    fns: dict[str, tuple[Any, Any, Any]] = {}  # contender -> (forward, value_and_grad, fd)
    if "vmap" in args.batchings:
        fns["unrolled vmap"] = (
            over(unrolled),
            jax.value_and_grad(over(unrolled)),
            differences(unrolled),
        )
    if "chunks" in args.batchings:
        fns["unrolled chunks"] = (fwd_chunks, grad_chunks, None)
    if "checkpoint" in args.batchings:
        fns["unrolled checkpoint"] = (
            over(checkpointed),
            jax.value_and_grad(over(checkpointed)),
            None,
        )
    for atol in args.adjoint_tol:  # one forward pass (the solve) and its differences for all
        fns[f"implicit {atol:g}"] = (
            over(solved),
            jax.value_and_grad(over(implicit(atol))),
            differences(solved),
        )
    progs, fds, shared = {}, {}, {}
    for name, (fwd, grad, fd) in fns.items():
        key = "solve" if name.startswith("implicit") else name
        if key not in shared:
            shared[key] = (
                jax.jit(fwd).lower(theta).compile(),
                None if fd is None else jax.jit(fd).lower(theta).compile(),
            )
        progs[f"{name} forward"] = shared[key][0]
        progs[f"{name} value_and_grad"] = jax.jit(grad).lower(theta).compile()
        if fd is not None:
            fds[name] = shared[key][1]
    return progs, fds, theta


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--iterations", type=int, default=10, help="K, unrolled iterations")
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--chunk", type=int, default=40, help="cases per chunk (divides --cases)")
    ap.add_argument("--kkt", default="woodbury_factored,riccati")
    ap.add_argument(
        "--batchings",
        default="vmap,chunks,checkpoint",
        help="unrolled contenders: any of vmap, chunks, checkpoint (implicit always runs)",
    )
    ap.add_argument("--tol", type=float, default=1e-12, help="the implicit solve's eps_r = eps_s")
    ap.add_argument("--max-iter", type=int, default=2000, help="the implicit solve's cap")
    ap.add_argument("--anderson", type=int, default=0, help="the implicit solve's Anderson memory")
    ap.add_argument(
        "--adjoint-tol",
        default="1e-6,1e-10",
        help="the implicit adjoint's relative tolerances, one contender each (1e-10: the default)",
    )
    ap.add_argument("--fd-step", type=float, default=1e-5, help="central-difference step")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--smoke", action="store_true", help="16 cases, K = 3, woodbury_factored, vmap only"
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    if args.smoke:
        args.cases, args.iterations, args.chunk, args.repeats = 16, 3, 8, 2
        args.kkt, args.batchings, args.adjoint_tol = "woodbury_factored", "vmap", "1e-6"
    args.batchings = tuple(b for b in args.batchings.split(",") if b)
    try:
        args.adjoint_tol = tuple(float(x) for x in args.adjoint_tol.split(",") if x)
    except ValueError:
        ap.error(f"--adjoint-tol: expected numbers, got {args.adjoint_tol!r}")
    if not args.adjoint_tol or not all(np.isfinite(t) and t > 0 for t in args.adjoint_tol):
        ap.error(f"--adjoint-tol: expected positive numbers, got {args.adjoint_tol}")
    bad = set(args.batchings) - {"vmap", "chunks", "checkpoint"}
    if bad:
        ap.error(f"--batchings: unknown {sorted(bad)}; expected vmap, chunks, checkpoint")
    if args.cases % args.chunk:
        ap.error(f"--chunk: {args.chunk} does not divide --cases {args.cases}")
    run = _meta.Run(_meta.output_path(args, STEM))
    T, data_of = bp.problem(args.horizon)
    ops = jax.tree.map(lambda x: x[:, 0], bp.drives(range(args.cases), 1))
    datas = jax.jit(jax.vmap(data_of))(ops)
    print(
        f"{args.cases} cruise steps (N_p = {args.horizon}, general rows), loss mean |u0|^2, "
        f"gradient wrt (log rho, relaxation, log R factor); unrolled: K = {args.iterations}; "
        f"implicit: solve to eps {args.tol:g} (cap {args.max_iter}, Anderson {args.anderson}, "
        f"adjoint tolerances {', '.join(f'{t:g}' for t in args.adjoint_tol)}); "
        f"1 device, float64, median of {args.repeats}; accuracy: max |g - fd| / max |fd|, "
        f"central differences of step {args.fd_step:g}"
    )
    print()
    print(
        "| KKT | contender | forward (ms) | value_and_grad (ms) | ratio | temp MB fwd / grad "
        "| gradient error vs fd |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    rows: dict[str, Any] = {}
    for kkt in args.kkt.split(","):
        solver = LocalExplicit(T, kkt=kkt)
        solver_tol = LocalExplicit(T, kkt=kkt, max_iter=args.max_iter, anderson=args.anderson)
        progs, fds, theta = programs(solver, solver_tol, datas, args)
        t = {k: timed(f, theta, args.repeats) for k, f in progs.items()}
        names = [k[: -len(" forward")] for k in progs if k.endswith(" forward")]
        rows[kkt] = {"ms": {k: v * 1e3 for k, v in t.items()}, "contenders": {}}
        for name in names:
            fwd, grad = progs[f"{name} forward"], progs[f"{name} value_and_grad"]
            g = np.asarray(ravel_pytree(grad(theta)[1])[0])
            ratio = t[f"{name} value_and_grad"] / t[f"{name} forward"]
            row = {
                "forward_ms": t[f"{name} forward"] * 1e3,
                "grad_ms": t[f"{name} value_and_grad"] * 1e3,
                "ratio": ratio,
                "temp_mb": [temp_mb(fwd), temp_mb(grad)],
                "gradient": [float(x) for x in g],
            }
            err = "-"
            if name in fds:
                fd = np.asarray(fds[name](theta))
                row["fd"] = [float(x) for x in fd]
                row["fd_error"] = float(np.max(np.abs(g - fd)) / np.max(np.abs(fd)))
                err = f"{row['fd_error']:.1e}"
            rows[kkt]["contenders"][name] = row
            print(
                f"| {kkt} | {name} | {row['forward_ms']:.1f} | {row['grad_ms']:.1f} | "
                f"{ratio:.2f} | {row['temp_mb'][0]:.1f} / {row['temp_mb'][1]:.1f} | {err} |"
            )
        for name in names:
            r = rows[kkt]["contenders"][name]
            print(f"|  | {name} gradient: {[f'{x:.6g}' for x in r['gradient']]} |  |  |  |  |  |")
    print()
    for kkt, r in rows.items():
        c = r["contenders"]
        unr = [n for n in UNROLLED if n in c]
        checks = [(n, c[n]["ratio"]) for n in c if n.startswith("implicit")]
        if unr:
            fastest = min(c[n]["grad_ms"] for n in unr) / min(c[n]["forward_ms"] for n in unr)
            r["fastest_unrolled_ratio"] = fastest
            checks.insert(0, ("unrolled", fastest))
        for label, v in checks:
            verdict = "PASS" if v <= TARGET else "MISS"
            print(
                f"{verdict} {kkt} {label}: value_and_grad / forward {v:.2f} (target <= "
                f"{TARGET:.0f}; {'fastest of ' + ', '.join(unr) if label == 'unrolled' else 'against the solve'})"
            )
    run.results = {
        "rows": rows,
        "cases": args.cases,
        "K": args.iterations,
        "chunk": args.chunk,
        "tol": args.tol,
        "anderson": args.anderson,
        "adjoint_tol": list(args.adjoint_tol),
        "fd_step": args.fd_step,
    }
    run.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
