"""Formulation 1's local QPs: the inner ADMM on a cached factorisation against qpax.

Formulations 1 and 2 solve, at every outer ADMM iteration and for every
objective j, the inequality-constrained local QP (eq.F1_primal)::

    min 1/2 u' P_j u + q_j' u   s.t.   Abar_j u <= b_j

with P_j fixed over a control step and q_j, b_j changing every outer
iteration. The package solves it by an inner ADMM on M_j = P_j + sigma_j
Abar_j'Abar_j, inverted once per control step (``ampc_jax.admm.local_qp``),
``inner_iterations`` = k inner steps per outer iteration, warm started from
the last. The alternative measured here is qpax (``qpax.solve_qp``, a
batched, jit-compatible primal-dual interior point in JAX), which cannot be
warm started and refactorises its KKT matrix at every one of its iterations.

Cases: the logged closed-loop steps of the cruise example
(``cruise_lane_change`` with Formulation 1 and the example's tuned solver
settings: Anderson memory 3, over-relaxation 1.5, eps = 1 Nm^2; each step
from the warm state the loop had; the steps taken in a strided order, so
that the first ``--cases`` spread over the whole run) and generated problems
(``ampc_jax.generate.random_problem(seed, J, shared="chain")``, seeds 0, 1,
..., N_p = 10, cold start, the formulation's defaults: eps = 1e-6, at most
500 outer iterations). qpax gets the rows each objective carries (those
involving an agent of S_j), as a dense Abar_j = I (x) A_in,j; the inner ADMM
keeps all rows (zero where j carries none).

1. Whole control steps, the decisive measurement. The same outer algorithm
   (``ConsensusADMM``'s setup, local, global and dual updates, stopping rule,
   Anderson acceleration and projection) with the local QPs solved

   * by the package: ``FullyDistributed(T, inner_iterations=k).solve`` for
     each k of ``--inner``, and once more at the default k with eps times
     ``--tight`` (0.01), so that one run of it is at least as accurate as
     qpax's at the same stopping rule;
   * by qpax: every outer iteration calls ``qpax.solve_qp`` on the J local QPs
     (vmapped over j) at its defaults (1e-5 on the inf-norm of the KKT
     residual, at most 30 iterations), cold; the stopping rule gets the local
     constraint violation as its inner primal residual (this script's
     ``QpaxFormulation1``; on the generated problems it takes the outer
     iteration counts of the package's solver at k -> infinity).

   Printed beside each time: e_u0 = max |u0 - u0*| over the inputs against the
   integrated optimum (``ampc_jax.reference.solve_reference``, Clarabel at
   1e-10; with box rows only, as in every case here, Formulation 1's fixed
   point is that optimum), p95 and max over the cases, and the max relative
   to the largest |u0*|; outer iterations; local QP solves per step (J x
   outer iterations); KKT factorisations per step (the package: the J
   matrices M_j, once; qpax: one per interior-point iteration plus one for
   its start, per local QP); the share of converged steps. "t_qpax / t" is
   the median over the cases of the per-case ratio. "fit a / b": t = a + b
   x (outer iterations) by least squares over the cases, the step's fixed
   part (call, setup, factorisation) and its cost per outer iteration.
2. The local QPs themselves, at the state after ``--outer-at`` outer
   iterations of the package's solver (k = 2): the J local QPs of one outer
   iteration (one call) solved by the inner ADMM (k iterations from the
   previous outer iteration's (s, y), on the cached factorisation), by qpax
   (cold), and the factorisation itself (once per control step). e_loc =
   max |u_j - u_j*| against Clarabel at 1e-10 on the same local QP (the
   inner ADMM is inexact by design: it is not run to convergence inside an
   outer iteration, part 1 shows what that costs).
3. Both, batched: ``jax.vmap`` over ``--batch`` cases (the cruise steps, the
   generated chains with J in ``--batched-j``), time per case. A vmapped
   ``while_loop`` runs every case until the slowest stops, for the outer loop
   and for qpax's own; whole qpax steps are batched only where the batch size
   times their single-step median stays within ``--qpax-batch-budget`` s.

Timing: every function compiled ahead of time (``jax.jit(...).lower(...).compile()``),
its inputs on the device, ``block_until_ready``, float64. The contenders
take turns case by case (the first one rotating), each turn one warm-up call
and the same number of timed calls in a row (``--repeats``, batches
``--batch-repeats``), medians: every contender is timed with its own data in
cache (rule: turns case by case, not call by call; reason: right after a
qpax call the inner ADMM's step is slowed by a cold cache, several times
over; ``bench_qp_peers.py`` times the same way). A call
whose warm-up took over 2 s is timed by that call alone. Run pinned to one
core::

    timeout 900 taskset -c 1 python bench/bench_local_qp.py
    python bench/bench_local_qp.py --smoke   # a quick check; no result file

Needs qpax (the ``bench`` extra: ``pip install -e '.[bench]'``). Result file:
``bench/results/bench_local_qp.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import _meta  # bench/_meta.py, beside this script
import numpy as np

import ampc_jax  # noqa: F401  (XLA:CPU workaround before JAX starts)

STEM = "bench_local_qp"

INNER = (1, 2, 5)  # inner ADMM iterations per outer iteration (whole steps)
LOCAL_INNER = (1, 2, 5, 25)  # inner iterations timed on the local QPs alone
GENERATED = (2, 4)  # objectives J of the generated chains
SINGLE_CASES, SMOKE_SINGLE_CASES = 50, 3  # cases timed one at a time (per case group)
BATCH, SMOKE_BATCH = (100, 1000), (8,)
REPEATS, SMOKE_REPEATS = 3, 2
BATCH_REPEATS = 3  # timed calls per batched contender (the 1000-case qpax steps take seconds)
OUTER_AT = 3
TIGHT = 0.01  # the package's solver once more with its tolerances times this
SMOKE_DURATION = 0.5  # s of cruise closed loop in a --smoke run
QPAX_TOL, QPAX_MAX_ITER = 1e-5, 30  # qpax.solve_qp's defaults
CLARABEL_EPS = 1e-10
LONG_CALL_S = 2.0  # a call longer than this is timed once (the vmapped qpax steps)
QPAX_BATCH_BUDGET_S = 20.0  # vmapped whole qpax steps only below this many s a call (estimated)
BATCHED_J = (2,)  # the generated chains that also run batched (J = 4: minutes a call)


class Case(NamedTuple):
    """One group of cases: a topology, its solver options and stacked per-case data."""

    label: str
    topology: Any
    options: dict  # FullyDistributed's static options besides inner_iterations
    params: Any  # SolverParams
    data: Any  # ProblemData, leading case axis
    warm: Any  # ConsensusState, leading case axis
    u0_ref: np.ndarray  # (B, n_u) integrated optimum's first input
    u_scale: float  # max |u0_ref|, for the relative errors


class QState(NamedTuple):
    """The outer iterate of the qpax variant (no inner state: qpax starts cold)."""

    U: Any
    Z: Any
    gamma: Any
    iteration: Any
    primal: Any
    dual: Any
    ip_iters: Any  # () total qpax iterations (for the factorisation count)


def _stack(items: list) -> Any:
    import jax

    return jax.tree.map(lambda *x: np.stack([np.asarray(a) for a in x]), *items)


def _take(tree: Any, idx: Any) -> Any:
    import jax

    return jax.tree.map(lambda a: np.asarray(a)[idx], tree)


# -- the local QPs in qpax's form -----------------------------------------------------------
def carried_rows(fd: Any) -> np.ndarray:
    """(J, C) the constraint rows objective j carries (those involving an agent of
    S_j), padded with n_c (no row) to the largest count C."""
    touched = fd._touched() > 0
    n_c = touched.shape[1]
    rows = [np.flatnonzero(t) for t in touched]
    C = max(1, max(len(r) for r in rows))
    out = np.full((len(rows), C), n_c, np.int32)
    for j, r in enumerate(rows):
        out[j, : len(r)] = r
    return out


def local_matrices(fd: Any, data: Any, setup: Any) -> tuple[Any, Any, Any]:
    """qpax's form of the local QPs: P_j (J, n, n), Abar_j (J, N C, n) on the rows j
    carries (:func:`carried_rows`) and the mask of the real ones (J, N C).

    P_j = H_j + rho_j I exactly as ``ConsensusADMM.setup`` builds it (Formulation
    1: H_j with the input weights); Abar_j = I (x) A_in,j on j's columns and
    rows (the inner ADMM keeps all n_c rows, zero where j carries none: its
    iteration is elementwise there; qpax's KKT matrix G' D G is not)."""
    import jax.numpy as jnp

    from ampc_jax.admm.costs import padded_costs

    T = fd.topology
    N = T.horizon
    c = padded_costs(T, data)
    n = c.H.shape[-1]
    P = c.H + setup.rho[:, None, None] * jnp.eye(n, dtype=c.H.dtype)
    idx = carried_rows(fd)
    A = jnp.pad(setup.qp.A, ((0, 0), (0, 1), (0, 0)))  # (J, n_c + 1, U), row n_c zero
    Ac = jnp.take_along_axis(A, jnp.asarray(idx)[:, :, None], axis=1)  # (J, C, U)
    J, C, U = Ac.shape
    eye = jnp.eye(N, dtype=A.dtype)
    G = jnp.einsum("kl,jcu->jkclu", eye, Ac).reshape(J, N * C, N * U)
    used = jnp.asarray(np.tile(idx < T.n_c, (1, N)))
    return P, G, used


def carried_rhs(fd: Any, b: Any) -> Any:
    """b_j (J, N, n_c) on the rows j carries, (J, N C) (padding 0)."""
    import jax.numpy as jnp

    idx = jnp.asarray(carried_rows(fd))
    J, N, _ = b.shape
    bp = jnp.pad(b, ((0, 0), (0, 0), (0, 1)))
    return jnp.take_along_axis(bp, idx[:, None, :], axis=2).reshape(J, -1)


def qpax_local(P: Any, q: Any, G: Any, h: Any, used: Any) -> tuple[Any, Any, Any]:
    """qpax on the J local QPs (vmapped over j): u (J, n), its iteration counts and
    convergence flags (J,).

    Rows an objective does not carry (zero in G) get h = 1, an inactive 0 <= 1,
    not the 0 <= 0 that would sit on the boundary of the interior point's cone."""
    import jax
    import jax.numpy as jnp
    import qpax

    n = P.shape[-1]
    h = jnp.where(used, h, 1.0)

    def one(P: Any, q: Any, G: Any, h: Any) -> tuple[Any, Any, Any]:
        A0 = jnp.zeros((0, n), P.dtype)
        b0 = jnp.zeros((0,), P.dtype)
        x, _, _, _, conv, its = qpax.solve_qp(
            P, q, A0, b0, G, h, solver_tol=QPAX_TOL, max_iter=QPAX_MAX_ITER
        )
        return x, its, conv

    return jax.vmap(one)(P, q, G, h)


class QpaxFormulation1:
    """``FullyDistributed``'s outer iteration with the local QPs solved by qpax.

    The setup (rho_j, the rows, the global map), global and dual updates,
    over-relaxation, stopping rule, Anderson acceleration (on (Z, gamma): qpax
    has no inner state to carry) and the result are the package's own; only
    the local update differs."""

    def __init__(self, fd: Any) -> None:
        self.fd = fd

    def step(self, setup: Any, P: Any, G: Any, used: Any, st: QState) -> QState:
        import jax.numpy as jnp

        from ampc_jax.admm.layout import padded_layout

        fd = self.fd
        T = fd.topology
        lay = padded_layout(T)
        J, U = lay.cols.shape
        N = T.horizon
        dt = setup.rho.dtype
        Psel = jnp.asarray(lay.P, dt)
        rho = setup.rho[:, None, None]
        Zj = jnp.einsum("jun,kn->jku", Psel, st.Z)
        q = setup.E + (st.gamma - rho * Zj).reshape(J, N * U)
        b = carried_rhs(fd, setup.b - jnp.einsum("jcn,kn->jkc", setup.Aout, st.Z))
        u, its, _ = qpax_local(P, q, G, b, used)
        viol = jnp.where(used, jnp.maximum(jnp.einsum("jrn,jn->jr", G, u) - b, 0.0), 0.0)
        Uj = u.reshape(J, N, U)
        Ur = Zj + setup.relaxation * (Uj - Zj)
        num = jnp.einsum("jun,jku->kn", Psel, st.gamma + rho * Ur)
        Z = num @ setup.Zmap
        Zn = jnp.einsum("jun,kn->jku", Psel, Z)
        gamma = st.gamma + rho * (Ur - Zn)
        r = Uj - Zn
        dz = Zn - Zj
        if fd.dual_residual == "paper":
            dz = rho * dz
        primal = jnp.sum(r * r, axis=(1, 2)) + jnp.sum(viol * viol, axis=1)
        dual = jnp.sum(dz * dz, axis=(1, 2))
        return QState(
            Uj, Z, gamma, st.iteration + 1, primal, dual, st.ip_iters + jnp.sum(its).astype(int)
        )

    def solve(self, data: Any, params: Any, warm: Any) -> Any:
        import jax.numpy as jnp

        from ampc_jax.admm.runners import run_while

        fd = self.fd
        setup = fd.setup(data, params)  # its factorisation is unused here (XLA drops it)
        P, G, used = local_matrices(fd, data, setup)
        dt = setup.rho.dtype
        J = setup.rho.shape[0]
        st = QState(
            warm.U,
            warm.Z,
            warm.gamma,
            jnp.zeros((), jnp.int32),
            jnp.full((J,), jnp.inf, dt),
            jnp.full((J,), jnp.inf, dt),
            jnp.zeros((), int),
        )
        za, ga = st.Z, st.gamma

        def point(s: QState) -> Any:
            return jnp.concatenate([s.Z.ravel(), s.gamma.ravel()])

        def at(x: Any, s: QState) -> QState:
            return s._replace(
                Z=x[: za.size].reshape(za.shape), gamma=x[za.size :].reshape(ga.shape)
            )

        out = run_while(
            lambda s: self.step(setup, P, G, used, s),
            lambda s: fd.converged(setup, s),
            st,
            fd.max_iter,
            anderson=fd.anderson,
            point=point,
            at=at,
        )
        # the package's result takes its own state: the outer iterate, no inner one
        full = fd.cold_state(out.Z.dtype)._replace(
            **{k: getattr(out, k) for k in QState._fields[:6]}
        )
        res = fd.result(setup, full)
        return res.u[0], res.iterations, res.converged, out.ip_iters


# -- cases ---------------------------------------------------------------------------------
def _reference_u0(T: Any, data: Any, n: int) -> np.ndarray:
    from ampc_jax.reference import solve_reference

    out = []
    for i in range(n):
        r = solve_reference(T, _take(data, i), eps=1e-10)
        out.append(np.asarray(r.u)[0])
    return np.stack(out)


def cruise_case(n_cases: int, n_single: int, duration: float | None) -> Case:
    import jax.numpy as jnp

    from ampc_jax.closed_loop import config_for, controller_for, simulate

    cfg = config_for("cruise_lane_change", formulation="fully_distributed", shadow=False)
    res = simulate("cruise_lane_change", cfg, duration=duration, timing=False)
    ctrl = controller_for(cfg)
    T = ctrl.topology
    log = res.log
    K = int(np.shape(log.t)[0])
    # the steps in a strided order (0, st, 2 st, ..., 1, 1 + st, ...): the first
    # n_single spread over the whole run; then cyclically for larger batches
    st = max(1, K // max(1, n_single))
    order = np.concatenate([np.arange(o, K, st) for o in range(st)])
    idx = order[np.arange(max(n_cases, K)) % K]
    data = _take(log.data, idx)
    warm = _take(log.warm, idx)
    params = cfg.loop_params(jnp.float64).controller.solver
    u0 = _reference_u0(T, data, K)[np.argsort(order)][idx]
    return Case(
        f"cruise_lane_change (N_p={T.horizon}, J={T.n_objectives}, {K} steps)",
        T,
        {"max_iter": cfg.max_iter, "anderson": cfg.anderson},
        params,
        data,
        warm,
        u0,
        float(np.max(np.abs(u0))),
    )


def generated_case(J: int, n_cases: int) -> Case:
    import jax.numpy as jnp

    from ampc_jax.formulations import FullyDistributed
    from ampc_jax.generate import random_problem

    probs = [random_problem(s, J, shared="chain") for s in range(n_cases)]
    T = probs[0].topology
    if any(p.topology != T for p in probs):
        raise RuntimeError("generated problems: the seeds gave different topologies")
    data = _stack([p.data() for p in probs])
    fd = FullyDistributed(T)
    cold = fd.cold_state(jnp.float64)
    warm = _stack([cold] * n_cases)
    u0 = _reference_u0(T, data, n_cases)
    return Case(
        f"generated chain (N_p={T.horizon}, J={J}, {n_cases} seeds)",
        T,
        {},
        fd.params(dtype=jnp.float64),
        data,
        warm,
        u0,
        float(np.max(np.abs(u0))),
    )


# -- timing --------------------------------------------------------------------------------
def _compile(fn: Callable, *args: Any) -> tuple[Any, float]:
    import jax

    t0 = time.perf_counter()
    c = jax.jit(fn).lower(*args).compile()
    return c, time.perf_counter() - t0


def in_turns(fns: dict[str, Any], args: dict[str, tuple], repeats: int, turn: int = 0):
    """Median time of each compiled function over ``repeats`` calls, and its output.

    The contenders take turns (the first one rotating with ``turn``); each turn
    is one warm-up call and ``repeats`` timed calls in a row, so that every
    contender is timed with its own data in cache (as ``bench_qp_peers.py``).
    A call whose warm-up took over ``LONG_CALL_S`` is timed by that call alone."""
    import jax

    keys = list(fns)
    keys = keys[turn % len(keys) :] + keys[: turn % len(keys)]
    out = {}
    for k in keys:
        t0 = time.perf_counter()
        o = jax.block_until_ready(fns[k](*args[k]))
        ts = [time.perf_counter() - t0]
        if ts[0] > LONG_CALL_S:
            out[k] = (ts[0], o)
            continue
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            o = jax.block_until_ready(fns[k](*args[k]))
            ts.append(time.perf_counter() - t0)
        out[k] = (float(np.median(ts)), o)
    return {k: out[k] for k in fns}


def _contenders(case: Case, inner: tuple, tight: float) -> dict[str, Callable]:
    """The package's solver for each k of ``inner`` (and at the default k with its
    tolerances times ``tight``, unless 0), then the qpax variant."""
    from ampc_jax.formulations import FullyDistributed

    T = case.topology
    out: dict[str, Callable] = {}
    runs = [(f"inner ADMM, k={k}", k, 1.0) for k in inner]
    if tight > 0:
        k = FullyDistributed.inner_iterations
        runs.append((f"inner ADMM, k={k}, eps x {tight:g}", k, tight))
    for label, k, scale in runs:
        fd = FullyDistributed(T, inner_iterations=k, **case.options)

        def lib(d: Any, p: Any, w: Any, fd: Any = fd, scale: float = scale) -> tuple:
            if scale != 1.0:
                p = p._replace(tol_primal=p.tol_primal * scale, tol_dual=p.tol_dual * scale)
            r = fd.solve(d, p, w)
            return r.u[0], r.iterations, r.converged, r.iterations * 0

        out[label] = lib
    q = QpaxFormulation1(FullyDistributed(T, **case.options))
    out["qpax"] = q.solve
    return out


def _step_row(case: Case, label: str, u0: Any, its: Any, conv: Any, ip: Any, lib: bool):
    e = np.max(np.abs(np.asarray(u0) - case.u0_ref[: len(np.atleast_2d(u0))]), axis=-1)
    its = np.atleast_1d(np.asarray(its))
    J = case.topology.n_objectives
    solves = J * its
    fact = np.full(its.shape, float(J)) if lib else np.atleast_1d(ip) + solves
    return {
        "case": case.label,
        "method": label,
        "e_u0_p95": float(np.percentile(e, 95)),
        "e_u0_max": float(np.max(e)),
        "e_u0_rel_max": float(np.max(e) / max(case.u_scale, 1e-300)),
        "outer_p50": float(np.median(its)),
        "outer_p95": float(np.percentile(its, 95)),
        "local_solves_p50": float(np.median(solves)),
        "factorisations_p50": float(np.median(fact)),
        "converged": float(np.mean(np.asarray(conv))),
    }


def _fit(its: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    """t = a + b its by least squares over the cases: the step's fixed part (call,
    setup, factorisation) and its cost per outer iteration; b alone (a = nan) when
    every case took the same number of iterations."""
    its = np.asarray(its, float)
    if np.ptp(its) == 0:
        return float("nan"), float(np.median(t) / max(its[0], 1.0))
    b, a = np.polyfit(its, t, 1)
    return float(a), float(b)


def whole_steps(case: Case, inner: tuple, tight: float, n_single: int, repeats: int) -> list[dict]:
    """Part 1: single control steps, case by case, contenders in turns."""
    import jax

    funcs = _contenders(case, inner, tight)
    d0, w0 = _take(case.data, 0), _take(case.warm, 0)
    compiled, t_comp = {}, {}
    for k, f in funcs.items():
        compiled[k], t_comp[k] = _compile(f, d0, case.params, w0)
    n = min(n_single, len(case.u0_ref))
    t: dict[str, list] = {k: [] for k in funcs}
    res: dict[str, list] = {k: [] for k in funcs}
    for i in range(n):
        d, w = jax.device_put((_take(case.data, i), _take(case.warm, i)))
        out = in_turns(compiled, {k: (d, case.params, w) for k in funcs}, repeats, i)
        for k, (ti, o) in out.items():
            t[k].append(ti)
            res[k].append([np.asarray(x) for x in o])
    rows = []
    tq = np.asarray(t["qpax"])
    for k in funcs:
        u0, its, conv, ip = (np.stack(c) for c in zip(*res[k], strict=True))
        row = _step_row(case, k, u0, its, conv, ip, k != "qpax")
        ti = np.asarray(t[k])
        a, b = _fit(its, ti)
        row.update(
            mode=f"single ({n})",
            cases=n,
            t_us=float(np.median(ti) * 1e6),
            t_fixed_us=a * 1e6,
            t_outer_us=b * 1e6,
            qpax_over=float(np.median(tq / ti)),
            compile_s=round(t_comp[k], 2),
        )
        rows.append(row)
    return rows


def batched_steps(
    case: Case,
    inner: tuple,
    tight: float,
    sizes: tuple,
    repeats: int,
    t_qpax: float,
    budget: float,
) -> list[dict]:
    """Part 3a: vmapped control steps, time per case. qpax only where B times its
    single-step median ``t_qpax`` is within ``budget`` s (a lower bound of the
    vmapped call: the batched local QPs cost qpax no less per case, part 3b)."""
    import jax

    rows = []
    for B in sizes:
        funcs = _contenders(case, inner, tight)
        if B * t_qpax > budget:
            del funcs["qpax"]
            print(
                f"  [{case.label}: vmap {B}: qpax left out, >= {B * t_qpax:.0f} s a call]",
                file=sys.stderr,
                flush=True,
            )
        d, w = jax.device_put((_take(case.data, np.arange(B)), _take(case.warm, np.arange(B))))
        compiled, t_comp = {}, {}
        for k, f in funcs.items():
            fb = jax.vmap(f, in_axes=(0, None, 0))
            compiled[k], t_comp[k] = _compile(fb, d, case.params, w)
        out = in_turns(compiled, {k: (d, case.params, w) for k in funcs}, repeats)
        tq = out["qpax"][0] if "qpax" in out else None
        for k, (ti, o) in out.items():
            u0, its, conv, ip = (np.asarray(x) for x in o)
            row = _step_row(case, k, u0, its, conv, ip, k != "qpax")
            row.update(
                mode=f"vmap {B}",
                cases=B,
                t_us=float(ti / B * 1e6),
                t_fixed_us=None,
                t_outer_us=None,
                qpax_over=None if tq is None else float(tq / ti),
                compile_s=round(t_comp[k], 2),
            )
            rows.append(row)
    return rows


# -- the local QPs alone ---------------------------------------------------------------------
def local_instances(case: Case, n: int, outer_at: int) -> dict[str, Any]:
    """The J local QPs of outer iteration ``outer_at + 1`` for the first n cases:
    the package's (qp, q, b, s, y) and qpax's (P, q, G, h, used), stacked."""
    import jax
    import jax.numpy as jnp

    from ampc_jax.admm.layout import padded_layout
    from ampc_jax.formulations import FullyDistributed

    fd = FullyDistributed(case.topology, inner_iterations=2, **case.options)
    T = case.topology
    lay = padded_layout(T)
    J, U = lay.cols.shape
    N = T.horizon

    def one(d: Any, w: Any) -> dict[str, Any]:
        setup = fd.setup(d, case.params)
        st = fd.run_fixed(setup, fd.init(setup, w), outer_at)
        P, G, used = local_matrices(fd, d, setup)
        Psel = jnp.asarray(lay.P, d.A.dtype)
        rho = setup.rho[:, None, None]
        Zj = jnp.einsum("jun,kn->jku", Psel, st.Z)
        q = setup.E + (st.gamma - rho * Zj).reshape(J, N * U)
        b = setup.b - jnp.einsum("jcn,kn->jkc", setup.Aout, st.Z)
        return {
            "qp": setup.qp,
            "P": P,
            "G": G,
            "used": used,
            "q": q,
            "b": b,
            "h": carried_rhs(fd, b),
            "s": st.s,
            "y": st.y,
        }

    d, w = _take(case.data, np.arange(n)), _take(case.warm, np.arange(n))
    return jax.tree.map(np.asarray, jax.jit(jax.vmap(one))(d, w))


def clarabel_local(inst: dict[str, Any], i: int) -> np.ndarray:
    """Clarabel's solutions (J, n) of case i's local QPs (only the rows j carries)."""
    from ampc_jax.problem import CondensedQP
    from ampc_jax.reference import clarabel_solve

    out = []
    for j in range(inst["P"].shape[1]):
        m = inst["used"][i, j]
        qp = CondensedQP(
            inst["P"][i, j],
            inst["q"][i, j],
            inst["G"][i, j][m],
            inst["h"][i, j][m],
        )
        sol = clarabel_solve(qp, eps=CLARABEL_EPS)
        out.append(np.asarray(sol.x))
    return np.stack(out)


def _local_fns(local_inner: tuple) -> dict[str, Callable]:
    from ampc_jax.admm.local_qp import InnerState, factor, iterate

    fns: dict[str, Callable] = {}
    for k in local_inner:

        def admm(x: dict, k: int = k) -> tuple:
            u, _, _, _ = iterate(x["qp"], x["q"], x["b"], InnerState(x["s"], x["y"]), k)
            return u, u[:, 0] * 0, u[:, 0] * 0 + 1

        fns[f"inner ADMM, k={k} (warm)"] = admm

    def qp(x: dict) -> tuple:
        return qpax_local(x["P"], x["q"], x["G"], x["h"], x["used"])

    fns["qpax (cold)"] = qp

    def fac(x: dict) -> tuple:
        N = x["b"].shape[1]
        qp = factor(x["P"], x["qp"].A, x["qp"].sigma, N)
        return qp.Minv, qp.sigma * 0, qp.sigma * 0 + 1

    fns["factor M_j (once per step)"] = fac
    return fns


def local_qps(
    case: Case,
    local_inner: tuple,
    n_single: int,
    sizes: tuple,
    repeats: int,
    b_repeats: int,
    outer_at: int,
) -> list[dict]:
    """Parts 2 and 3b: the J local QPs of one outer iteration, one case and batched."""
    import jax

    n_all = max([n_single, *sizes])
    inst = local_instances(case, n_all, outer_at)
    refs = [clarabel_local(inst, i) for i in range(n_all)]
    ref = np.stack(refs)  # (n, J, n)
    fns = _local_fns(local_inner)
    rows = []

    def errs(u: np.ndarray, lo: int, hi: int) -> np.ndarray:
        return np.max(np.abs(u - ref[lo:hi]), axis=(-1, -2))

    # one case at a time
    x0 = _take(inst, 0)
    compiled = {k: _compile(f, x0)[0] for k, f in fns.items()}
    t: dict[str, list] = {k: [] for k in fns}
    outs: dict[str, list] = {k: [] for k in fns}
    n = min(n_single, n_all)
    for i in range(n):
        x = jax.device_put(_take(inst, i))
        o = in_turns(compiled, {k: (x,) for k in fns}, repeats, i)
        for k, (ti, oi) in o.items():
            t[k].append(ti)
            outs[k].append([np.asarray(v) for v in oi])
    tq = np.asarray(t["qpax (cold)"])
    for k in fns:
        u, its, conv = (np.stack(c) for c in zip(*outs[k], strict=True))
        row = {"case": case.label, "method": k, "mode": f"single ({n})", "cases": n}
        ti = np.asarray(t[k])
        row["t_us"] = float(np.median(ti) * 1e6)
        row["qpax_over"] = float(np.median(tq / ti))
        if not k.startswith("factor"):
            e = errs(u, 0, n)
            row.update(e_loc_p95=float(np.percentile(e, 95)), e_loc_max=float(np.max(e)))
        if k.startswith("qpax"):
            row.update(
                ip_iters_p50=float(np.median(its)),
                ip_iters_max=float(np.max(its)),
                qpax_converged=float(np.mean(conv)),
            )
        rows.append(row)
    # batched
    for B in sizes:
        xb = jax.device_put(_take(inst, np.arange(B)))
        compiled = {k: _compile(jax.vmap(f), xb)[0] for k, f in fns.items()}
        o = in_turns(compiled, {k: (xb,) for k in fns}, b_repeats)
        tq = o["qpax (cold)"][0]
        for k, (ti, oi) in o.items():
            u, its, conv = (np.asarray(v) for v in oi)
            row = {"case": case.label, "method": k, "mode": f"vmap {B}", "cases": B}
            row["t_us"] = float(ti / B * 1e6)
            row["qpax_over"] = float(tq / ti)
            if not k.startswith("factor"):
                e = errs(u, 0, B)
                row.update(e_loc_p95=float(np.percentile(e, 95)), e_loc_max=float(np.max(e)))
            if k.startswith("qpax"):
                row.update(
                    ip_iters_p50=float(np.median(its)),
                    ip_iters_max=float(np.max(its)),
                    qpax_converged=float(np.mean(conv)),
                )
            rows.append(row)
    return rows


# -- output ----------------------------------------------------------------------------------
def _g(x: Any, fmt: str = ".2g") -> str:
    return "-" if x is None else format(x, fmt)


def _pct(x: Any) -> str:
    return "-" if x is None else f"{x:.0%}"


def print_steps(rows: list[dict]) -> None:
    print(
        "| case | mode | method | t / step (us) | **t_qpax / t** | fit a + b its: a / b (us) "
        "| e_u0 p95 / max | e_u0 max / max abs u0* | outer its p50 / p95 "
        "| local QP solves / step | KKT factorisations / step | converged |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['case']} | {r['mode']} | {r['method']} | {r['t_us']:.1f} "
            f"| {_g(r['qpax_over'], '.2f')} | {_g(r['t_fixed_us'], '.0f')} / "
            f"{_g(r['t_outer_us'], '.2f')} "
            f"| {_g(r['e_u0_p95'])} / {_g(r['e_u0_max'])} "
            f"| {_g(r['e_u0_rel_max'])} | {r['outer_p50']:.0f} / {r['outer_p95']:.0f} "
            f"| {r['local_solves_p50']:.0f} | {r['factorisations_p50']:.0f} "
            f"| {r['converged']:.0%} |",
            flush=True,
        )


def print_local(rows: list[dict]) -> None:
    print(
        "| case | mode | the J local QPs of one outer iteration | t (us) | **t_qpax / t** "
        "| e_loc p95 / max | qpax iterations p50 / max | qpax converged |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        it = f"{r['ip_iters_p50']:.0f} / {r['ip_iters_max']:.0f}" if "ip_iters_p50" in r else "-"
        print(
            f"| {r['case']} | {r['mode']} | {r['method']} | {r['t_us']:.2f} "
            f"| {r['qpax_over']:.2f} | {_g(r.get('e_loc_p95'))} / {_g(r.get('e_loc_max'))} "
            f"| {it} | {_pct(r.get('qpax_converged'))} |",
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--inner",
        type=int,
        nargs="+",
        help=f"inner ADMM iterations per outer iteration, whole steps (default: "
        f"{' '.join(map(str, INNER))}; --smoke: 2)",
    )
    ap.add_argument(
        "--local-inner",
        type=int,
        nargs="+",
        help=f"inner iterations timed on the local QPs alone (default: "
        f"{' '.join(map(str, LOCAL_INNER))}; --smoke: 2)",
    )
    ap.add_argument(
        "--generated",
        type=int,
        nargs="*",
        help=f"objectives J of the generated chains, none for none (default: "
        f"{' '.join(map(str, GENERATED))}; --smoke: 2)",
    )
    ap.add_argument(
        "--no-cruise", action="store_true", help="leave out the cruise example (default: in)"
    )
    ap.add_argument(
        "--cases",
        type=int,
        help=f"cases timed one at a time per case group (default: {SINGLE_CASES}; "
        f"--smoke: {SMOKE_SINGLE_CASES})",
    )
    ap.add_argument(
        "--batch",
        type=int,
        nargs="*",
        help=f"vmapped batch sizes, none for none (default: {' '.join(map(str, BATCH))}; "
        f"--smoke: {' '.join(map(str, SMOKE_BATCH))})",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        help=f"timed calls per contender and case, one at a time, medians (default: "
        f"{REPEATS}; --smoke: {SMOKE_REPEATS})",
    )
    ap.add_argument(
        "--batch-repeats",
        type=int,
        help=f"timed calls per contender and batch, medians (default: {BATCH_REPEATS}; "
        f"--smoke: {SMOKE_REPEATS})",
    )
    ap.add_argument(
        "--qpax-batch-budget",
        type=float,
        default=QPAX_BATCH_BUDGET_S,
        help="vmapped whole qpax steps only where batch size x its single-step median "
        f"stays within this many seconds, otherwise the inner ADMM alone (default: "
        f"{QPAX_BATCH_BUDGET_S:g}; the local QPs alone are batched at every size)",
    )
    ap.add_argument(
        "--batched-j",
        type=int,
        nargs="*",
        help=f"the generated chains (by J) that also run batched; the cruise example always "
        f"does (default: {' '.join(map(str, BATCHED_J))}; --smoke: none)",
    )
    ap.add_argument(
        "--tight",
        type=float,
        default=TIGHT,
        help=f"one more whole-step run of the package's solver at its default k with "
        f"the tolerances times this factor, for an accuracy at least qpax's; 0 for "
        f"none (default: {TIGHT:g})",
    )
    ap.add_argument(
        "--outer-at",
        type=int,
        default=OUTER_AT,
        help=f"outer iterations before the local QPs are taken (default: {OUTER_AT})",
    )
    ap.add_argument(
        "--smoke",
        action="store_true",
        help=f"a quick check of the same code (default: off): {SMOKE_DURATION:g} s of "
        "cruise, the smoke defaults above; writes no result file unless --out is given",
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    sm = args.smoke
    inner = tuple(args.inner or ((2,) if sm else INNER))
    local_inner = tuple(args.local_inner or ((2,) if sm else LOCAL_INNER))
    generated = (
        tuple((2,) if sm else GENERATED) if args.generated is None else tuple(args.generated)
    )
    n_single = args.cases or (SMOKE_SINGLE_CASES if sm else SINGLE_CASES)
    sizes = tuple(SMOKE_BATCH if sm else BATCH) if args.batch is None else tuple(args.batch)
    repeats = args.repeats or (SMOKE_REPEATS if sm else REPEATS)
    b_repeats = args.batch_repeats or (SMOKE_REPEATS if sm else BATCH_REPEATS)
    for name, vals in (("inner", inner), ("local-inner", local_inner)):
        if any(v < 1 for v in vals):
            print(f"--{name}: expected integers >= 1, got {vals}", file=sys.stderr)
            return 2
    try:
        import qpax  # noqa: F401
    except ImportError:
        print(
            "bench_local_qp needs qpax: pip install qpax (or pip install -e '.[bench]')",
            file=sys.stderr,
        )
        return 2
    import jax

    jax.config.update("jax_enable_x64", True)
    from importlib.metadata import version

    run = _meta.Run(_meta.output_path(args, STEM))
    run.meta["qpax"] = version("qpax")
    n_cases = max([n_single, *sizes])
    print(
        f"jax {jax.__version__}, qpax {version('qpax')}, float64; qpax at its defaults "
        f"(tol {QPAX_TOL:g}, max_iter {QPAX_MAX_ITER}); medians of {repeats} calls per "
        f"contender and case ({b_repeats} per batch), the contenders in turns\n",
        flush=True,
    )
    batched_j = set((() if sm else BATCHED_J) if args.batched_j is None else args.batched_j)
    cases = []  # (case, batch sizes)
    if not args.no_cruise:
        cases.append((cruise_case(n_cases, n_single, SMOKE_DURATION if sm else None), sizes))
    for J in generated:
        bs = sizes if J in batched_j else ()
        cases.append((generated_case(J, max([n_single, *bs])), bs))
    step_rows, local_rows = [], []
    for c, bs in cases:
        print(f"  [{c.label}: whole steps]", file=sys.stderr, flush=True)
        rows = whole_steps(c, inner, args.tight, n_single, repeats)
        step_rows += rows
        t_q = next(r["t_us"] for r in rows if r["method"] == "qpax") * 1e-6
        if bs:
            step_rows += batched_steps(
                c, inner, args.tight, bs, b_repeats, t_q, args.qpax_batch_budget
            )
        print(f"  [{c.label}: local QPs]", file=sys.stderr, flush=True)
        local_rows += local_qps(c, local_inner, n_single, bs, repeats, b_repeats, args.outer_at)
    print("Whole control steps (Formulation 1), the same outer algorithm, two local solvers:\n")
    print_steps(step_rows)
    print(
        f"\nThe local QPs alone, at outer iteration {args.outer_at + 1} (one call: all J "
        "objectives):\n"
    )
    print_local(local_rows)
    run.results = {
        "inner": list(inner),
        "local_inner": list(local_inner),
        "cases_single": n_single,
        "batch": list(sizes),
        "repeats": repeats,
        "batch_repeats": b_repeats,
        "qpax_batch_budget_s": args.qpax_batch_budget,
        "batched_j": sorted(batched_j),
        "long_call_s": LONG_CALL_S,
        "outer_at": args.outer_at,
        "tight": args.tight,
        "qpax_tol": QPAX_TOL,
        "qpax_max_iter": QPAX_MAX_ITER,
        "clarabel_eps": CLARABEL_EPS,
        "whole_steps": step_rows,
        "local_qps": local_rows,
    }
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
