"""Local Explicit against the strongest CPU QP peers on a time-varying QP with general rows.

Problem: the cruise-control model of ``bench_local_explicit.py`` (3 states;
agents DTR, RTV, FDB = 4 inputs; objectives LST and YRT on the groups derived
from the model, ``GROUPS`` there), re-linearised at a new operating point
every control step (its ``drive``: consecutive steps are close, warm started
along each drive), plus two general rows per prediction step::

    T_DTR + T_FDB,l + T_FDB,r <= 1500 Nm,    -(T_DTR + T_FDB,l + T_FDB,r) <= 2500 Nm

(``Topology.build(..., general_rows=[G])``, ``make_data(..., G=G, g=g)``).
The drives are used as they are: they leave a general row active at the
reference solution in about 70 % of the steps (printed by every run; the
issue asks for 56 % to 76 %), so no operating point or v_ref is scaled.

Truth: Clarabel at 1e-13 on the unscaled condensed QP
(:func:`~ampc_jax.problem.condensed_qp`). Accuracy is each contender's
first-step error max_i |u0_i - u0_i*| (Nm), worst and median, printed beside
every time; the common target is a worst error under ``ERR_TARGET`` = 1e-2 Nm.

Calibration (per N_p, printed as scans): on the first ``REF_CASES`` drives of
the throughput cases (``--steps`` steps each, warm along each drive) every
iterative contender takes the loosest setting of its own knob whose worst
error is under the target (the best one, flagged, where none is):

* Local Explicit, ``LocalExplicit(T, max_iter=2000, kkt=K)`` with the "tuned"
  configuration of bench_local_explicit (rho = (1, 0.1) x eq.opt_ro's rho*,
  relaxation 1.6): eps_r = eps_s (Nm^2) from ``LE_TOL_SCAN``, loose to tight,
  for every K and dtype (the scan stops at the first tolerance under the
  target, or once fewer than ``CONVERGED_MIN`` of the steps converge). Where
  none reaches the target (float32 has an error floor on these QPs) it takes
  the loosest tolerance within ``LE_FLOOR_FACTOR`` of the floor, flagged;
* OSQP (native two-sided rows l <= Ax <= u: the bounds and one row per step
  -2500 <= T_DTR + T_FDB <= 1500; unscaled, polish off, warm started): eps_abs
  = eps_rel from ``OSQP_EPS_SCAN``;
* proxsuite (ProxQP dense, box constraints, warm start from the previous
  result, variables scaled by their bounds x = D y, D = (ub - lb) / 2):
  eps_abs from ``PROX_EPS_SCAN`` (eps_rel 0);
* qpax (``solve_qp``, interior point, variables scaled by their bounds and the
  general rows normalised): a fixed iteration count from ``QPAX_ITERS`` (its
  vmapped batch runs to its slowest case anyway);
* DAQP (dual active set, ``daqp.Model``: ``setup`` once, ``update`` +
  ``solve`` per step, warm from the previous working set; simple bounds plus
  the two-sided general rows): exact, no knob.

The peers solve the condensed QP; condensing (the re-linearised model ->
H, f, bounds, rows) is part of their cost, timed separately and together:
per step the jitted ``data_of`` + ``condensed_qp`` (one call, outputs to
numpy), batched the same program jitted and mapped in chunks of
``COND_BATCH`` (``jax.lax.map(..., batch_size=32)``: 2x faster than one
``vmap`` of the whole chunk), one XLA device per worker process. Local
Explicit's step contains its own re-linearisation and setup.

1. ``latency`` -- one time-varying full step on one core, N_p = 10 and 20:
   Local Explicit's full step (data -> setup -> iterate, ahead-of-time
   compiled, warm along the drive) for every K and dtype, its data, setup
   (``solver.setup`` compiled alone) and iterations alone; the condensing
   alone; DAQP update + solve; DAQP + condensing in one timed call; proxsuite;
   OSQP. ``LAT_DRIVES`` drives of ``LAT_STEPS`` steps (a drive of S steps is S
   solves: step 0 cold and untimed for everyone, steps 1 .. S-1 timed), every
   call single and timed alone (no best-of-n for anyone), interleaved in
   blocks of ``BLOCK`` consecutive steps whose contender order rotates from
   block to block. Median and p99 over the timed steps. The section needs one
   core: when this process may run on more, it runs in a child process pinned
   to the last core of its affinity (as ``taskset -c 1`` on two cores), its
   printout relayed.
2. ``throughput`` -- batches of B cases, each a drive of ``--steps`` steps
   (default 10), B = 1, 10, 100, 1,000, 10,000 (100,000 with ``--full``), N_p
   = 10 and 20: Local Explicit vmapped over every CPU device (one per core of
   this process's affinity, set before JAX starts; ``ampc_jax.batch.map_scenarios``,
   chunks of ``VMAP_CHUNK`` drives, at most ``CALL_CASES`` cases per compiled
   call) per K and dtype; DAQP, OSQP and proxsuite one pinned process per core,
   each condensing (batched, jitted, chunks of ``WORKER_CHUNK`` cases) and
   solving its share (solve alone = the slowest worker's solve time; with
   condensing = the call's wall time); proxsuite's ``solve_in_parallel``
   (``BatchQP``, which has no box form: the bounds as general rows; OpenMP
   over the cores, condensing sharded over the devices); qpax vmapped on one
   device (two devices running its batched LAPACK calls can deadlock). One
   warm-up call per contender and compiled size, then ``--repeats`` calls (1
   from 10,000 cases on) interleaved, the order rotated, median. A peer
   whose call would take more than ``PEER_BUDGET_S`` (from its previous size)
   is skipped at that size (printed). Steps/s, the ratios LE / DAQP (solve
   alone) and LE / (DAQP + condensing), errors on the first ``REF_CASES``
   cases (all their steps), Local Explicit's data + setup alone against its
   full step, and its flop rate: XLA's flop count of the batched program
   (``cost_analysis()['flops']``; it counts a loop body once, whatever its trip
   count) and an estimate counting every solve (the flops of one data + setup
   plus the mean iterations times one iteration's, from the cost analysis of
   those pieces), each per second and as a share of this machine's matmul
   peak (a 4096 x 4096 matmul in JAX sharded over all devices, best of 3).

Targets, printed as PASS / MISS lines: Local Explicit's throughput >= 2x
DAQP's QP solve alone at 1,000 and 10,000 cases, N_p 10 and 20, with a worst
error < 1e-2 Nm (the fastest K and dtype that reaches it); Local Explicit's
single full step (median) <= DAQP update + solve + condensing (timed
together).

Run (``--kkt``: default every name in ``ampc_jax.admm.kkt.KKT_SOLVES`` but
"auto" that ``select_kkt`` accepts for the topology)::

    python bench/bench_peers.py                   # both sections (about 40 min)
    python bench/bench_peers.py --full            # adds 100,000 cases
    taskset -c 1 python bench/bench_peers.py --only latency
    python bench/bench_peers.py --horizons 10 --max-batch 1000 --out /tmp/peers.json
    python bench/bench_peers.py --finish active_set --rho-method carried   # the exact
                                                  # finish and the carried rho (LE's options)
    python bench/bench_peers.py --smoke           # N_p 10, float64, the "auto" K, one
                                                  # 6-step latency drive, batches 1 and
                                                  # 10 of 3-step drives (about 50 s)

Needs daqp, proxsuite and qpax (a missing one is skipped, said so). Result
file: ``bench/results/bench_peers.json`` (``--out``; ``bench/_meta.py``; a
``--smoke`` run writes none unless ``--out`` is given). docs/bench_peers.md
describes the output.
"""

from __future__ import annotations

import os
import sys

from ampc_jax.results import Status  # noqa: E402


def _preset() -> None:
    """Before JAX starts: pin this process (``--pin CORE``: the latency child) and give
    XLA one CPU device per core of its affinity (``--devices N`` overrides)."""
    argv = sys.argv
    if "--pin" in argv and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {int(argv[argv.index("--pin") + 1])})
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    if "--devices" in argv:
        n = int(argv[argv.index("--devices") + 1])
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


if __name__ == "__main__":
    _preset()

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import multiprocessing as mp  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import _meta  # noqa: E402  (bench/_meta.py, beside this script)
import bench_local_explicit as ble  # noqa: E402  (the cruise problem, beside this script)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import ampc_jax  # noqa: E402, F401  (XLA:CPU workaround before JAX starts)

jax.config.update("jax_enable_x64", True)

from ampc_jax.admm import kkt as kkt_module  # noqa: E402
from ampc_jax.batch import map_scenarios  # noqa: E402
from ampc_jax.formulations import LocalExplicit  # noqa: E402
from ampc_jax.problem import CondensedQP, Topology, condensed_qp  # noqa: E402
from ampc_jax.reference import clarabel_solve  # noqa: E402
from ampc_jax.vehicle import CRUISE, CruiseSettings  # noqa: E402

STEM = "bench_peers"
SECTIONS = ("latency", "throughput")

# -- the problem -----------------------------------------------------------------------------
G_ROW = np.array([1.0, 0.0, 1.0, 1.0])  # T_DTR + T_FDB,l + T_FDB,r (inputs DTR, RTV, FDB_l, FDB_r)
G_UPPER, G_LOWER = 1500.0, -2500.0  # Nm
G_ROWS = np.stack([G_ROW, -G_ROW])  # G (2, n_u): G u <= g
G_RHS = np.array([G_UPPER, -G_LOWER])  # g (2,)
N_U = G_ROW.size
ACTIVE_TOL = 1e-3  # Nm: a general row within this of its bound counts as active
ACTIVE_RANGE = (0.56, 0.76)  # the share of steps with an active general row

# -- accuracy and settings -------------------------------------------------------------------
REF_EPS = 1e-13
ERR_TARGET = 1e-2  # Nm, worst first-step error
MAX_ITER = ble.MAX_ITER  # 2000
TUNED = ble.TUNED  # rho (1, 0.1) x rho*, relaxation 1.6
LE_TOL_SCAN = (1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5, 3e-6, 1e-6, 1e-7, 1e-8)
OSQP_EPS_SCAN = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9)
OSQP_MAX_ITER = 20000
PROX_EPS_SCAN = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8)
QPAX_ITERS = (10, 12, 15, 20, 25, 30, 40)  # fixed iteration counts, tried in this order
CONVERGED_MIN = 0.99  # a tolerance scan stops where fewer steps converge (float32's floor)
LE_FLOOR_FACTOR = 1.25
LE_OPTIONS: dict[str, Any] = {}  # Local Explicit's strategy options (--finish, --rho-method)

# -- sizes -----------------------------------------------------------------------------------
SIZES = (1, 10, 100, 1000, 10000)
FULL_SIZES = (100000,)
SMOKE_SIZES = (1, 10)
REF_CASES = 100  # throughput cases with a Clarabel reference (every step of each)
CALL_CASES = 1000  # cases per compiled call (Local Explicit, qpax)
VMAP_CHUNK = 32  # drives vmapped together (map_scenarios)
COND_BATCH = 32  # QPs condensed together (jax.lax.map batch_size)
WORKER_CHUNK = 250  # cases a worker (or solve_in_parallel) condenses at a time
PEER_BUDGET_S = 60.0  # a peer's call estimated longer than this is skipped at that size
LAT_DRIVES, LAT_STEPS, BLOCK = 10, 21, 10  # 200 timed steps; 10 drives sample the
# drives' phases (4 of 51 steps: the general rows active in 42 % and 84 % of the steps)
SMOKE_LAT = (1, 6, 5)  # drives, steps, block
LAT_SEED = 50_000  # latency drives: seeds LAT_SEED + 100 N_p + i (throughput cases: 0, 1, ...)
PEAK_N, SMOKE_PEAK_N = 4096, 1024


def say(*args: Any) -> None:
    print(*args, flush=True)


def short(dtype: str) -> str:
    return {"float64": "f64", "float32": "f32"}.get(dtype, dtype)


def topology(horizon: int) -> Topology:
    """bench_local_explicit's cruise topology with the two general rows."""
    agents = CRUISE.agents
    return Topology.build(
        n_x=CRUISE.n_x,
        horizon=horizon,
        agent_names=agents,
        agent_sizes=CRUISE.agent_sizes,
        objective_names=CRUISE.objectives,
        output_sizes=tuple(len(CRUISE.outputs[o]) for o in CRUISE.objectives),
        groups=[tuple(agents.index(a) for a in ble.GROUPS[o]) for o in CRUISE.objectives],
        general_rows=[G_ROWS],
    )


def make_data_of(T: Topology, settings: CruiseSettings) -> Any:
    """op (one operating point) -> the step's ProblemData with the general rows (jittable),
    in the operating point's dtype."""
    return ble.make_data_of(T, settings, G=G_ROWS, g=G_RHS)


def problem(horizon: int) -> tuple[Topology, Any]:
    T = topology(horizon)
    return T, make_data_of(T, CruiseSettings(horizon=horizon))


def form_of(T: Topology, data_of: Any) -> Any:
    """op -> the peers' condensed QP (jittable): H (n, n), f (n,), the variables' bounds
    ub, lb (n,) and the general row's two sides gu, gl (N_p,) of gl <= (I (x) G_ROW) U <= gu."""
    nb = len(T.box_rows)
    assert T.n_c == nb + 2, T.n_c

    def form(op: dict) -> tuple:
        d = data_of(op)
        qp = condensed_qp(T, d)
        return qp.H, qp.E, d.ub.reshape(-1), d.lb.reshape(-1), d.bin[:, nb], -d.bin[:, nb + 1]

    return form


def drives(seeds: Any, steps: int) -> dict[str, np.ndarray]:
    """Operating points (len(seeds), steps, ...) of bench_local_explicit's drives, float64."""
    ds = [ble.drive(steps, seed=int(s)) for s in seeds]
    return {k: np.stack([d[k] for d in ds]) for k in ds[0]}


def cast(ops: dict, dtype: str) -> dict:
    return {k: np.asarray(v, dtype) for k, v in ops.items()}


def take(ops: dict, lo: int, hi: int) -> dict:
    return {k: v[lo:hi] for k, v in ops.items()}


def flat(ops: dict) -> dict:
    """(cases, steps, ...) -> (cases * steps, ...): one QP per row."""
    return {k: v.reshape(-1, *v.shape[2:]) for k, v in ops.items()}


def errors(u0: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Worst and median over steps of max_i |u0_i - u0_i*| (Nm); NaN reference steps left out."""
    e = np.max(np.abs(np.asarray(u0, float).reshape(ref.shape) - ref), axis=-1).ravel()
    e = e[np.isfinite(ref).all(axis=-1).ravel()]
    if e.size == 0:
        return float("nan"), float("nan")
    if not np.all(np.isfinite(e)):
        return float("inf"), float(np.median(e))
    return float(np.max(e)), float(np.median(e))


def fmt_err(e: tuple[float, float] | None) -> str:
    return "- | -" if e is None else f"{e[0]:.2e} | {e[1]:.2e}"


def references(T: Topology, data_of: Any, ops: dict) -> dict[str, Any]:
    """Clarabel at REF_EPS on every step of ``ops`` (cases, steps): u0* (cases, steps, n_u)
    and whether a general row is active at the solution (first prediction step, any step)."""
    shape = ops["v_x"].shape
    ref_fn = jax.jit(
        lambda o: jax.lax.map(lambda op: tuple(condensed_qp(T, data_of(op))), o, batch_size=32)
    )
    H, E, Gm, h = (np.asarray(x) for x in ref_fn(flat(ops)))
    m = H.shape[0]
    u0 = np.full((m, N_U), np.nan)
    act0 = np.zeros(m, bool)
    act_any = np.zeros(m, bool)
    failed = 0
    t0 = time.perf_counter()
    for k in range(m):
        sol = clarabel_solve(CondensedQP(H[k], E[k], Gm[k], h[k]), REF_EPS)
        if "solved" not in str(sol.status).lower() or "almost" in str(sol.status).lower():
            failed += 1
            continue
        u = np.asarray(sol.x).reshape(T.horizon, T.n_u)
        u0[k] = u[0]
        s = u @ G_ROW
        act = (s >= G_UPPER - ACTIVE_TOL) | (s <= G_LOWER + ACTIVE_TOL)
        act0[k], act_any[k] = act[0], act.any()
    return {
        "u0": u0.reshape(*shape, N_U),
        "active_first": float(act0.mean()),
        "active_any": float(act_any.mean()),
        "failed": failed,
        "clarabel_s_per_qp": (time.perf_counter() - t0) / max(m, 1),
    }


def activity_line(label: str, ref: dict) -> str:
    lo, hi = ACTIVE_RANGE
    a = ref["active_any"]
    where = "inside" if lo <= a <= hi else "OUTSIDE"
    return (
        f"{label}: a general row is active at the reference solution in {100 * ref['active_first']:.0f} % "
        f"of the steps at the first prediction step, {100 * a:.0f} % at any prediction step "
        f"({where} the issue's {100 * lo:.0f} % to {100 * hi:.0f} %; drives unscaled); "
        f"Clarabel {ref['clarabel_s_per_qp'] * 1e3:.1f} ms a QP"
        + (f", {ref['failed']} reference solves failed (left out)" if ref["failed"] else "")
    )


def kkt_names(T: Topology) -> list[str]:
    """Every KKT solve of ``KKT_SOLVES`` but "auto" that ``select_kkt`` accepts for ``T``
    (read at run time, so a new one is picked up)."""
    out = []
    for name in kkt_module.KKT_SOLVES:
        if name == "auto":
            continue
        try:
            kkt_module.select_kkt(T, name)
        except ValueError as e:
            say(f"  [kkt {name!r} skipped for this topology: {e}]")
            continue
        out.append(name)
    return out


def auto_kkt(T: Topology) -> str:
    return kkt_module.select_kkt(T, "auto").name


def le_kkts(args: Any, T: Topology) -> list[str]:
    """--kkt, else (--smoke) the one "auto" picks, else every accepted one."""
    return args.kkt_list or ([auto_kkt(T)] if args.smoke else kkt_names(T))


def le_params(solver: LocalExplicit, tol: float, dtype: str) -> Any:
    return solver.params(
        rho=TUNED["rho"],
        relaxation=TUNED["relaxation"],
        tol_primal=tol,
        tol_dual=tol,
        dtype=dtype,
    )


def _flops(obj: Any) -> float:
    """XLA's flop count of a lowered or compiled program (a dict, or a list of them)."""
    try:
        ca = obj.cost_analysis()
    except Exception:  # noqa: BLE001  (not every backend and version has it)
        return float("nan")
    if isinstance(ca, (list, tuple)):
        ca = ca[0] if ca else {}
    return float((ca or {}).get("flops", float("nan")))


# -- the peers in their native forms ----------------------------------------------------------
class DaqpPeer:
    """DAQP: ``setup`` at the first QP, then ``update`` + ``solve`` (warm working set)."""

    def __init__(self, horizon: int, setting: Any = None) -> None:
        self.A = np.kron(np.eye(horizon), G_ROW)  # the general rows (two-sided)
        self.model = None

    def solve(self, H, f, ub, lb, gu, gl) -> tuple[np.ndarray, bool]:
        bu = np.concatenate([ub, gu])  # first n entries: simple bounds on the variables
        bl = np.concatenate([lb, gl])
        if self.model is None:
            import daqp

            self.model = daqp.Model()
            self.model.setup(np.array(H), np.array(f), self.A.copy(), bu, bl)
        else:
            self.model.update(H=H, f=f, bupper=bu, blower=bl)
        x, _, flag, info = self.model.solve()
        self.iterations = int(info.get("iterations", -1))  # active-set changes
        return np.asarray(x), int(flag) > 0


class OsqpPeer:
    """OSQP: l <= [I; I (x) G_ROW] U <= u (two-sided rows), unscaled, polish off, warm."""

    def __init__(self, horizon: int, eps: float) -> None:
        import scipy.sparse as sp

        n = horizon * N_U
        rows, cols = np.triu_indices(n)
        P = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n)).tocsc()
        self._P = P  # the dense upper triangle: updates never change the sparsity
        self._pr, self._pc = P.indices, np.repeat(np.arange(n), np.diff(P.indptr))
        self.A = sp.csc_matrix(np.vstack([np.eye(n), np.kron(np.eye(horizon), G_ROW)]))
        self.eps = float(eps)
        self.solver = None

    def solve(self, H, f, ub, lb, gu, gl) -> tuple[np.ndarray, bool]:
        l = np.concatenate([lb, gl])
        u = np.concatenate([ub, gu])
        Px = H[self._pr, self._pc]
        if self.solver is None:
            import osqp
            import scipy.sparse as sp

            P = sp.csc_matrix((Px, self._P.indices, self._P.indptr), shape=self._P.shape)
            self.solver = osqp.OSQP()
            self.solver.setup(
                P=P,
                q=np.array(f),
                A=self.A,
                l=l,
                u=u,
                eps_abs=self.eps,
                eps_rel=self.eps,
                polishing=False,
                scaling=0,
                warm_starting=True,
                max_iter=OSQP_MAX_ITER,
                verbose=False,
            )
        else:
            self.solver.update(Px=Px, q=f, l=l, u=u)
        r = self.solver.solve(raise_error=False)
        self.iterations = int(r.info.iter)
        ok = str(r.info.status).lower() == "solved"
        x = np.asarray(r.x) if r.x is not None else np.full(f.shape, np.nan)
        return x, ok


class ProxPeer:
    """proxsuite ProxQP dense: box constraints, variables scaled by their bounds, warm."""

    def __init__(self, horizon: int, eps: float) -> None:
        self.horizon = horizon
        self.A2 = np.kron(np.eye(horizon), G_ROW)
        self.eps = float(eps)
        self.qp = None
        self.D = None

    def solve(self, H, f, ub, lb, gu, gl) -> tuple[np.ndarray, bool]:
        import proxsuite

        D = 0.5 * (ub - lb)  # x = D y (every bound finite here)
        Hs = D[:, None] * H * D[None, :]
        gs = D * f
        C = None if self.D is not None and np.array_equal(D, self.D) else self.A2 * D[None, :]
        self.D = D
        if self.qp is None:
            n = H.shape[0]
            qp = proxsuite.proxqp.dense.QP(n, 0, self.horizon, True)
            qp.settings.eps_abs = self.eps
            qp.settings.eps_rel = 0.0
            qp.settings.initial_guess = (
                proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            )
            qp.init(Hs, gs, None, None, C, gl, gu, lb / D, ub / D)
            self.qp = qp
        else:
            self.qp.update(H=Hs, g=gs, C=C, l=gl, u=gu, l_box=lb / D, u_box=ub / D)
        self.qp.solve()
        self.iterations = int(self.qp.results.info.iter)
        ok = self.qp.results.info.status == proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
        return D * self.qp.results.x, bool(ok)


PEERS = {"daqp": DaqpPeer, "osqp": OsqpPeer, "proxsuite": ProxPeer}
LABELS = {"daqp": "DAQP", "osqp": "OSQP", "proxsuite": "proxsuite"}


def available(module: str) -> bool:
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def run_sequential(peer: Any, qps: list[tuple]) -> tuple[np.ndarray, np.ndarray]:
    """One peer object over the QPs in order (warm from one to the next): u0s, ok flags."""
    u0 = np.empty((len(qps), N_U))
    ok = np.empty(len(qps), bool)
    for k, qp in enumerate(qps):
        x, ok[k] = peer.solve(*qp)
        u0[k] = x[:N_U]
    return u0, ok


def qpax_program(form: Any, horizon: int) -> Any:
    """Jitted: ops (m, ...) flattened QPs, tol, iterations -> u0 (m, n_u), iterations, converged.
    The variables scaled by their bounds, the general rows normalised; the tolerance and
    the iteration cap are traced (one program for every setting)."""
    import qpax

    n = horizon * N_U
    A2 = np.kron(np.eye(horizon), G_ROW)

    def one(op: dict, tol: Any, iters: Any) -> tuple:
        H, f, ub, lb, gu, gl = form(op)
        D = 0.5 * (ub - lb)
        Hs, fs = D[:, None] * H * D[None, :], D * f
        Ag = jnp.asarray(A2, H.dtype) * D[None, :]
        s = 1.0 / jnp.linalg.norm(Ag, axis=1)
        Ag, gu, gl = Ag * s[:, None], gu * s, gl * s
        eye = jnp.eye(n, dtype=H.dtype)
        G = jnp.concatenate([eye, -eye, Ag, -Ag])
        h = jnp.concatenate([ub / D, -lb / D, gu, -gl])
        y, _, _, _, conv, its = qpax.solve_qp(
            Hs,
            fs,
            jnp.zeros((0, n), H.dtype),
            jnp.zeros((0,), H.dtype),
            G,
            h,
            solver_tol=tol,
            max_iter=iters,
        )
        return (D * y)[:N_U], its, conv

    return jax.jit(
        lambda ops, tol, iters: jax.lax.map(lambda op: one(op, tol, iters), ops, batch_size=32)
    )


# -- the worker processes (DAQP, OSQP, proxsuite: one per core) --------------------------------
_W: dict[str, Any] = {}


def _worker_init(core: int, ops: dict, steps: int) -> None:
    """Worker start: pinned to ``core`` (one XLA device), its share of the cases."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})
    _W.update(ops=ops, steps=steps, forms={}, peers={})


def _worker_form(horizon: int) -> Any:
    if horizon not in _W["forms"]:
        T, data_of = problem(horizon)
        form = form_of(T, data_of)
        _W["forms"][horizon] = jax.jit(lambda o: jax.lax.map(form, o, batch_size=COND_BATCH))
    return _W["forms"][horizon]


def _worker_run(peer: str, horizon: int, setting: Any, n: int, chunk: int) -> tuple:
    """Condense and solve this worker's first ``n`` cases, drive by drive, with one peer
    object (kept between calls, warm): (condense s, solve s, u0 (n, S, n_u), ok (n, S))."""
    cond = _worker_form(horizon)
    key = (peer, horizon, setting)
    if key not in _W["peers"]:
        _W["peers"][key] = PEERS[peer](horizon, setting)
    solver = _W["peers"][key]
    ops, S = _W["ops"], _W["steps"]
    u0 = np.full((n, S, N_U), np.nan)
    ok = np.zeros((n, S), bool)
    t_cond = t_solve = 0.0
    size = min(n, chunk)
    for lo in range(0, n, size):
        m = min(size, n - lo)
        idx = np.minimum(np.arange(lo, lo + size), n - 1)  # the last chunk padded
        chunk_ops = {k: v[idx].reshape(size * S, *v.shape[2:]) for k, v in ops.items()}
        t0 = time.perf_counter()
        qp = [np.array(x) for x in cond(chunk_ops)]
        t1 = time.perf_counter()
        for c in range(m):
            for s in range(S):
                k = c * S + s
                x, ok[lo + c, s] = solver.solve(*(a[k] for a in qp))
                u0[lo + c, s] = x[:N_U]
        t_cond += t1 - t0
        t_solve += time.perf_counter() - t1
    return t_cond, t_solve, u0, ok


class PeerPool:
    """One pinned process per core; worker w holds cases w, w + W, ... (so that the first
    n cases split evenly for every n)."""

    def __init__(self, ops: dict, steps: int, cores: list[int]) -> None:
        ctx = mp.get_context("spawn")
        env = os.environ.get("XLA_FLAGS", "")
        keep = [f for f in env.split() if "xla_force_host_platform_device_count" not in f]
        os.environ["XLA_FLAGS"] = " ".join([*keep, "--xla_force_host_platform_device_count=1"])
        W = len(cores)
        try:
            self.pools = [
                ctx.Pool(1, _worker_init, (c, {k: v[w::W] for k, v in ops.items()}, steps))
                for w, c in enumerate(cores)
            ]
        finally:
            os.environ["XLA_FLAGS"] = env
        self.steps = steps

    def __call__(self, peer: str, horizon: int, setting: Any, n: int) -> dict[str, Any]:
        W = len(self.pools)
        counts = [len(range(w, n, W)) for w in range(W)]
        t0 = time.perf_counter()
        jobs = [
            (w, p.apply_async(_worker_run, (peer, horizon, setting, counts[w], WORKER_CHUNK)))
            for w, p in enumerate(self.pools)
            if counts[w]
        ]
        outs = {w: j.get() for w, j in jobs}
        wall = time.perf_counter() - t0
        u0 = np.empty((n, self.steps, N_U))
        ok = np.empty((n, self.steps), bool)
        for w, o in outs.items():
            u0[w::W], ok[w::W] = o[2], o[3]
        return {
            "wall": wall,
            "cond": max(o[0] for o in outs.values()),
            "solve": max(o[1] for o in outs.values()),
            "u0": u0,
            "ok": ok,
        }

    def close(self) -> None:
        for p in self.pools:
            p.close()
            p.join()


# -- Local Explicit programs -------------------------------------------------------------------
class LEBatch:
    """Local Explicit on batches of drives: vmapped (chunks of VMAP_CHUNK drives) over every
    device, scanned over the steps (step 0 from the cold state, then warm), one compiled
    program per distinct call size (at most CALL_CASES cases)."""

    def __init__(self, T: Topology, data_of: Any, kkt: str, dtype: str, tol: float) -> None:
        self.kkt, self.dtype, self.tol = kkt, dtype, tol
        self.solver = LocalExplicit(T, max_iter=MAX_ITER, kkt=kkt, **LE_OPTIONS)
        solver = self.solver
        self.data_of = data_of
        self.name = f"LE {kkt} {short(dtype)}"
        self.compiled: dict[int, Any] = {}
        self.compile_s: dict[int, float] = {}
        self.flops_program: dict[int, float] = {}
        self.setup_compiled: dict[int, Any] = {}

        def one_drive(case: tuple) -> tuple:
            ops, p = case

            def body(st: Any, op: dict) -> tuple:
                r = solver.solve(data_of(op), p, solver.shift(st))
                return r.state, (r.u0, r.iterations, r.status)

            _, out = jax.lax.scan(body, solver.cold_state(dtype), ops)
            return out

        def setup_drive(case: tuple) -> Any:
            ops, p = case

            def one(op: dict) -> Any:  # data + setup, reduced to one number (no big output)
                s = solver.setup(data_of(op), p)
                return sum(jnp.sum(x) for x in jax.tree.leaves(s))

            return jax.lax.map(one, ops)

        def batched(fn: Any) -> Any:
            def run(ops: dict, p: Any) -> Any:
                n = ops["v_x"].shape[0]
                pb = jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x))), p)
                return map_scenarios(fn, (ops, pb), chunk=VMAP_CHUNK)

            return jax.jit(run)

        self._full = batched(one_drive)
        self._setup = batched(setup_drive)

    def params(self, tol: float | None = None) -> Any:
        return le_params(self.solver, self.tol if tol is None else tol, self.dtype)

    def program(self, ops: dict) -> Any:
        m = ops["v_x"].shape[0]
        if m not in self.compiled:
            t0 = time.perf_counter()
            self.compiled[m] = self._full.lower(ops, self.params()).compile()
            self.compile_s[m] = time.perf_counter() - t0
            self.flops_program[m] = _flops(self.compiled[m])
        return self.compiled[m]

    def run(
        self, ops: dict, B: int, tol: float | None = None, keep: int | None = None
    ) -> tuple[float, dict]:
        """The first B cases of ``ops`` (float64, cast here) in calls of at most CALL_CASES:
        wall s, and the outputs (u0, iterations, status) of the first ``keep`` cases
        (default: the first call's)."""
        m = min(B, CALL_CASES)
        calls = math.ceil(B / m)
        chunks = [cast(take(ops, c * m, c * m + m), self.dtype) for c in range(calls)]
        prog = self.program(chunks[0])
        p = self.params(tol)
        kept = math.ceil((m if keep is None else keep) / m)
        t0 = time.perf_counter()
        outs = []
        for c in chunks:
            out = jax.block_until_ready(prog(c, p))
            if len(outs) < kept:
                outs.append(out)
        wall = time.perf_counter() - t0
        u0, its, status = (np.concatenate([np.asarray(o[k]) for o in outs]) for k in range(3))
        return wall, {"u0": u0, "iterations": its, "status": status}

    def run_setup(self, ops: dict, B: int) -> float:
        """Data + setup alone of the first B cases' steps (one call of B cases)."""
        c = cast(take(ops, 0, B), self.dtype)
        if B not in self.setup_compiled:
            self.setup_compiled[B] = self._setup.lower(c, self.params()).compile()
        prog = self.setup_compiled[B]
        p = self.params()
        t0 = time.perf_counter()
        jax.block_until_ready(prog(c, p))
        return time.perf_counter() - t0

    def piece_flops(self, op0: dict) -> tuple[float, float]:
        """XLA's flops of one data + setup and of one iteration (single case)."""
        solver, p = self.solver, self.params()
        op0 = cast(op0, self.dtype)

        def setup(op: dict, p: Any) -> Any:
            return solver.setup(self.data_of(op), p)

        f_setup = _flops(jax.jit(setup).lower(op0, p))
        shape = jax.eval_shape(setup, op0, p)
        f_step = _flops(jax.jit(solver.step).lower(shape, solver.cold_state(self.dtype)))
        return f_setup, f_step


_LE_CACHE: dict[tuple, LEBatch] = {}


def le_batch(horizon: int, kkt: str, dtype: str, tol: float) -> LEBatch:
    """One LEBatch per (N_p, K, dtype) for the whole run (its compiled programs kept)."""
    key = (horizon, kkt, dtype)
    if key not in _LE_CACHE:
        T, data_of = problem(horizon)
        _LE_CACHE[key] = LEBatch(T, data_of, kkt, dtype, tol)
    le = _LE_CACHE[key]
    le.tol = tol
    return le


# -- calibration -------------------------------------------------------------------------------
def pick(scan: list[dict], key: str, loosest: str = "max") -> tuple[Any, bool]:
    """The loosest setting whose worst error is under ERR_TARGET (``loosest``: "max" for a
    tolerance, "first" for the first of an ordered list); else the most accurate one."""
    ok = [r for r in scan if r["err_max"] < ERR_TARGET]
    if ok:
        best = ok[0] if loosest == "first" else max(ok, key=lambda r: r[key])
        return best[key], True
    return min(scan, key=lambda r: r["err_max"])[key], False


def pick_le(scan: list[dict]) -> tuple[float, bool]:
    """Local Explicit's tolerance: the loosest under ERR_TARGET; where none is (float32's
    error floor), the loosest whose worst error is within LE_FLOOR_FACTOR of the smallest
    among the tolerances where CONVERGED_MIN of the steps converge."""
    ok = [r for r in scan if r["err_max"] < ERR_TARGET]
    if ok:
        return max(ok, key=lambda r: r["tol"])["tol"], True
    conv = [r for r in scan if r["converged"] >= CONVERGED_MIN] or scan
    floor = min(r["err_max"] for r in conv)
    near = [r for r in conv if r["err_max"] <= LE_FLOOR_FACTOR * floor]
    return max(near, key=lambda r: r["tol"])["tol"], False


def calibrate(
    horizon: int, dtypes: list[str], kkts: list[str], cases: dict, n_ref: int
) -> tuple[dict, dict]:
    """Settings of every iterative contender on the first n_ref cases (printed scans);
    returns (settings, reference)."""
    T, data_of = problem(horizon)
    form = form_of(T, data_of)
    ops = take(cases, 0, n_ref)
    S = ops["v_x"].shape[1]
    say(f"\n### N_p = {horizon}: calibration on {n_ref} cases x {S} steps (Clarabel {REF_EPS:g})\n")
    ref = references(T, data_of, ops)
    say(activity_line(f"N_p={horizon} throughput cases", ref))
    settings: dict[str, Any] = {"le_tol": {}, "le_ok": {}, "scans": {}}
    u_ref = ref["u0"]

    say(
        f"\nLocal Explicit tolerance scans (tuned: rho {TUNED['rho']} x rho*, relaxation "
        f"{TUNED['relaxation']}; loose to tight, stopped at the first tolerance under "
        f"{ERR_TARGET:g} Nm or once fewer than {100 * CONVERGED_MIN:.0f} % of the steps converge)\n"
    )
    say(
        "| LE | tol (Nm^2) | worst error (Nm) | median error (Nm) | iterations mean / max | converged |"
    )
    say("| --- | --- | --- | --- | --- | --- |")
    for dtype in dtypes:
        for kkt in kkts:
            le = le_batch(horizon, kkt, dtype, LE_TOL_SCAN[0])
            scan = []
            for tol in LE_TOL_SCAN:
                _, out = le.run(ops, n_ref, tol=tol, keep=n_ref)
                w, m = errors(out["u0"], u_ref)
                its = out["iterations"]
                conv = float(np.mean(out["status"] == Status.SOLVED))
                scan.append(
                    {
                        "tol": tol,
                        "err_max": w,
                        "err_median": m,
                        "it_mean": float(its.mean()),
                        "it_max": int(its.max()),
                        "converged": conv,
                    }
                )
                say(
                    f"| {le.name} | {tol:g} | {w:.2e} | {m:.2e} | {its.mean():.1f} / {its.max()} "
                    f"| {100 * conv:.1f} % |"
                )
                if w < ERR_TARGET or conv < CONVERGED_MIN:
                    break
            tol, ok = pick_le(scan)
            key = f"{kkt}/{dtype}"
            settings["le_tol"][key], settings["le_ok"][key] = tol, ok
            settings["scans"][f"le {key}"] = scan
            say(
                f"|  -> {le.name}: tol {tol:g} |  |  |  |  |  |"
                if ok
                else f"|  -> {le.name}: tol {tol:g} (NO tolerance reaches {ERR_TARGET:g} Nm: the "
                f"loosest within {LE_FLOOR_FACTOR:g}x of its error floor) |  |  |  |  |  |"
            )

    fj = jax.jit(lambda o: jax.lax.map(form, o, batch_size=COND_BATCH))
    out = [np.array(x) for x in fj(flat(ops))]
    qps = [tuple(a[k] for a in out) for k in range(out[0].shape[0])]
    for peer, scan_values, knob in (
        ("osqp", OSQP_EPS_SCAN, "eps"),
        ("proxsuite", PROX_EPS_SCAN, "eps"),
    ):
        if not available(peer):
            say(f"\n{LABELS[peer]}: not installed, skipped")
            continue
        say(
            f"\n{LABELS[peer]} {knob} scan (one solver object, warm along the cases' steps in order)\n"
        )
        say(f"| {knob} | worst error (Nm) | median error (Nm) | solved | us a solve |")
        say("| --- | --- | --- | --- | --- |")
        scan = []
        for v in scan_values:
            t0 = time.perf_counter()
            u0, okf = run_sequential(PEERS[peer](horizon, v), qps)
            t = (time.perf_counter() - t0) / len(qps)
            w, m = errors(u0, u_ref)
            scan.append(
                {knob: v, "err_max": w, "err_median": m, "solved": float(okf.mean()), "us": t * 1e6}
            )
            say(f"| {v:g} | {w:.2e} | {m:.2e} | {100 * okf.mean():.1f} % | {t * 1e6:.0f} |")
        v, ok = pick(scan, knob)
        settings[f"{peer}_eps"], settings[f"{peer}_ok"] = v, ok
        settings["scans"][peer] = scan
        say(
            f"  -> {LABELS[peer]}: {knob} {v:g}"
            + (
                ""
                if ok
                else f" (NO {knob} reaches {ERR_TARGET:g} Nm: the most accurate one, worst {min(r['err_max'] for r in scan):.2e} Nm)"
            )
        )
    if available("daqp"):
        u0, okf = run_sequential(DaqpPeer(horizon), qps)
        w, m = errors(u0, u_ref)
        settings["daqp_err"] = [w, m]
        say(
            f"\nDAQP (exact, no knob): worst error {w:.2e} Nm, median {m:.2e} Nm, exit flag > 0 in {100 * okf.mean():.1f} %"
        )
    if available("qpax"):
        prog = qpax_program(form, horizon)
        dev = jax.devices()[0]
        o = jax.device_put(flat(ops), dev)
        say("\nqpax iteration scan (fixed iteration count, vmapped on one device)\n")
        say("| iterations | worst error (Nm) | median error (Nm) |")
        say("| --- | --- | --- |")
        scan = []
        for it in QPAX_ITERS:
            u0, _, _ = jax.block_until_ready(prog(o, 0.0, it))
            w, m = errors(np.asarray(u0), u_ref)
            scan.append({"iterations": it, "err_max": w, "err_median": m})
            say(f"| {it} | {w:.2e} | {m:.2e} |")
            if w < ERR_TARGET:
                break
        it, ok = pick(scan, "iterations", loosest="first")
        settings["qpax_iters"], settings["qpax_ok"] = it, ok
        settings["scans"]["qpax"] = scan
        say(
            f"  -> qpax: {it} iterations"
            + ("" if ok else " (NONE reaches the target: the most accurate)")
        )
    return settings, ref


# -- 1. latency --------------------------------------------------------------------------------
class Contender:
    """A latency contender: ``start(d)`` solves drive d's step 0 (untimed, cold where the
    solver has a cold start), ``step(d, i)`` one timed call; times and u0s recorded."""

    name = ""
    setting = ""
    u0_of = True

    def __init__(self) -> None:
        self.times: list[float] = []
        self.u0: dict[tuple[int, int], np.ndarray] = {}
        self.iterations: list[int] = []

    def start(self, d: int) -> None:
        raise NotImplementedError

    def call(self, d: int, i: int) -> Any:
        raise NotImplementedError

    def step(self, d: int, i: int) -> None:
        t0 = time.perf_counter()
        out = self.call(d, i)
        self.times.append(time.perf_counter() - t0)
        self.record(d, i, out)

    def record(self, d: int, i: int, out: Any) -> None:
        pass


class LEFull(Contender):
    """Local Explicit's full step (data -> setup -> iterate), warm along the drive."""

    def __init__(self, T, data_of, kkt, dtype, tol, lat) -> None:
        super().__init__()
        self.solver = s = LocalExplicit(T, max_iter=MAX_ITER, kkt=kkt, **LE_OPTIONS)
        self.p = le_params(s, tol, dtype)
        self.lat, self.dtype = lat, dtype
        self.name = f"LE {kkt} {short(dtype)} full step"
        self.setting = f"tol {tol:g}"

        def warm(op: dict, p: Any, st: Any) -> Any:
            return s.solve(data_of(op), p, s.shift(st))

        t0 = time.perf_counter()
        self.prog = jax.jit(warm).lower(lat.op(0, 0, dtype), self.p, s.cold_state(dtype)).compile()
        self.compile_s = time.perf_counter() - t0

    def start(self, d: int) -> None:
        r = self.prog(self.lat.op(d, 0, self.dtype), self.p, self.solver.cold_state(self.dtype))
        self.state = jax.block_until_ready(r).state

    def call(self, d: int, i: int) -> Any:
        return jax.block_until_ready(self.prog(self.lat.op(d, i, self.dtype), self.p, self.state))

    def record(self, d: int, i: int, r: Any) -> None:
        self.state = r.state
        self.u0[d, i] = np.asarray(r.u0)
        self.iterations.append(int(r.iterations))


class LESetup(Contender):
    """``solver.setup`` alone (compiled separately) on the step's data."""

    u0_of = False

    def __init__(self, full: LEFull, kkt: str) -> None:
        super().__init__()
        self.full, self.lat, self.dtype = full, full.lat, full.dtype
        self.name = f"LE {kkt} {short(full.dtype)} setup alone"
        s = full.solver
        d0 = self.lat.data(0, 0, self.dtype)
        self.prog = jax.jit(s.setup).lower(d0, full.p).compile()

    def start(self, d: int) -> None:
        pass

    def call(self, d: int, i: int) -> Any:
        return jax.block_until_ready(self.prog(self.lat.data(d, i, self.dtype), self.full.p))


class LEIterate(Contender):
    """Local Explicit's iterations alone (warm) on precomputed setups."""

    def __init__(self, full: LEFull, setup: LESetup, kkt: str) -> None:
        super().__init__()
        self.full, self.lat, self.dtype = full, full.lat, full.dtype
        self.name = f"LE {kkt} {short(full.dtype)} iterations alone"
        s = full.solver

        def iterate(setup: Any, st: Any) -> Any:
            return s.result(setup, s.run(setup, s.init(setup, s.shift(st))))

        self.setups = {
            (d, i): jax.block_until_ready(setup.prog(self.lat.data(d, i, self.dtype), full.p))
            for d in range(self.lat.n_drives)
            for i in range(self.lat.n_steps)
        }
        self.prog = jax.jit(iterate).lower(self.setups[0, 0], s.cold_state(self.dtype)).compile()

    def start(self, d: int) -> None:
        r = self.prog(self.setups[d, 0], self.full.solver.cold_state(self.dtype))
        self.state = jax.block_until_ready(r).state

    def call(self, d: int, i: int) -> Any:
        return jax.block_until_ready(self.prog(self.setups[d, i], self.state))

    def record(self, d: int, i: int, r: Any) -> None:
        self.state = r.state
        self.u0[d, i] = np.asarray(r.u0)
        self.iterations.append(int(r.iterations))


class LEData(Contender):
    """The re-linearisation alone (``data_of``), float64."""

    u0_of = False
    name = "LE data (re-linearise) f64"

    def __init__(self, lat: Any) -> None:
        super().__init__()
        self.lat = lat
        self.prog = jax.jit(lat.data_of).lower(lat.op(0, 0, "float64")).compile()

    def start(self, d: int) -> None:
        pass

    def call(self, d: int, i: int) -> Any:
        return jax.block_until_ready(self.prog(self.lat.op(d, i, "float64")))


class Condense(Contender):
    """The peers' condensing alone: jitted data_of + condensed_qp, outputs to numpy."""

    u0_of = False
    name = "condensing (jitted condensed_qp, to numpy)"

    def __init__(self, lat: Any) -> None:
        super().__init__()
        self.lat = lat
        self.prog = jax.jit(form_of(lat.T, lat.data_of)).lower(lat.op(0, 0, "float64")).compile()

    def start(self, d: int) -> None:
        pass

    def call(self, d: int, i: int) -> Any:
        return [np.array(x) for x in self.prog(self.lat.op(d, i, "float64"))]


class PeerStep(Contender):
    """A peer's update + solve on the step's precomputed condensed QP (or, with
    ``condense``, condensing and solving in one timed call)."""

    def __init__(self, lat: Any, peer: str, setting: Any, condense: Condense | None = None) -> None:
        super().__init__()
        self.lat, self.cond = lat, condense
        self.peer = PEERS[peer](lat.T.horizon, setting)
        label = LABELS[peer]
        self.name = f"{label} + condensing (one call)" if condense else f"{label} update + solve"
        self.setting = "" if setting is None else f"eps {setting:g}"
        self.ok: list[bool] = []

    def start(self, d: int) -> None:
        x, _ = self.peer.solve(*self.lat.qps[d, 0])

    def call(self, d: int, i: int) -> Any:
        qp = (
            [np.array(x) for x in self.cond.prog(self.lat.op(d, i, "float64"))]
            if self.cond
            else self.lat.qps[d, i]
        )
        return self.peer.solve(*qp)

    def record(self, d: int, i: int, out: Any) -> None:
        self.u0[d, i] = out[0][:N_U]
        self.ok.append(out[1])
        it = getattr(self.peer, "iterations", None)  # the solve just recorded
        if it is not None and it >= 0:
            self.iterations.append(it)


class LatencyData:
    """The latency drives: operating points per (drive, step) in each dtype, the
    ProblemData, the peers' condensed QPs and the Clarabel references."""

    def __init__(self, horizon: int, n_drives: int, n_steps: int, dtypes: list[str]) -> None:
        self.T, self.data_of = problem(horizon)
        self.n_drives, self.n_steps = n_drives, n_steps
        seeds = [LAT_SEED + 100 * horizon + k for k in range(n_drives)]
        ops = drives(seeds, n_steps)
        self.ops = {
            dt: {
                (d, i): {k: np.asarray(v[d, i], dt) for k, v in ops.items()}
                for d in range(n_drives)
                for i in range(n_steps)
            }
            for dt in {"float64", *dtypes}
        }
        self._data: dict[str, dict] = {}
        form = jax.jit(form_of(self.T, self.data_of))
        self.qps = {
            key: tuple(np.array(x) for x in form(op)) for key, op in self.ops["float64"].items()
        }
        self.ref = references(self.T, self.data_of, ops)

    def op(self, d: int, i: int, dtype: str) -> dict:
        return self.ops[dtype][d, i]

    def data(self, d: int, i: int, dtype: str) -> Any:
        if dtype not in self._data:
            fn = jax.jit(self.data_of)
            self._data[dtype] = {
                k: jax.block_until_ready(fn(op)) for k, op in self.ops[dtype].items()
            }
        return self._data[dtype][d, i]


def section_latency(args: Any, settings: dict, horizons: list[int], dtypes: list[str]) -> dict:
    n_drives, n_steps, block = SMOKE_LAT if args.smoke else (LAT_DRIVES, LAT_STEPS, BLOCK)
    out: dict[str, Any] = {}
    say(
        f"\n## latency: one time-varying step on one core (affinity {sorted(os.sched_getaffinity(0))}, "
        f"{len(jax.devices())} XLA device(s)); {n_drives} drive(s) x {n_steps} steps, step 0 cold and "
        f"untimed, blocks of {block} steps rotated between contenders; single calls"
    )
    for h in horizons:
        st = settings[str(h)]
        t0 = time.perf_counter()
        lat = LatencyData(h, n_drives, n_steps, dtypes)
        say(f"\n### N_p = {h}\n")
        say(activity_line(f"N_p={h} latency drives", lat.ref))
        kkts = le_kkts(args, lat.T)
        cons: list[Contender] = []
        le_rows = []
        for dtype in dtypes:
            for K in kkts:
                full = LEFull(lat.T, lat.data_of, K, dtype, st["le_tol"][f"{K}/{dtype}"], lat)
                setup = LESetup(full, K)
                it = LEIterate(full, setup, K)
                cons += [full, setup, it]
                le_rows.append((K, dtype, full, setup, it))
                say(
                    f"  compiled {full.name} ({full.compile_s:.1f} s), its setup alone and iterations alone"
                )
        data = LEData(lat)
        cond = Condense(lat)
        cons += [data, cond]
        peers = {}
        for peer in ("daqp", "proxsuite", "osqp"):
            if not available(peer):
                say(f"  {LABELS[peer]}: not installed, skipped")
                continue
            setting = None if peer == "daqp" else st[f"{peer}_eps"]
            peers[peer] = PeerStep(lat, peer, setting)
            cons.append(peers[peer])
            if peer == "daqp":
                peers["daqp+cond"] = PeerStep(lat, peer, setting, condense=cond)
                cons.append(peers["daqp+cond"])
        say(f"  prepared in {time.perf_counter() - t0:.1f} s; timing {len(cons)} contenders")
        b = 0
        for d in range(n_drives):
            for c in cons:
                c.start(d)
            for lo in range(1, n_steps, block):
                r = b % len(cons)
                for c in cons[r:] + cons[:r]:
                    for i in range(lo, min(lo + block, n_steps)):
                        c.step(d, i)
                b += 1
        u_ref = {(d, i): lat.ref["u0"][d, i] for d in range(n_drives) for i in range(1, n_steps)}
        ref_arr = np.stack(list(u_ref.values()))
        rows = []
        say(
            f"\nN_p = {h}: {n_drives * (n_steps - 1)} timed steps; first-step error against Clarabel "
            f"{REF_EPS:g} on the same steps\n"
        )
        say(
            "| contender | setting | median (us) | p99 (us) | worst error (Nm) | median error (Nm) | iterations median / max |"
        )
        say("| --- | --- | --- | --- | --- | --- | --- |")
        for c in cons:
            ts = np.asarray(c.times) * 1e6
            err = errors(np.stack([c.u0[k] for k in u_ref]), ref_arr) if c.u0_of else None
            its = f"{np.median(c.iterations):.0f} / {max(c.iterations)}" if c.iterations else "-"
            row = {
                "contender": c.name,
                "setting": c.setting,
                "median_us": float(np.median(ts)),
                "p99_us": float(np.percentile(ts, 99)),
                "err_max": None if err is None else err[0],
                "err_median": None if err is None else err[1],
                "iterations_median": float(np.median(c.iterations)) if c.iterations else None,
                "iterations_max": int(max(c.iterations)) if c.iterations else None,
            }
            rows.append(row)
            say(
                f"| {c.name} | {c.setting or '-'} | {row['median_us']:.1f} | {row['p99_us']:.1f} | {fmt_err(err)} | {its} |"
            )
        med = {r["contender"]: r["median_us"] for r in rows}
        res: dict[str, Any] = {"rows": rows, "drives": n_drives, "steps": n_steps, "block": block}
        res["activity"] = {k: lat.ref[k] for k in ("active_first", "active_any", "failed")}
        say("")
        for K, dtype, full, setup, it in le_rows:
            parts = (med[data.name], med[setup.name], med[it.name])
            say(
                f"LE {K} {short(dtype)} breakdown (medians): data {parts[0]:.1f} + setup {parts[1]:.1f} "
                f"+ iterations {parts[2]:.1f} = {sum(parts):.1f} us; full step {med[full.name]:.1f} us"
            )
        if "daqp" in peers:
            dq, cd, tog = med[peers["daqp"].name], med[cond.name], med[peers["daqp+cond"].name]
            say(
                f"DAQP update+solve {dq:.1f} us + condensing {cd:.1f} us = {dq + cd:.1f} us (sum of medians); "
                f"timed together {tog:.1f} us"
            )
            by_name = {r["contender"]: r for r in rows}
            ok_le = [
                (med[full.name], full.name)
                for _, _, full, _, _ in le_rows
                if by_name[full.name]["err_max"] < ERR_TARGET
            ]
            if ok_le:
                t, name = min(ok_le)
                r = by_name[name]
                verdict = "PASS" if t <= tog else "MISS"
                line = (
                    f"{verdict} latency N_p={h}: {name} {t:.1f} us (worst error {r['err_max']:.2e} Nm) "
                    f"vs DAQP update+solve + condensing {tog:.1f} us (one call; {dq + cd:.1f} us summed): "
                    f"ratio {t / tog:.2f}; target <= 1"
                )
            else:
                verdict = "MISS"
                line = f"MISS latency N_p={h}: no Local Explicit full step reaches {ERR_TARGET:g} Nm on these steps"
            say(line)
            res["target"] = {"verdict": verdict, "line": line}
        out[str(h)] = res
    return out


def run_latency_child(args: Any, settings: dict) -> dict:
    """The latency section in a child process pinned to one core; its printout relayed."""
    core = max(os.sched_getaffinity(0))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "latency.json"
        spath = Path(tmp) / "settings.json"
        spath.write_text(json.dumps(settings))
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--only",
            "latency",
            "--pin",
            str(core),
        ]
        cmd += ["--horizons", args.horizons, "--dtypes", args.dtypes, "--child-out", str(path)]
        cmd += ["--settings", str(spath)]
        if args.kkt:
            cmd += ["--kkt", args.kkt]
        cmd += ["--finish", args.finish, "--rho-method", args.rho_method]
        if args.smoke:
            cmd.append("--smoke")
        env = dict(os.environ)
        env["XLA_FLAGS"] = " ".join(
            f
            for f in env.get("XLA_FLAGS", "").split()
            if "xla_force_host_platform_device_count" not in f
        )
        say(f"\n[latency: a child process pinned to core {core}]")
        p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True, bufsize=1)
        assert p.stdout is not None
        for line in p.stdout:
            print(line, end="", flush=True)
        if p.wait() != 0:
            raise RuntimeError(f"the latency child exited {p.returncode}")
        return json.loads(path.read_text())


# -- 2. throughput -----------------------------------------------------------------------------
def matmul_peak(n: int, dtype: str, repeats: int = 3) -> float:
    """FLOP/s of an n x n matmul in JAX, rows sharded over every device, best of ``repeats``."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devs = jax.devices()
    mesh = Mesh(np.asarray(devs), ("d",))
    rows, rep = NamedSharding(mesh, PartitionSpec("d", None)), NamedSharding(mesh, PartitionSpec())
    rng = np.random.default_rng(0)
    a = jax.device_put(rng.standard_normal((n, n)).astype(dtype), rows)
    b = jax.device_put(rng.standard_normal((n, n)).astype(dtype), rep)
    f = jax.jit(lambda a, b: a @ b, out_shardings=rows)
    jax.block_until_ready(f(a, b))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(a, b))
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best


class ProxParallel:
    """proxsuite's ``solve_in_parallel`` on a ``BatchQP`` (no box form there: the bounds
    as general rows), in chunks of WORKER_CHUNK cases, one QP object per case of a chunk
    (warm from the chunk before); the condensing sharded over every device."""

    def __init__(self, horizon: int, eps: float, threads: int) -> None:
        T, data_of = problem(horizon)
        form = form_of(T, data_of)
        self.cond = jax.jit(lambda o: map_scenarios(form, o, chunk=COND_BATCH))
        self.h, self.eps, self.threads = horizon, float(eps), threads
        self.batches: dict[int, Any] = {}
        n = horizon * N_U
        self.C0 = np.vstack([np.eye(n), np.kron(np.eye(horizon), G_ROW)])

    def _batch(self, m: int) -> tuple[Any, list]:
        import proxsuite

        if m not in self.batches:
            n = self.h * N_U
            batch = proxsuite.proxqp.dense.BatchQP()
            for _ in range(m):
                batch.init_qp_in_place(n, 0, n + self.h)
            qps = [batch.get(k) for k in range(m)]  # after the last insertion (no moves)
            for q in qps:
                q.settings.eps_abs = self.eps
                q.settings.eps_rel = 0.0
                q.settings.initial_guess = (
                    proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
                )
            self.batches[m] = [batch, qps, False]
        return self.batches[m]

    def __call__(self, ops: dict, n: int) -> dict[str, Any]:
        import proxsuite

        S = ops["v_x"].shape[1]
        u0 = np.full((n, S, N_U), np.nan)
        ok = np.zeros((n, S), bool)
        t_cond = t_solve = 0.0
        t_all = time.perf_counter()
        size = min(n, WORKER_CHUNK)
        solved = proxsuite.proxqp.QPSolverOutput.PROXQP_SOLVED
        for lo in range(0, n, size):
            m = min(size, n - lo)
            idx = np.minimum(np.arange(lo, lo + size), n - 1)
            chunk_ops = {k: v[idx].reshape(size * S, *v.shape[2:]) for k, v in ops.items()}
            t0 = time.perf_counter()
            H, f, ub, lb, gu, gl = (
                np.array(x).reshape(size, S, *x.shape[1:]) for x in self.cond(chunk_ops)
            )
            t1 = time.perf_counter()
            entry = self._batch(size)
            batch, qps, started = entry
            for s in range(S):
                for c in range(size):
                    D = 0.5 * (ub[c, s] - lb[c, s])
                    Hs = D[:, None] * H[c, s] * D[None, :]
                    lo_, up_ = (
                        np.concatenate([lb[c, s] / D, gl[c, s]]),
                        np.concatenate([ub[c, s] / D, gu[c, s]]),
                    )
                    if not started:
                        C = self.C0.copy()
                        C[H.shape[-1] :] *= D[None, :]
                        qps[c].init(Hs, D * f[c, s], None, None, C, lo_, up_)
                    else:
                        qps[c].update(H=Hs, g=D * f[c, s], l=lo_, u=up_)
                started = entry[2] = True
                proxsuite.proxqp.dense.solve_in_parallel(batch, self.threads)
                for c in range(m):
                    D = 0.5 * (ub[c, s] - lb[c, s])
                    u0[lo + c, s] = (D * qps[c].results.x)[:N_U]
                    ok[lo + c, s] = qps[c].results.info.status == solved
            t_cond += t1 - t0
            t_solve += time.perf_counter() - t1
        return {
            "wall": time.perf_counter() - t_all,
            "cond": t_cond,
            "solve": t_solve,
            "u0": u0,
            "ok": ok,
        }


def section_throughput(
    args: Any,
    settings: dict,
    refs: dict,
    horizons: list[int],
    dtypes: list[str],
    cases: dict,
    sizes: list[int],
    n_ref: int,
) -> dict:
    S = cases["v_x"].shape[1]
    cores = sorted(os.sched_getaffinity(0))
    devs = jax.devices()
    W = len(cores)
    out: dict[str, Any] = {"sizes": sizes, "steps": S, "devices": len(devs), "workers": W}
    say(
        f"\n## throughput: batches of drives of {S} steps; Local Explicit on {len(devs)} XLA device(s); "
        f"DAQP, OSQP, proxsuite: {W} pinned process(es) (cores {cores}); qpax on 1 device"
    )
    peak_n = SMOKE_PEAK_N if args.smoke else PEAK_N
    peak = {dt: matmul_peak(peak_n, dt) for dt in ("float64", "float32")}
    out["peak_flops"] = peak
    out["peak_n"] = peak_n
    say(
        f"matmul peak ({peak_n} x {peak_n}, sharded over {len(devs)} device(s), best of 3): "
        f"float64 {peak['float64'] / 1e9:.1f} GFLOP/s, float32 {peak['float32'] / 1e9:.1f} GFLOP/s"
    )
    have = {p: available(p) for p in ("daqp", "osqp", "proxsuite", "qpax")}
    pool = (
        PeerPool(cases, S, cores) if any(have[p] for p in ("daqp", "osqp", "proxsuite")) else None
    )
    out["targets"] = []
    try:
        for h in horizons:
            out[str(h)] = throughput_one(
                args,
                h,
                settings[str(h)],
                refs[str(h)],
                dtypes,
                cases,
                sizes,
                n_ref,
                pool,
                have,
                peak,
                W,
                out["targets"],
            )
    finally:
        if pool is not None:
            pool.close()
    return out


def _le_runner(le: LEBatch, cases: dict) -> Any:
    def run(B: int) -> tuple[dict, dict]:
        wall, out = le.run(cases, B)
        return {le.name: wall}, out

    return run


def _le_setup_runner(le: LEBatch, cases: dict) -> Any:
    def run(B: int) -> tuple[dict, dict]:
        return {f"{le.name} data + setup": le.run_setup(cases, B)}, {}

    return run


def throughput_one(
    args, h, st, ref, dtypes, cases, sizes, n_ref, pool, have, peak, W, targets
) -> dict:
    """The throughput section at one N_p: every contender at every batch size."""
    S = cases["v_x"].shape[1]
    T, data_of = problem(h)
    kkts = le_kkts(args, T)
    say(f"\n### N_p = {h}: Local Explicit KKT solves {kkts}, dtypes {dtypes}\n")
    u_ref = ref["u0"]
    # contenders: name -> callable(B) -> (times {row: s}, outputs {u0, ...})
    cons: dict[str, Any] = {}
    les = {}
    for dtype in dtypes:
        for K in kkts:
            le = le_batch(h, K, dtype, st["le_tol"][f"{K}/{dtype}"])
            les[le.name] = le
            cons[le.name] = _le_runner(le, cases)
    for peer in ("daqp", "osqp", "proxsuite"):
        if not have[peer]:
            say(f"{LABELS[peer]}: not installed, skipped")
            continue
        setting = None if peer == "daqp" else st[f"{peer}_eps"]
        label = LABELS[peer]

        def run_pool(B: int, peer=peer, setting=setting, label=label) -> tuple:
            r = pool(peer, h, setting, B)
            times = {f"{label} solve": r["solve"], f"{label} + condensing": r["wall"]}
            if peer == "daqp":
                times["condensing alone"] = r["cond"]
            return times, r

        cons[label] = run_pool
    if have["proxsuite"]:
        par = ProxParallel(h, st["proxsuite_eps"], W)

        def run_par(B: int) -> tuple:
            r = par(cases, B)
            return {
                "proxsuite solve_in_parallel": r["solve"],
                "proxsuite solve_in_parallel + condensing": r["wall"],
            }, r

        cons["proxsuite solve_in_parallel"] = run_par
    if have["qpax"]:
        qprog = qpax_program(form_of(T, data_of), h)
        dev = jax.devices()[0]
        iters = st["qpax_iters"]

        def run_qpax(B: int) -> tuple:
            m = min(B, CALL_CASES)
            chunks = [flat(take(cases, c * m, c * m + m)) for c in range(math.ceil(B / m))]
            t0 = time.perf_counter()
            first = None
            for c in chunks:
                r = jax.block_until_ready(qprog(jax.device_put(c, dev), 0.0, iters))
                first = r if first is None else first
            wall = time.perf_counter() - t0
            return {"qpax": wall}, {"u0": np.asarray(first[0]).reshape(m, S, N_U)}

        cons["qpax"] = run_qpax
    setup_B = max([B for B in sizes if B <= CALL_CASES] or [min(sizes)])
    for le in les.values():
        cons[f"{le.name} data + setup"] = _le_setup_runner(le, cases)
    seen: dict[str, set] = {k: set() for k in cons}
    times: dict[int, dict[str, list[float]]] = {}
    outputs: dict[str, tuple[int, dict]] = {}
    per_step: dict[str, float] = {}  # contender -> s a step at its last size (for the budget)
    skipped: dict[int, list[str]] = {}
    rows = []
    for bi, B in enumerate(sizes):
        active = []
        for name in cons:
            if name.endswith("data + setup") and B != setup_B:
                continue
            is_target = name.startswith("LE ") or name == "DAQP"
            est = per_step.get(name, 0.0) * B * S
            if not args.smoke and not is_target and est > PEER_BUDGET_S:
                skipped.setdefault(B, []).append(f"{name} (about {est:.0f} s a call)")
                continue
            active.append(name)
        repeats = args.repeats if B <= CALL_CASES else 1
        t_size = time.perf_counter()
        for name in active:  # warm-up: compiles, a worker's first chunk size, DAQP's setup
            key = min(B, CALL_CASES)
            if key not in seen[name]:
                seen[name].add(key)
                cons[name](B)
        times[B] = {}
        for r in range(repeats):
            k = (r + bi) % len(active)
            for name in active[k:] + active[:k]:
                tm, o = cons[name](B)
                for row, t in tm.items():
                    times[B].setdefault(row, []).append(t)
                per_step[name] = max(tm.values()) / (B * S)
                if "u0" in o and (name not in outputs or outputs[name][0] < B):
                    outputs[name] = (B, o)
        say(
            f"  {B:,} cases: {len(active)} contenders x {repeats} call(s) in {time.perf_counter() - t_size:.1f} s"
            + (f"; skipped: {', '.join(skipped[B])}" if B in skipped else "")
        )
        med = {row: float(np.median(ts)) for row, ts in times[B].items()}
        for row, t in med.items():
            rows.append(
                {
                    "cases": B,
                    "contender": row,
                    "s": t,
                    "steps_per_s": B * S / t,
                    "calls": len(times[B][row]),
                }
            )

    # tables
    def times_rows(name: str) -> list[str]:
        """The table rows of contender ``name``, in the order of the contenders."""
        if name in LABELS.values():
            return [f"{name} solve", f"{name} + condensing"] + (
                ["condensing alone"] if name == "DAQP" else []
            )
        if name == "proxsuite solve_in_parallel":
            return [name, f"{name} + condensing"]
        return [name]

    def rate(B: int, row: str) -> float | None:
        ts = times.get(B, {}).get(row)
        return B * S / float(np.median(ts)) if ts else None

    say(
        f"\nN_p = {h}: steps per second (cases x {S} steps / median call; a peer's 'solve' is its slowest "
        f"worker's solve time, '+ condensing' the call's wall time)\n"
    )
    say("| cases | contender | steps/s | / DAQP solve | / (DAQP + condensing) |")
    say("| --- | --- | --- | --- | --- |")
    order = [r for n in cons for r in times_rows(n)]
    for B in sizes:
        d_solve, d_all = rate(B, "DAQP solve"), rate(B, "DAQP + condensing")
        for row in sorted(times[B], key=lambda r: order.index(r) if r in order else len(order)):
            v = rate(B, row)
            r1 = f"{v / d_solve:.2f}" if d_solve else "-"
            r2 = f"{v / d_all:.2f}" if d_all else "-"
            say(f"| {B:,} | {row} | {v:,.0f} | {r1} | {r2} |")
    # accuracy
    say(
        f"\nN_p = {h}: first-step error against Clarabel {REF_EPS:g} on the first cases (all their steps) of each contender's largest run\n"
    )
    say("| contender | setting | worst error (Nm) | median error (Nm) | cases x steps | solved |")
    say("| --- | --- | --- | --- | --- | --- |")
    acc = {}
    for name, (_, o) in outputs.items():
        k = min(n_ref, o["u0"].shape[0])
        e = errors(o["u0"][:k], u_ref[:k])
        if name.startswith("LE "):
            setting = f"tol {les[name].tol:g}"
            solved = float(np.mean(o["status"][:k] == Status.SOLVED))
        elif name == "qpax":
            setting = f"{st['qpax_iters']} iterations"
            solved = float("nan")
        else:
            setting = (
                "exact"
                if name == "DAQP"
                else f"eps {st['proxsuite_eps' if 'proxsuite' in name else 'osqp_eps']:g}"
            )
            solved = float(np.mean(o["ok"][:k]))
        acc[name] = {
            "err_max": e[0],
            "err_median": e[1],
            "cases": k,
            "setting": setting,
            "solved": solved,
        }
        sv = "-" if np.isnan(solved) else f"{100 * solved:.1f} %"
        say(f"| {name} | {setting} | {e[0]:.2e} | {e[1]:.2e} | {k} x {S} | {sv} |")
    # breakdown and flops
    say(
        f"\nN_p = {h}: Local Explicit, data + setup alone against the full step (us a step, {setup_B:,} cases, {len(jax.devices())} device(s))\n"
    )
    say("| contender | data + setup | full step | setup share | iterations mean |")
    say("| --- | --- | --- | --- | --- |")
    brk = {}
    for name in les:
        ts, tf = rate(setup_B, f"{name} data + setup"), rate(setup_B, name)
        if not ts or not tf:
            continue
        its = float(np.mean(outputs[name][1]["iterations"])) if name in outputs else float("nan")
        brk[name] = {
            "setup_us": 1e6 / ts,
            "full_us": 1e6 / tf,
            "share": tf / ts,
            "iterations_mean": its,
        }
        say(f"| {name} | {1e6 / ts:.1f} | {1e6 / tf:.1f} | {100 * tf / ts:.0f} % | {its:.1f} |")
    say(
        f"\nN_p = {h}: Local Explicit's flop rate at its largest batch (XLA: the batched program's own count, "
        "a loop body counted once; estimate: every solve's data + setup + mean iterations x one iteration)\n"
    )
    say(
        "| contender | cases | XLA flops a call | GFLOP/s (XLA) | % of peak | est. flops a step | GFLOP/s (est.) | % of peak |"
    )
    say("| --- | --- | --- | --- | --- | --- | --- | --- |")
    flops = {}
    op0 = {k: v[0, 0] for k, v in cases.items()}
    for name, le in les.items():
        Bs = [B for B in sizes if times.get(B, {}).get(name)]
        if not Bs:
            continue
        B = Bs[-1]
        m = min(B, CALL_CASES)
        t_call = float(np.median(times[B][name])) / math.ceil(B / m)
        f_prog = le.flops_program.get(m, float("nan"))
        f_setup, f_step = le.piece_flops(op0)
        its = float(np.mean(outputs[name][1]["iterations"]))
        f_est = f_setup + its * f_step
        r_xla, r_est = f_prog / t_call, f_est * m * S / t_call
        pk = peak[le.dtype]
        flops[name] = {
            "cases": B,
            "flops_program": f_prog,
            "gflops_xla": r_xla / 1e9,
            "flops_setup": f_setup,
            "flops_iteration": f_step,
            "flops_step_est": f_est,
            "gflops_est": r_est / 1e9,
            "peak_gflops": pk / 1e9,
        }
        say(
            f"| {name} | {B:,} | {f_prog:.3g} | {r_xla / 1e9:.2f} | {100 * r_xla / pk:.2f} % | {f_est:.3g} | {r_est / 1e9:.2f} | {100 * r_est / pk:.1f} % |"
        )
    say(
        f"\nN_p = {h}: each piece of Local Explicit's step against its flop floor (us a case-step; "
        f"the floor is XLA's flops of the piece at the {len(jax.devices())}-device matmul peak; "
        f"iterations = full step - data + setup, {setup_B:,} cases)\n"
    )
    say("| contender | piece | us a case-step | flops | floor (us) | time / floor |")
    say("| --- | --- | --- | --- | --- | --- |")
    floors: dict[str, Any] = {}
    for name in les:
        if name not in brk or name not in flops:
            continue
        b, fl = brk[name], flops[name]
        pk = fl["peak_gflops"] * 1e9
        pieces = {
            "data + setup": (b["setup_us"], fl["flops_setup"]),
            f"iterations ({b['iterations_mean']:.1f})": (
                b["full_us"] - b["setup_us"],
                b["iterations_mean"] * fl["flops_iteration"],
            ),
        }
        floors[name] = {}
        for piece, (us, f) in pieces.items():
            floor = 1e6 * f / pk
            floors[name][piece] = {"us": us, "flops": f, "floor_us": floor}
            say(f"| {name} | {piece} | {us:.1f} | {f:.3g} | {floor:.2f} | {us / floor:.0f}x |")
    # targets
    say("")
    for B in (1000, 10000):
        d = rate(B, "DAQP solve")
        cand = [
            (rate(B, n), n)
            for n in les
            if rate(B, n) and n in acc and acc[n]["err_max"] < ERR_TARGET
        ]
        if d is None:
            line = f"NOT RUN throughput N_p={h}, {B:,} cases (not in this run's sizes, or no DAQP)"
            verdict = "NOT RUN"
        elif not cand:
            verdict = "MISS"
            line = (
                f"MISS throughput N_p={h}, {B:,} cases: no Local Explicit reaches {ERR_TARGET:g} Nm"
            )
        else:
            v, n = max(cand)
            verdict = "PASS" if v >= 2 * d else "MISS"
            line = (
                f"{verdict} throughput N_p={h}, {B:,} cases: {n} {v:,.0f} steps/s = {v / d:.2f}x DAQP's "
                f"QP solve alone ({d:,.0f} steps/s; {v / rate(B, 'DAQP + condensing'):.2f}x DAQP + condensing), "
                f"worst error {acc[n]['err_max']:.2e} Nm; target >= 2x at < {ERR_TARGET:g} Nm"
            )
        say(line)
        targets.append({"horizon": h, "cases": B, "verdict": verdict, "line": line})
    return {
        "kkts": kkts,
        "rows": rows,
        "accuracy": acc,
        "breakdown": brk,
        "flops": flops,
        "floors": floors,
        "skipped": {str(k): v for k, v in skipped.items()},
        "compile_s": {n: {str(k): v for k, v in le.compile_s.items()} for n, le in les.items()},
        "settings": {k: v for k, v in st.items() if k != "scans"},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=SECTIONS, help="run one of the two sections")
    ap.add_argument(
        "--horizons", default=None, help="comma-separated N_p (default 10,20; --smoke 10)"
    )
    ap.add_argument(
        "--dtypes",
        default=None,
        help="Local Explicit's dtypes (default float64,float32; --smoke float64)",
    )
    ap.add_argument(
        "--kkt",
        default=None,
        help="comma-separated KKT solves (default: every one select_kkt accepts but 'auto'; --smoke: the one 'auto' picks)",
    )
    ap.add_argument(
        "--finish",
        default="none",
        help="Local Explicit's finish: none (default, the paper's iteration) or active_set",
    )
    ap.add_argument(
        "--rho-method",
        default="power",
        help="Local Explicit's rho rule: power (default), carried, eigh or given",
    )
    ap.add_argument("--max-batch", type=int, default=None, help="largest batch size")
    ap.add_argument("--full", action="store_true", help="add 100,000 cases")
    ap.add_argument(
        "--steps", type=int, default=None, help="steps per throughput drive (default 10; --smoke 3)"
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="timed calls per contender and size (default 3; --smoke 1)",
    )
    ap.add_argument(
        "--devices",
        type=int,
        default=None,
        help="XLA CPU devices (set before JAX starts; default: the cores of this process's affinity)",
    )
    ap.add_argument(
        "--smoke",
        action="store_true",
        help="tiny sizes, a check of the code; no result file unless --out",
    )
    _meta.add_out_argument(ap, STEM)
    # internal: the latency child
    ap.add_argument("--pin", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child-out", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--settings", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.horizons is None:
        args.horizons = "10" if args.smoke else "10,20"
    if args.dtypes is None:
        args.dtypes = "float64" if args.smoke else "float64,float32"
    if args.steps is None:
        args.steps = 3 if args.smoke else 10
    if args.repeats is None:
        args.repeats = 1 if args.smoke else 3
    args.kkt_list = args.kkt.split(",") if args.kkt else None
    LE_OPTIONS.update(finish=args.finish, rho_method=args.rho_method)
    horizons = [int(h) for h in args.horizons.split(",")]
    dtypes = args.dtypes.split(",")
    sizes = list(SMOKE_SIZES if args.smoke else SIZES + (FULL_SIZES if args.full else ()))
    if args.max_batch is not None:
        sizes = [n for n in sizes if n <= args.max_batch]
    sections = [args.only] if args.only else list(SECTIONS)
    if "throughput" in sections and not sizes:
        ap.error("--max-batch leaves no batch size")
    n_ref = min(REF_CASES, max(sizes)) if sizes else REF_CASES
    child = args.child_out is not None
    run = None if child else _meta.Run(_meta.output_path(args, STEM))
    say(
        f"jax {jax.__version__}; {len(jax.devices())} XLA CPU device(s); affinity {sorted(os.sched_getaffinity(0))}; "
        f"KKT_SOLVES {kkt_module.KKT_SOLVES}; target: worst first-step error < {ERR_TARGET:g} Nm against "
        f"Clarabel {REF_EPS:g}"
    )
    results: dict[str, Any] = {
        "horizons": horizons,
        "dtypes": dtypes,
        "err_target": ERR_TARGET,
        "general_rows": {"G": G_ROWS, "g": G_RHS},
        "tuned": TUNED,
    }
    n_cases = max(max(sizes), n_ref) if "throughput" in sections else n_ref
    t0 = time.perf_counter()
    cases = drives(range(n_cases), args.steps)
    settings: dict[str, Any] = {}
    refs: dict[str, Any] = {}
    if args.settings is not None:
        settings = json.loads(args.settings.read_text())
    else:
        say(
            f"{n_cases:,} throughput drives of {args.steps} steps generated in {time.perf_counter() - t0:.1f} s"
        )
        for h in horizons:
            kkts = le_kkts(args, topology(h))
            settings[str(h)], refs[str(h)] = calibrate(h, dtypes, kkts, cases, n_ref)
        results["calibration"] = settings
        results["reference"] = {
            h: {k: r[k] for k in ("active_first", "active_any", "failed")} for h, r in refs.items()
        }
    if "latency" in sections:
        if len(os.sched_getaffinity(0)) > 1 and not child:
            results["latency"] = run_latency_child(args, settings)
        else:
            results["latency"] = section_latency(args, settings, horizons, dtypes)
    if child:
        args.child_out.write_text(json.dumps(results["latency"], default=_meta._jsonable))
        return 0
    if "throughput" in sections:
        results["throughput"] = section_throughput(
            args, settings, refs, horizons, dtypes, cases, sizes, n_ref
        )
    say("\n## targets\n")
    for lat in results.get("latency", {}).values():
        if "target" in lat:
            say(lat["target"]["line"])
    for t in results.get("throughput", {}).get("targets", []):
        say(t["line"])
    assert run is not None
    run.results = results
    run.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
