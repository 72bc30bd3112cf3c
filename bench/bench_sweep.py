"""Sweeps of many (case, rho) pairs: throughput against QP peers, compaction, gradients, pencil.

Four sections (``--only`` picks some), each printed as a table and stored in the
result file:

1. ``throughput`` -- solves per second of Local Explicit through
   :func:`ampc_jax.sweep.sweep_solve` (setup, rho*, factorisation and iterations
   of every pair in one program, the pair axis sharded over the devices) on
   ``cruise_step`` cases at N_p = 10 against a grid of ``RHO_GRID`` rho scales,
   for 1 .. 10,000 cases (100,000 with ``--full``). Peers on the same cases,
   each case's condensed QP (:func:`ampc_jax.problem.condensed_qp`, jitted
   and vmapped) built inside its timed call:

   * DAQP (``daqp.Model``: ``setup`` once, then ``update`` + ``solve`` per case,
     warm started from the previous working set; the box rows as simple bounds),
     one process per core (``multiprocessing``, each pinned to its core),
     each condensing and solving its half of the cases; the condensing alone
     is shown beside it;
   * qpax (``qpax.solve_qp``, interior point) vmapped in one jitted program
     with the condensing, the variables scaled by their bounds (its best form
     on these QPs), tolerance ``QPAX_TOL``; on one device (its batched LAPACK
     calls use both cores through XLA's pool; two devices running them can
     deadlock, docs/known-issues.md).

   A QP peer has no rho: one of its solves is one case, one of Local Explicit's
   is one (case, rho) pair, so the table compares solves per second. Accuracy
   is matched on the first step u0: each contender's worst and median
   max_i |u0_i - u0_i*| (Nm) against Clarabel at 1e-13 on the condensed QP, on
   the first ``REF_CASES`` cases (Local Explicit: over every rho point), is
   printed beside its time. Local Explicit runs on the cruise groups derived
   from the model (LST: DTR, RTV, FDB; :func:`exact_groups`): with the paper's
   groups its fixed point is not the integrated optimum (a line shows that
   error, untimed). Its tolerance (``LE_TOL``, eps_r = eps_s in Nm^2; with
   ``--tune-tol`` the loosest of ``TOL_SCAN`` whose worst error is below
   ``ERR_TARGET`` = 1e-2 Nm, the scan printed) is used by sections 1 to 3. Protocol, the same for every contender: one
   warm-up call (compiling, and filling DAQP's workspace) excluded, then
   ``--repeats`` calls on the same cases, interleaved contender by contender,
   median reported; setup and condensing inside every timed call.

2. ``waste`` -- ``jax.vmap`` of a ``while_loop`` runs every pair until the
   slowest is done; compaction runs segments on the pairs still running
   (:func:`ampc_jax.sweep.solve_pairs`). Work.computed / Work.needed and the
   wall time of ``compaction=False`` against ``True`` for a few segment sizes,
   on ``cruise_step``, ``stability_step`` and ``generated``.

3. ``grad`` -- ``jax.grad`` of a loss of the vmapped ``solve_fixed`` (K
   iterations, K the median iteration count to tolerance) with respect to
   log rho and the relaxation, against the forward ``solve_fixed`` and the
   to-tolerance ``solve`` on the same batch (one device); also forward mode
   (``jax.jacfwd``, two tangents), with Anderson acceleration (``ANDERSON``)
   and without. Both modes' gradients are printed: they should agree.

4. ``pencil`` -- rho sweeps need K_j(rho) = H_j + rho Abar_j'Abar_j for every
   rho. The library factorises each (``LocalExplicit.setup`` vmapped over
   pairs: Woodbury or dense sweeps, :mod:`ampc_jax.admm.kkt`). One generalised
   eigendecomposition per case (H_j = L L', V D V' = L^-1 (Abar_j'Abar_j) L^-T,
   W = L^-T V) gives K_j(rho)^-1 = W diag(1 / (1 + rho D)) W' for every rho by
   a rescale. Timed batched in JAX for P rho points, per case: the library's
   setup P times, its factorisation alone P times (the costs shared), and the
   pencil (one decomposition, then P rescales) kept factored (W, 1 / (1 + rho D))
   or with K_j^-1 formed. On one device (batched eigh is a LAPACK call).

Run (both cores as two XLA devices: ``--devices 2`` sets
``--xla_force_host_platform_device_count`` before JAX starts)::

    python bench/bench_sweep.py --devices 2 --tune-tol          # the committed run
    python bench/bench_sweep.py --devices 2 --tune-tol --full   # adds 100,000 cases
    python bench/bench_sweep.py --smoke --devices 2             # tiny sizes; no result file

Needs daqp and qpax (the ``bench`` extra). Result file:
``bench/results/bench_sweep.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__" and "--devices" in sys.argv:  # before JAX starts its CPU backend
    _i = sys.argv.index("--devices")
    if _i + 1 < len(sys.argv) and sys.argv[_i + 1].isdigit():
        _flags = os.environ.get("XLA_FLAGS", "")
        if "xla_force_host_platform_device_count" not in _flags:
            os.environ["XLA_FLAGS"] = (
                f"{_flags} --xla_force_host_platform_device_count={sys.argv[_i + 1]}".strip()
            )

import argparse  # noqa: E402
import multiprocessing as mp  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import _meta  # noqa: E402  (bench/_meta.py, beside this script)
import numpy as np  # noqa: E402

import ampc_jax  # noqa: E402, F401  (XLA:CPU workaround before JAX starts)

STEM = "bench_sweep"
SECTIONS = ("throughput", "waste", "grad", "pencil")
HORIZON = 10
RHO_GRID = (0.5, 1.0, 2.0, 4.0)  # factors on eq.opt_ro's rho*
ANDERSON = 3  # the closed-loop default
MAX_ITER = 500
TOL_SCAN = (1.0, 1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8)
LE_OPTIONS: dict[str, Any] = {}  # Local Explicit's strategy options (--finish)
LE_TOL = 1e-8  # Nm^2, the default; --tune-tol picks the loosest power of ten under ERR_TARGET
CASES = (1, 10, 100, 1000, 10000)
FULL_CASES = (100000,)
SMOKE_CASES = (4,)
REF_CASES = 100
REF_EPS = 1e-13
ERR_TARGET = 1e-2  # Nm
QPAX_TOL, QPAX_MAX_ITER = 1e-7, 40  # tol: the default; --tune-tol scans QPAX_TOL_SCAN
QPAX_TOL_SCAN = (1e-5, 1e-6, 1e-7, 1e-8)
WASTE_CASES = 1000
SEGMENTS = (8, 32)
GRAD_BATCH = 64
PENCIL_CASES = 256
PENCIL_P = (1, 4, 16, 30)


def exact_groups(cases: Any) -> Any:
    """``cases`` with the cruise topology's LST group widened to {DTR, RTV, FDB}.

    The paper's S_LST = {DTR, FDB} drops RTV's weak coupling to v_x when cornering
    (docs/known-issues.md), so Local Explicit's fixed point is not the integrated
    optimum (errors of several Nm against Clarabel, printed by the throughput
    section); with the groups derived from the model the decomposition is exact
    (``bench/bench_local_explicit.py`` does the same). The data are unchanged.
    """
    from ampc_jax.problem.topology import Topology

    T = cases.topology
    names = T.agent_names
    groups = [
        tuple(range(len(names))) if o == "LST" else g
        for o, g in zip(T.objective_names, T.groups, strict=True)
    ]
    T2 = Topology.build(
        n_x=T.n_x,
        horizon=T.horizon,
        agent_names=names,
        agent_sizes=T.agent_sizes,
        objective_names=T.objective_names,
        output_sizes=T.output_sizes,
        groups=groups,
    )
    assert T2.box_rows == T.box_rows and T2.n_c == T.n_c
    return cases._replace(topology=T2)


def _median_time(fn: Any, repeats: int) -> tuple[float, Any]:
    """One warm-up call, then the median of ``repeats`` timed calls (and the last output)."""
    out = fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), out


def _numpy_tree(tree: Any) -> Any:
    import jax

    return jax.tree.map(np.asarray, tree)


def _take(tree: Any, lo: int, hi: int) -> Any:
    import jax

    return jax.tree.map(lambda x: x[lo:hi], tree)


def _bounds_of(topology: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Box rows of A_in as simple bounds: (input of each +1 row, of each -1 row, general rows)."""
    up = [c for c, (_, s) in enumerate(topology.box_rows) if s > 0]
    lo = [c for c, (_, s) in enumerate(topology.box_rows) if s < 0]
    gen = np.arange(len(topology.box_rows), topology.n_c)
    return np.asarray(up), np.asarray(lo), gen


def condenser(topology: Any) -> Any:
    """Jitted, vmapped: ProblemData (batch) -> (H, f, A general rows, upper, lower) per case,
    the variables' bounds first (DAQP's form; +-1e30 where a bound is absent)."""
    import jax
    import jax.numpy as jnp

    from ampc_jax.problem import condensed_qp

    T = topology
    up, lo, gen = _bounds_of(T)
    N, n_u = T.horizon, T.n_u
    iu = np.asarray([T.box_rows[c][0] for c in up])
    il = np.asarray([T.box_rows[c][0] for c in lo])

    def one(d: Any) -> tuple:
        qp = condensed_qp(T, d)
        ub = jnp.full((N, n_u), 1e30, d.A.dtype)
        lb = jnp.full((N, n_u), -1e30, d.A.dtype)
        if up.size:
            ub = ub.at[:, iu].set(d.bin[:, up])
        if lo.size:
            lb = lb.at[:, il].set(-d.bin[:, lo])
        A = jnp.kron(jnp.eye(N, dtype=d.A.dtype), d.Ain[gen]) if gen.size else None
        bu = d.bin[:, gen].reshape(-1) if gen.size else jnp.zeros((0,), d.A.dtype)
        A = jnp.zeros((0, N * n_u), d.A.dtype) if A is None else A
        upper = jnp.concatenate([ub.reshape(-1), bu])
        lower = jnp.concatenate([lb.reshape(-1), jnp.full_like(bu, -1e30)])
        return qp.H, qp.E, A, upper, lower

    return jax.jit(jax.vmap(one))


# -- DAQP, one process per core ------------------------------------------------------------
_W: dict[str, Any] = {}


def _daqp_init(core: int, topology: Any, data: Any) -> None:
    """Worker start: pinned to ``core``, one XLA device, this worker's cases."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core % (os.cpu_count() or 1)})
    import jax

    jax.config.update("jax_enable_x64", True)
    _W.update(topology=topology, data=data, cond=condenser(topology))


def _daqp_solve(n: int) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Condense and solve the worker's first ``n`` cases: (condense s, total s, u0, exitflags)."""
    import daqp
    import jax

    t0 = time.perf_counter()
    out = jax.block_until_ready(_W["cond"](_take(_W["data"], 0, n)))
    H, f, A, bu, bl = (np.array(x) for x in out)  # writable copies (DAQP's buffers)
    t1 = time.perf_counter()
    n_u = _W["topology"].n_u
    u0 = np.empty((n, n_u))
    flags = np.empty(n, int)
    model = daqp.Model()
    model.setup(H[0], f[0], A[0], bu[0], bl[0])
    for k in range(n):
        if k:
            model.update(H=H[k], f=f[k], bupper=bu[k], blower=bl[k])
        x, _, flag, _ = model.solve()
        u0[k] = x[:n_u]
        flags[k] = flag
    return t1 - t0, time.perf_counter() - t0, u0, flags


class DaqpPool:
    """``workers`` pinned processes; worker w holds cases w, w + workers, ... (so that the
    first n cases split evenly for every n)."""

    def __init__(self, topology: Any, data: Any, workers: int) -> None:
        import jax

        ctx = mp.get_context("spawn")
        env = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = " ".join(
            f for f in env.split() if "xla_force_host_platform_device_count" not in f
        )
        try:
            self.pools = [
                ctx.Pool(
                    1,
                    _daqp_init,
                    (w, topology, jax.tree.map(lambda x, w=w: np.asarray(x)[w::workers], data)),
                )
                for w in range(workers)
            ]
        finally:
            os.environ["XLA_FLAGS"] = env

    def __call__(self, n: int) -> tuple[float, float, np.ndarray, np.ndarray]:
        """Solve the first ``n`` cases over the workers: wall s, condense s (the slowest
        worker's), u0 (n, n_u), DAQP exit flags (n,)."""
        W = len(self.pools)
        counts = [len(range(w, n, W)) for w in range(W)]
        t0 = time.perf_counter()
        jobs = [
            (w, p.apply_async(_daqp_solve, (counts[w],)))
            for w, p in enumerate(self.pools)
            if counts[w]
        ]
        outs = {w: j.get() for w, j in jobs}
        wall = time.perf_counter() - t0
        u0 = np.empty((n, outs[0][2].shape[1]))
        flags = np.empty(n, int)
        for w, o in outs.items():
            u0[w::W], flags[w::W] = o[2], o[3]
        return wall, max(o[0] for o in outs.values()), u0, flags

    def close(self) -> None:
        for p in self.pools:
            p.close()
            p.join()


# -- qpax, vmapped -------------------------------------------------------------------------
def qpax_program(topology: Any, tol: float = QPAX_TOL) -> Any:
    """Jitted: ProblemData (batch) -> u0 (batch, n_u), iterations; condensing inside, the
    variables scaled by their bounds (x = D y, D = (ub - lb) / 2 where both are finite)."""
    import jax
    import jax.numpy as jnp
    import qpax

    cond = condenser(topology)
    n_u = topology.n_u

    def one(H: Any, f: Any, A: Any, bu: Any, bl: Any) -> tuple:
        n = H.shape[0]
        ub, lb = bu[:n], bl[:n]
        fin = (ub < 1e29) & (lb > -1e29)
        D = jnp.where(fin, 0.5 * (ub - lb), 1.0)
        Hs = D[:, None] * H * D[None, :]
        fs = D * f
        eye = jnp.eye(n, dtype=H.dtype)
        keep_u, keep_l = ub < 1e29, lb > -1e29
        G = jnp.concatenate([eye, -eye, A * D[None, :]], axis=0)
        h = jnp.concatenate(
            [jnp.where(keep_u, ub / D, 1e6), jnp.where(keep_l, -lb / D, 1e6), bu[n:]]
        )
        Aeq, beq = jnp.zeros((0, n), H.dtype), jnp.zeros((0,), H.dtype)
        y, _, _, _, conv, its = qpax.solve_qp(
            Hs, fs, Aeq, beq, G, h, solver_tol=tol, max_iter=QPAX_MAX_ITER
        )
        return (D * y)[:n_u], its, conv

    def run(data: Any) -> tuple:
        return jax.vmap(one)(*cond(data))

    return jax.jit(run)


def _case(data: Any, k: int) -> Any:
    import jax

    return jax.tree.map(lambda x: np.asarray(x)[k], data)


def clarabel_u0(topology: Any, data: Any) -> np.ndarray:
    from ampc_jax.reference import _numpy_qp, clarabel_solve

    B = int(np.shape(data.A)[0])
    out = np.full((B, topology.n_u), np.nan)
    for k in range(B):
        sol = clarabel_solve(_numpy_qp(topology, _case(data, k)), REF_EPS)
        out[k] = np.asarray(sol.x)[: topology.n_u]
    return out


def _err(u0: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    e = np.max(np.abs(np.asarray(u0) - ref), axis=-1)
    return float(np.max(e)), float(np.median(e))


def le_setup(cases: Any, tol: float, n_cases: int) -> tuple[Any, Any, Any, Any]:
    """Solver, pair data and pair params for the first ``n_cases`` cases and the rho grid."""
    from ampc_jax.formulations import formulation
    from ampc_jax.sweep import pair_data, pair_params

    T = cases.topology
    solver = formulation("local_explicit", T, max_iter=MAX_ITER, anderson=ANDERSON, **LE_OPTIONS)
    P = len(RHO_GRID)
    grid = solver.params(
        rho=np.asarray(RHO_GRID)[:, None] * np.ones((1, solver.n_rho)),
        tol_primal=tol,
        tol_dual=tol,
    )
    data = _take(cases.data, 0, n_cases)
    return solver, pair_data(data, P), pair_params(grid, n_cases), grid


def tune_tol(cases: Any, ref: np.ndarray, devs: list) -> list[dict[str, Any]]:
    """Worst / median first-step error of Local Explicit for a few tolerances (the choice)."""
    import jax

    from ampc_jax.sweep import sweep_solve

    n = ref.shape[0]
    rows = []
    for tol in TOL_SCAN:
        solver, pd_, pp, _ = le_setup(cases, tol, n)
        res, _ = jax.block_until_ready(sweep_solve(solver, pd_, pp, devices=devs))
        worst, med = _err(np.asarray(res.u0), np.repeat(ref, len(RHO_GRID), axis=0))
        its = np.asarray(res.iterations)
        rows.append({"tol": tol, "err_max": worst, "err_median": med, "it_max": int(its.max())})
        print(f"| {tol:g} | {worst:.2e} | {med:.2e} | {int(its.max())} |", flush=True)
    return rows


# -- 1. throughput -------------------------------------------------------------------------
def section_throughput(args: Any, devs: list) -> dict[str, Any]:
    import jax

    from ampc_jax.sweep import family, sweep_solve

    sizes = list(SMOKE_CASES if args.smoke else CASES + (FULL_CASES if args.full else ()))
    n_max = max(sizes)
    t0 = time.perf_counter()
    cases = family("cruise_step").sample(n_max, 0, horizon=HORIZON)
    print(
        f"sampled {n_max} cruise_step cases (N_p = {HORIZON}) in {time.perf_counter() - t0:.1f} s; "
        "Local Explicit on the exact groups (LST: DTR, RTV, FDB)"
    )
    paper, cases = cases, exact_groups(cases)
    T = cases.topology
    P = len(RHO_GRID)
    n_ref = min(REF_CASES if not args.smoke else 4, n_max)
    ref_data = _take(cases.data, 0, n_ref)
    ref = clarabel_u0(T, ref_data)
    out: dict[str, Any] = {"rho_grid": RHO_GRID, "ref_cases": n_ref}
    tol = LE_TOL
    if args.tune_tol:
        print(
            "\nLocal Explicit's first-step error against its tolerance (Clarabel 1e-13, "
            f"{n_ref} cases x {P} rho)\n"
        )
        print("| tol (Nm^2) | worst error (Nm) | median error (Nm) | iterations max |")
        print("| --- | --- | --- | --- |")
        out["tolerance_scan"] = scan = tune_tol(cases, ref, devs)
        ok = [r["tol"] for r in scan if r["err_max"] < ERR_TARGET]
        if ok:
            tol = max(ok)
    out["le_tol"] = args.le_tol = tol
    q_tol = QPAX_TOL
    if args.tune_tol:
        print(
            f"\nqpax's first-step error against its solver_tol ({n_ref} cases, max_iter "
            f"{QPAX_MAX_ITER})\n"
        )
        print("| solver_tol | worst error (Nm) | median error (Nm) | iterations min / max |")
        print("| --- | --- | --- | --- |")
        scan = []
        for qt in QPAX_TOL_SCAN:
            u_q, it_q, _ = qpax_program(T, qt)(jax.device_put(ref_data, devs[0]))
            w, m = _err(np.asarray(u_q), ref)
            its = np.asarray(it_q)
            scan.append(
                {
                    "tol": qt,
                    "err_max": w,
                    "err_median": m,
                    "it_min": int(its.min()),
                    "it_max": int(its.max()),
                }
            )
            print(f"| {qt:g} | {w:.2e} | {m:.2e} | {its.min()} / {its.max()} |", flush=True)
        out["qpax_tolerance_scan"] = scan
        ok = [r["tol"] for r in scan if r["err_max"] < ERR_TARGET]
        if ok:
            q_tol = max(ok)
    out["qpax_tol"] = q_tol

    # accuracy of every contender on the reference subset
    solver, pd_, pp, _ = le_setup(cases, tol, n_ref)
    res, _ = sweep_solve(solver, pd_, pp, devices=devs)
    acc = {"Local Explicit": _err(np.asarray(res.u0), np.repeat(ref, P, axis=0))}
    if not args.smoke:  # a compile fewer in the smoke run
        s_p, pd_p, pp_p, _ = le_setup(paper, tol, n_ref)
        res_p, _ = sweep_solve(s_p, pd_p, pp_p, devices=devs)
        acc["Local Explicit, the paper's groups (not timed)"] = _err(
            np.asarray(res_p.u0), np.repeat(ref, P, axis=0)
        )
    qp_fn = qpax_program(T, q_tol)
    d0 = jax.device_put(ref_data, devs[0])
    u_q, it_q, conv_q = qp_fn(d0)
    acc["qpax"] = _err(np.asarray(u_q), ref)
    pool = DaqpPool(T, cases.data, len(devs))
    try:
        _, _, u_d, fl = pool(n_ref)
        acc["DAQP"] = _err(u_d, ref)
        print(
            f"\nfirst-step error against Clarabel at {REF_EPS:g} on {n_ref} cases "
            f"(Local Explicit: x {P} rho points, tol {tol:g} Nm^2; qpax: solver_tol {q_tol:g})\n"
        )
        print("| contender | worst error (Nm) | median error (Nm) |")
        print("| --- | --- | --- |")
        for k, (w, m) in acc.items():
            print(f"| {k} | {w:.2e} | {m:.2e} |")
        out["accuracy"] = {k: {"err_max": w, "err_median": m} for k, (w, m) in acc.items()}
        gap = float(np.max(np.abs(u_d - np.asarray(u_q))))
        out["daqp_vs_qpax_max"] = gap
        print(f"\nDAQP against qpax on the same cases: max |u0 difference| {gap:.1e} Nm")
        out["daqp_exitflags_ref"] = np.unique(fl).tolist()
        out["qpax_iterations_ref"] = [int(np.min(it_q)), int(np.max(it_q))]
        out["qpax_converged_ref"] = float(np.mean(np.asarray(conv_q)))

        print(
            f"\nsolves per second (median of {args.repeats} calls after one warm-up; "
            f"Local Explicit: {len(devs)} device(s), {P} rho points per case; DAQP: "
            f"{len(devs)} processes; qpax: 1 device)\n"
        )
        print(
            "| cases | LE pairs | LE solves/s | LE it mean / max | DAQP solves/s "
            "| DAQP condense (ms) | qpax solves/s | LE / DAQP | LE / qpax |"
        )
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        rows = []
        for n in sizes:
            solver, pd_, pp, _ = le_setup(cases, tol, n)
            pd_, pp = jax.device_put((pd_, pp))
            dq = jax.device_put(_take(cases.data, 0, n), devs[0])
            f_le = lambda: jax.block_until_ready(sweep_solve(solver, pd_, pp, devices=devs))  # noqa: B023, E731
            f_q = lambda: jax.block_until_ready(qp_fn(dq))  # noqa: B023, E731
            # warm-up of each, then the timed calls interleaved contender by contender
            res, _ = f_le()
            f_q()
            pool(n)
            t_le, t_q, t_d, t_c = [], [], [], []
            for _ in range(args.repeats):
                t = time.perf_counter()
                res, work = f_le()
                t_le.append(time.perf_counter() - t)
                wall, cond, _, _ = pool(n)
                t_d.append(wall)
                t_c.append(cond)
                t = time.perf_counter()
                f_q()
                t_q.append(time.perf_counter() - t)
            its = np.asarray(res.iterations)
            r = {
                "cases": n,
                "pairs": n * P,
                "le_s": float(np.median(t_le)),
                "daqp_s": float(np.median(t_d)),
                "daqp_condense_s": float(np.median(t_c)),
                "qpax_s": float(np.median(t_q)),
                "le_it_mean": float(its.mean()),
                "le_it_max": int(its.max()),
                "le_converged": float(np.mean(np.asarray(res.converged))),
                "work_waste": float(np.sum(np.asarray(work.computed)))
                / max(float(np.sum(np.asarray(work.needed))), 1.0),
            }
            r["le_solves_per_s"] = n * P / r["le_s"]
            r["daqp_solves_per_s"] = n / r["daqp_s"]
            r["qpax_solves_per_s"] = n / r["qpax_s"]
            r["le_over_daqp"] = r["le_solves_per_s"] / r["daqp_solves_per_s"]
            r["le_over_qpax"] = r["le_solves_per_s"] / r["qpax_solves_per_s"]
            rows.append(r)
            print(
                f"| {n:,} | {n * P:,} | {r['le_solves_per_s']:,.0f} | {r['le_it_mean']:.1f} / "
                f"{r['le_it_max']} | {r['daqp_solves_per_s']:,.0f} | "
                f"{r['daqp_condense_s'] * 1e3:.2f} | {r['qpax_solves_per_s']:,.0f} | "
                f"{r['le_over_daqp']:.2f} | {r['le_over_qpax']:.2f} |",
                flush=True,
            )
        out["rows"] = rows
    finally:
        pool.close()
    return out


# -- 2. waste ------------------------------------------------------------------------------
def section_waste(args: Any, devs: list) -> dict[str, Any]:
    import jax

    from ampc_jax.formulations import formulation
    from ampc_jax.sweep import family, pair_data, pair_params, sweep_solve

    n = 8 if args.smoke else WASTE_CASES
    P = len(RHO_GRID)
    segs = (16,) if args.smoke else SEGMENTS
    print(
        f"\nwaste of vmapped while loops: {n} cases x {P} rho points, "
        f"{len(devs)} device(s), median of {args.repeats} calls\n"
    )
    print("| family | runner | computed / needed | wall (ms) | speed-up |")
    print("| --- | --- | --- | --- | --- |")
    rows = []
    fams = (("cruise_step", {"horizon": HORIZON}), ("stability_step", {}), ("generated", {}))
    for name, opts in fams[2:] if args.smoke else fams:
        cases = family(name).sample(n, 0, **opts)
        T = cases.topology
        tol = args.le_tol if cases.config is not None else 1e-6
        solver = formulation("local_explicit", T, max_iter=MAX_ITER, anderson=ANDERSON)
        grid = solver.params(
            rho=np.asarray(RHO_GRID)[:, None] * np.ones((1, solver.n_rho)),
            tol_primal=tol,
            tol_dual=tol,
        )
        pd_, pp = jax.device_put((pair_data(cases.data, P), pair_params(grid, n)))
        base = None
        for comp, seg in [(False, 16)] + [(True, s) for s in segs]:
            f = lambda: jax.block_until_ready(  # noqa: E731
                sweep_solve(solver, pd_, pp, devices=devs, compaction=comp, segment=seg)  # noqa: B023
            )
            t, (res, work) = _median_time(f, args.repeats)
            waste = float(np.sum(np.asarray(work.computed))) / max(
                float(np.sum(np.asarray(work.needed))), 1.0
            )
            base = t if base is None else base
            label = "vmap while_loop" if not comp else f"compaction, segment {seg}"
            its = np.asarray(res.iterations)
            rows.append(
                {
                    "family": name,
                    "compaction": comp,
                    "segment": seg if comp else None,
                    "waste": waste,
                    "wall_s": t,
                    "speedup": base / t,
                    "tol": tol,
                    "it_mean": float(its.mean()),
                    "it_max": int(its.max()),
                }
            )
            print(
                f"| {name} (N_p {T.horizon}, it mean {its.mean():.1f} / max {its.max()}) "
                f"| {label} | {waste:.2f} | {t * 1e3:.1f} | {base / t:.2f} |",
                flush=True,
            )
    return {"cases": n, "rows": rows}


# -- 3. grad -------------------------------------------------------------------------------
def section_grad(args: Any, devs: list) -> dict[str, Any]:
    import jax
    import jax.numpy as jnp

    from ampc_jax.formulations import formulation
    from ampc_jax.sweep import family

    B = 8 if args.smoke else GRAD_BATCH
    cases = exact_groups(family("cruise_step").sample(B, 1, horizon=HORIZON))
    T = cases.topology
    data = jax.device_put(cases.data, devs[0])
    tol = args.le_tol
    theta = jnp.asarray([0.0, 1.0])  # (log rho scale, relaxation)
    print(
        f"\none gradient against one forward pass: {B} cruise_step cases (N_p {HORIZON}), "
        f"loss = mean |u0|^2 of solve_fixed with K iterations (K: the median to tol {tol:g}), "
        f"gradient wrt (log rho, relaxation), 1 device, median of {args.repeats} calls\n"
    )
    print(
        "| anderson | K (it max to tol) | call | ms | per case (us) | / forward solve_fixed "
        "| / solve to tolerance |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    out: dict[str, Any] = {"batch": B, "tol": tol, "rows": []}
    for anderson in (ANDERSON,) if args.smoke else (ANDERSON, 0):
        solver = formulation("local_explicit", T, max_iter=MAX_ITER, anderson=anderson)
        p_tol = solver.params(tol_primal=tol, tol_dual=tol)
        solve = jax.jit(jax.vmap(solver.solve, in_axes=(0, None)))
        its = np.asarray(solve(data, p_tol).iterations)
        K = max(int(np.median(its)), 1)

        def u0s(theta: Any, solver: Any = solver, p_tol: Any = p_tol, K: int = K) -> Any:
            p = p_tol._replace(
                rho=jnp.exp(theta[0]) * jnp.ones_like(p_tol.rho),
                relaxation=theta[1] + 0.0 * p_tol.relaxation,
            )
            return jax.vmap(lambda d: solver.solve_fixed(d, K, p).u[0])(data)

        def loss(theta: Any, u0s: Any = u0s) -> Any:
            return jnp.mean(jnp.sum(u0s(theta) ** 2, axis=-1)) * 1e-6

        calls = {
            "forward solve_fixed": jax.jit(u0s),
            "jax.grad (reverse mode)": jax.jit(jax.grad(loss)),
            "jax.jacfwd (forward mode, 2 tangents)": jax.jit(jax.jacfwd(loss)),
            "solve to tolerance": lambda th, solve=solve, p_tol=p_tol: solve(data, p_tol),
        }
        if args.smoke:  # one compile fewer
            del calls["jax.jacfwd (forward mode, 2 tangents)"]
        t = {}
        for label, fn in calls.items():
            t[label], _ = _median_time(lambda fn=fn: jax.block_until_ready(fn(theta)), args.repeats)
        g_rev = np.asarray(calls["jax.grad (reverse mode)"](theta))
        fm = calls.get("jax.jacfwd (forward mode, 2 tangents)")
        g_fwd = np.asarray(fm(theta)) if fm is not None else np.full(2, np.nan)
        fwd, tol_t = t["forward solve_fixed"], t["solve to tolerance"]
        for label, v in t.items():
            print(
                f"| {anderson} | {K} ({its.max()}) | {label} | {v * 1e3:.2f} | "
                f"{v / B * 1e6:.1f} | {v / fwd:.2f} | {v / tol_t:.2f} |",
                flush=True,
            )
        out["rows"].append(
            {
                "anderson": anderson,
                "K": K,
                "it_max": int(its.max()),
                "times_s": t,
                "grad_over_forward": t["jax.grad (reverse mode)"] / fwd,
                "grad_over_solve": t["jax.grad (reverse mode)"] / tol_t,
                "jacfwd_over_forward": t.get("jax.jacfwd (forward mode, 2 tangents)", np.nan) / fwd,
                "grad": g_rev.tolist(),
                "grad_fwd_mode": g_fwd.tolist(),
            }
        )
        print(
            f"|  |  | (gradient, reverse / forward mode: ({g_rev[0]:.4e}, {g_rev[1]:.4e}) / "
            f"({g_fwd[0]:.4e}, {g_fwd[1]:.4e})) |  |  |  |  |"
        )
    out["grad_over_forward"] = out["rows"][0]["grad_over_forward"]
    return out


# -- 4. pencil -----------------------------------------------------------------------------
def pencil_programs(solver: Any, grid_rho: Any) -> dict[str, Any]:
    """Per case (vmapped): the library's setup / factorisation P times, and the pencil."""
    import jax
    import jax.numpy as jnp

    from ampc_jax.admm.costs import padded_costs
    from ampc_jax.admm.layout import padded_layout
    from ampc_jax.admm.linalg import block_diag
    from ampc_jax.sweep import pair_data, pair_params

    T = solver.topology
    lay = padded_layout(T)
    N = T.horizon
    kkt = solver.kkt_solve
    P = grid_rho.shape[0]

    def rows_of(d: Any) -> tuple:
        Aix = jnp.pad(d.Ain, ((0, 1), (0, 1)))
        Ain = Aix[lay.rows[:, :, None], lay.cols[:, None, :]]
        return jnp.einsum("jcu,jcv->juv", Ain, Ain)

    def library_setup(data: Any, params: Any) -> Any:
        B = int(np.shape(data.A)[0])
        pd_, pp = pair_data(data, P), pair_params(params, B)
        s = jax.vmap(solver.setup)(pd_, pp)
        return s.Kinv, s.KE

    def library_factor(data: Any) -> Any:
        def one(d: Any) -> Any:
            c = padded_costs(T, d, with_H=not kkt.woodbury)
            AtA = rows_of(d)

            def per(rho: Any) -> Any:
                Kinv = kkt.factor(c, rho[:, None, None] * AtA, N)
                return Kinv, kkt.apply(Kinv, c.E)

            return jax.vmap(per)(grid_rho)

        return jax.vmap(one)(data)

    def pencil(formed: bool) -> Any:
        def run(data: Any) -> Any:
            def one(d: Any) -> Any:
                c = padded_costs(T, d, with_H=True)
                M = block_diag(rows_of(d), N)  # (J, n, n) Abar_j'Abar_j
                L = jnp.linalg.cholesky(c.H)
                Li = jax.lax.linalg.triangular_solve(
                    L,
                    jnp.broadcast_to(jnp.eye(L.shape[-1], dtype=L.dtype), L.shape),
                    left_side=True,
                    lower=True,
                )
                S = Li @ M @ jnp.swapaxes(Li, 1, 2)
                D, V = jnp.linalg.eigh(0.5 * (S + jnp.swapaxes(S, 1, 2)))
                W = jnp.swapaxes(Li, 1, 2) @ V  # K(rho)^-1 = W diag(1 / (1 + rho D)) W'
                WE = jnp.einsum("jab,ja->jb", W, c.E)

                def per(rho: Any) -> Any:
                    s = 1.0 / (1.0 + rho[:, None] * D)
                    KE = jnp.einsum("jab,jb->ja", W, s * WE)
                    if formed:
                        return jnp.einsum("jab,jb,jcb->jac", W, s, W), KE
                    return s, KE

                return W, jax.vmap(per)(grid_rho)

            return jax.vmap(one)(data)

        return run

    return {
        "library setup x P": jax.jit(library_setup),
        "library factorisation x P": jax.jit(library_factor),
        "pencil, factored (W, s)": jax.jit(pencil(False)),
        "pencil, K^-1 formed": jax.jit(pencil(True)),
    }


def section_pencil(args: Any, devs: list) -> dict[str, Any]:
    import jax

    from ampc_jax.formulations import formulation
    from ampc_jax.sweep import family

    n = 8 if args.smoke else PENCIL_CASES
    Ps = (2,) if args.smoke else PENCIL_P
    print(
        f"\nsetup for P rho points: {n} cases, batched, 1 device, median of {args.repeats} "
        "calls; time per case\n"
    )
    print(
        "| family | P | library setup x P (us) | library factorisation x P (us) "
        "| pencil, factored (us) | pencil, K^-1 formed (us) | best |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    rows = []
    fams = (("cruise_step", {"horizon": HORIZON}), ("generated", {}))
    for name, opts in fams[1:] if args.smoke else fams:
        cases = family(name).sample(n, 0, **opts)
        solver = formulation("local_explicit", cases.topology, max_iter=MAX_ITER)
        data = jax.device_put(cases.data, devs[0])
        check = None
        for P in Ps:
            rhos = np.geomspace(0.1, 10.0, P) if P > 1 else np.ones(1)
            rho = np.asarray(rhos)[:, None] * np.ones((1, solver.n_rho))
            params = solver.params(rho=rho)
            progs = pencil_programs(solver, jax.device_put(rho, devs[0]))
            t = {}
            for label, fn in progs.items():
                arg = (data, params) if label.startswith("library setup") else (data,)
                t[label], out = _median_time(
                    lambda fn=fn, arg=arg: jax.block_until_ready(fn(*arg)), args.repeats
                )
                if label == "library factorisation x P":
                    ke_lib = np.asarray(out[1])
                if label == "pencil, K^-1 formed":
                    ke_pen = np.asarray(out[1][1])
            err = float(np.max(np.abs(ke_lib - ke_pen)) / max(np.max(np.abs(ke_lib)), 1e-300))
            check = err if check is None else max(check, err)
            best = min(t, key=t.get)
            r = {
                "family": name,
                "P": P,
                "kkt": solver.kkt_solve.name,
                **{k: v / n for k, v in t.items()},
                "best": best,
                "ke_rel_diff": err,
            }
            rows.append(r)
            cells = " | ".join(f"{t[k] / n * 1e6:.1f}" for k in progs)
            print(f"| {name} ({solver.kkt_solve.name}) | {P} | {cells} | {best} |", flush=True)
        print(
            f"  [{name}: K^-1 E by the pencil against the library's: max relative "
            f"difference {check:.1e}]"
        )
    return {"cases": n, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=SECTIONS, help="default: all four")
    ap.add_argument(
        "--devices",
        type=int,
        default=None,
        help="XLA CPU devices (set before JAX starts; default: what XLA_FLAGS gives)",
    )
    ap.add_argument("--full", action="store_true", help="add 100,000 cases to the throughput")
    ap.add_argument("--repeats", type=int, help="timed calls per contender (default 3; smoke 1)")
    ap.add_argument(
        "--tune-tol",
        action="store_true",
        help="print Local Explicit's error for tolerances 1 .. 1e-8 and pick LE_TOL",
    )
    ap.add_argument("--smoke", action="store_true", help="tiny sizes, a check of the code")
    ap.add_argument(
        "--finish",
        default="none",
        help="Local Explicit's finish: none (default, the paper's iteration) or active_set",
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    LE_OPTIONS.update(finish=args.finish)
    args.le_tol = LE_TOL  # the throughput section's --tune-tol may change it
    if args.repeats is None:
        args.repeats = 1 if args.smoke else 3
    try:
        import daqp  # noqa: F401
        import qpax  # noqa: F401
    except ImportError:
        print("bench_sweep needs daqp and qpax: pip install -e '.[bench]'", file=sys.stderr)
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    run = _meta.Run(_meta.output_path(args, STEM))
    devs = jax.devices()
    print(
        f"jax {jax.__version__}; {len(devs)} device(s); float64; Local Explicit anderson "
        f"{ANDERSON}, max_iter {MAX_ITER}, rho grid {RHO_GRID} x rho*"
    )
    for name in args.only or SECTIONS:
        run.results[name] = {
            "throughput": section_throughput,
            "waste": section_waste,
            "grad": section_grad,
            "pencil": section_pencil,
        }[name](args, devs)
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
