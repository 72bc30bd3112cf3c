"""A whole sweep: cases of a family against a grid of rho scales, streamed in chunks to Parquet.

:func:`run_sweep` draws the cases chunk by chunk (each chunk ``chunk`` cases
times the grid's P points), solves the (case, point) pairs of a chunk in
calls of the compiled program (:func:`~ampc_jax.sweep.engine.sweep_solve`:
compaction, the pair axis sharded over every device of every process) of
about :data:`SUB_PAIRS` pairs per device each, compares each pair's
first-step inputs with the integrated optimum (Clarabel on the condensed QP,
once per case) and writes one Parquet file per chunk under ``OUT/chunks/``.
At the end the chunks are joined into ``OUT/sweep.parquet`` (one row per case
and point, the run's metadata in the schema and in ``OUT/sweep.json``) and the
figures are drawn (:mod:`ampc_jax.sweep.figures`).

Resume and refusal: every chunk carries the hash of the spec that wrote it
and the cases it holds (its Parquet metadata, key ``ampc_sweep``). A rerun
with the same spec skips the chunks already written; any file under
``OUT/chunks/`` of another spec, another chunk layout, unreadable or with
rows missing, and an ``OUT/sweep.json`` of another spec or unreadable, are
refused before anything runs (ValueError ``out: ...``), so a table never
mixes two sweeps (:func:`check_out`).

Memory: a call of the program holds about SUB_PAIRS pairs per device, a chunk
its rows, the join every row; all three are estimated from the family's case
size and refused up front against the memory the machine has
(:func:`check_memory`; ``--rho``, ``--chunk`` or ``--cases`` named). 10,000
cases x 30 points is 40 chunks of 256 cases and a 300,000-row table.

With several processes (``jax.distributed.initialize()`` before the call),
every process runs the same chunks (the program is collective), writes the
rows of the pairs its own devices hold to ``chunk_NNNNN.pKofN.parquet``, and
process 0 joins the parts after a barrier
(``multihost_utils.sync_global_devices``).

A ``shard`` (``--shard I/N``) computes chunks I, I + N, ... into a directory of
its own and joins nothing; :func:`~ampc_jax.sweep.merge.merge_shards` joins them.
"""

from __future__ import annotations

import json
import subprocess
import time
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..batch import pad_cases
from ..formulations import (
    DEFAULT_FORMULATION,
    check_formulation,
    formulation,
    formulation_info,
    formulation_names,
)
from ..problem.limits import check_memory as check_problem_memory
from ..reference import reference_inputs
from ..results import STATUS
from ..validation import check_count, check_non_negative, check_relaxation
from . import memory, store
from .engine import Work, pair_data, pair_params, sweep_solve
from .families import StepCases, family
from .memory import check_points
from .store import Shard, chunk_name

__all__ = [
    "SweepSpec",
    "SweepSummary",
    "check_memory",
    "check_out",
    "drawn",
    "rho_grid",
    "run_sweep",
    "shard_chunks",
]

FORMAT = "ampc-sweep/1"

SUB_PAIRS = 1024
"""(case, point) pairs per device in one call of the compiled program. Rule: a
chunk is solved in calls of about this many pairs per device and the progress
bar moves after each; reason: a chunk of 256 cases x 13 points was one call,
so the bar moved once per chunk (several seconds to minutes), and the memory
of a call is bounded whatever ``--chunk`` is."""

LOOP_SUB_PAIRS = 32
"""Closed-loop pairs per device in one call: each is a whole manoeuvre (320
control steps for the cruise lane change), and the runs go 8 pairs at a time inside the call
(:func:`~ampc_jax.sweep.loops.loop_pairs`), so small calls cost nothing and
keep the bar moving."""


def rho_grid(text: str) -> tuple[float, ...]:
    """A rho-scale grid from ``LO:HI:N`` (N points, geometric) or ``a,b,c``; ValueError otherwise.

    Every call of the program holds all N points of at least one case, so N
    points that cannot fit in the available memory are refused before the grid
    is formed (:func:`~ampc_jax.sweep.memory.check_points`)."""
    t = str(text).strip()
    n_i = None
    try:
        if ":" in t:
            lo, hi, n = t.split(":")
            lo_f, hi_f, n_i = float(lo), float(hi), int(n)
            if n_i < 1 or not (np.isfinite(lo_f) and np.isfinite(hi_f)) or lo_f <= 0 or hi_f <= 0:
                raise ValueError
        else:
            vals = np.array([float(x) for x in t.split(",") if x.strip()])
    except ValueError:
        raise ValueError(
            f"expected LO:HI:N (N geometric points) or a comma list of positive numbers, "
            f"got {t[:80]!r}"
        ) from None
    check_points(n_i if n_i is not None else vals.size)
    if n_i is not None:
        vals = np.geomspace(lo_f, hi_f, n_i)
    if vals.size == 0 or not np.all(np.isfinite(vals) & (vals > 0)):
        raise ValueError(f"expected positive finite rho scales, got {t[:80]!r}")
    return tuple(float(v) for v in vals)


@dataclass(frozen=True)
class SweepSpec:
    """What a sweep is (everything that decides its rows; a resumed run must match it).

    family : a registered step family (:data:`~ampc_jax.sweep.families.FAMILIES`).
    cases : number of cases (case indices 0 .. cases-1 of the family under ``seed``).
    rho : the rho scales (factors on eq.opt_ro's rho_j*, the same for every objective).
    formulation : a registered formulation (default ``local_explicit``; ``fully_distributed``,
        ``virtual_center``, ``integrated``); a closed-loop family takes those that are
        decomposed and serve closed loops.
    seed : the family's seed (default 0).
    tol : eps_r = eps_s of eq.Convergence (squared norms; default: the example's
        closed-loop tolerance, 1 Nm^2, for the vehicle families and 1e-6 otherwise).
    relaxation, anderson, max_iter : the solver's over-relaxation (default 1), Anderson
        memory (default 0) and iteration cap (default 500).
    horizon : N_p of a vehicle or generated family (default: the family's own).
    chunk : cases per chunk (default 256); the memory bound and the resume grain.
    float32 : solve in float32 (default float64).
    compaction : re-batch the pairs still running between segments (default True).
    duration : simulated seconds of a closed-loop family's runs (default: the scenario's).
    groups : agent groups of a vehicle step family: ``"paper"`` (default, the
        example's own) or ``"full"`` (every agent in every group: the exact
        decomposition, :data:`~ampc_jax.sweep.families.GROUPS`).

    A closed-loop family (``kind="loop"``) gives one row per (manoeuvre, point)
    with the run's reductions (:class:`~ampc_jax.sweep.loops.LoopRow`); its
    ``iterations`` column is the mean per control step.
    """

    family: str
    cases: int
    rho: tuple[float, ...]
    formulation: str = DEFAULT_FORMULATION
    seed: int = 0
    tol: float | None = None
    relaxation: float = 1.0
    anderson: int = 0
    max_iter: int = 500
    horizon: int | None = None
    chunk: int = 256
    float32: bool = False
    compaction: bool = True
    duration: float | None = None
    groups: str | None = None

    def __post_init__(self) -> None:
        fam = family(self.family)
        if fam.kind == "loop":
            names = formulation_names(decomposed=True, closed_loop=True)
            if self.formulation not in names:
                raise ValueError(
                    f"formulation: a closed-loop family runs one of {list(names)}, "
                    f"got {self.formulation!r}"
                )
        else:
            check_formulation(self.formulation)
        if fam.kind == "step" and self.duration is not None:
            raise ValueError(f"duration: family {self.family!r} is of single steps")
        for name in ("cases", "chunk", "max_iter"):
            check_count(getattr(self, name), name)
        object.__setattr__(self, "rho", tuple(float(r) for r in self.rho))
        if not self.rho or not all(np.isfinite(r) and r > 0 for r in self.rho):
            raise ValueError(f"rho: expected positive finite scales, got {self.rho!r}")
        if self.tol is not None:
            check_non_negative(self.tol, "tol")
        check_relaxation(self.relaxation)

    @property
    def dtype(self) -> Any:
        return jnp.float32 if self.float32 else jnp.float64


@dataclass
class SweepSummary:
    """What :func:`run_sweep` did: the table's path, the figures, timings and the work."""

    out: Path
    table: Path | None
    figures: list[Path]
    rows: int
    wall_s: float
    solve_s: float
    reference_s: float
    chunks_run: int
    chunks_skipped: int
    computed: int
    needed: int
    devices: int
    processes: int
    steady_pairs_per_s: float | None = None  # after the first chunk, which compiles

    @property
    def waste(self) -> float:
        return Work(self.computed, self.needed).waste


def git_commit() -> str:
    """The short commit of the package's checkout (``unknown`` outside git)."""
    try:
        r = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return r.stdout.strip() or "unknown"


def _solver(spec: SweepSpec, topology: Any) -> Any:
    """The formulation of ``spec`` with its batched KKT form (``info.batch_kkt``:
    the explicit formulations declare the Riccati recursion, whose setup is 3.4x
    to 5x cheaper than the condensed forms' on a vmapped batch of single steps
    at N_p = 10 and 20, docs/bench_peers.md, "Where the cost goes"; drives
    scanned in chunks of 32 favour woodbury_factored instead, bench/bench_peers.py)."""
    kkt = formulation_info(spec.formulation).batch_kkt
    extra = {} if kkt is None else {"kkt": kkt}
    return formulation(
        spec.formulation, topology, max_iter=spec.max_iter, anderson=spec.anderson, **extra
    )


def _tol(spec: SweepSpec, cases: StepCases) -> float:
    if spec.tol is not None:
        return float(spec.tol)
    return float(cases.config.tol_primal) if cases.config is not None else 1e-6


def _local_rows(arrays: Any) -> tuple[np.ndarray, Any]:
    """The pair indices and values of the shards this process holds (all of them
    with one process), in pair order."""
    leaves, tree = jax.tree.flatten(arrays)
    first = leaves[0]
    if jax.process_count() == 1:
        idx = np.arange(first.shape[0])
        return idx, jax.tree.unflatten(tree, [np.asarray(x) for x in leaves])
    starts = sorted(
        {s.index[0].start or 0: s for s in first.addressable_shards}.items(), key=lambda kv: kv[0]
    )
    idx = np.concatenate([np.arange(k, k + s.data.shape[0]) for k, s in starts])

    def local(x: Any) -> np.ndarray:
        parts = {s.index[0].start or 0: np.asarray(s.data) for s in x.addressable_shards}
        return np.concatenate([parts[k] for k in sorted(parts)])

    return idx, jax.tree.unflatten(tree, [local(x) for x in leaves])


def _chunk_names(k: int) -> list[str]:
    n = jax.process_count()
    return [chunk_name(k, p, n) for p in range(n)]


def _chunk_done(out: Path, k: int) -> bool:
    return all((out / "chunks" / name).exists() for name in _chunk_names(k))


def _spec_dict(spec: SweepSpec) -> dict[str, Any]:
    d = asdict(spec)
    d["rho"] = list(spec.rho)
    return d


def shard_chunks(spec: SweepSpec, n_dev: int, shard: Shard | None) -> tuple[int, range]:
    """(cases per chunk, the chunks a run computes): every chunk of the layout on
    ``n_dev`` devices, or ``shard``'s chunks of the layout of ``spec.chunk``
    cases (ValueError ``shard:`` with fewer chunks than shards)."""
    chunk, n_chunks = _layout(spec, n_dev if shard is None else 1)
    return chunk, range(n_chunks) if shard is None else shard.chunks(n_chunks, chunk)


def drawn(spec: SweepSpec, start: int, n: int) -> tuple[dict[str, np.ndarray], float]:
    """The columns the family draws for cases ``start .. start + n - 1`` and the
    ``tol`` the rows carry: what :func:`~ampc_jax.sweep.store.check_drawn`
    checks a chunk of them against."""
    fam = family(spec.family)
    cases = fam.sample(n, spec.seed, start, **_sample_options(spec, fam))
    return cases.columns, _tol(spec, cases)


def _layout(spec: SweepSpec, n_dev: int) -> tuple[int, int]:
    """(cases per chunk, number of chunks): ``spec.chunk`` rounded up to a multiple
    of the device count, and never beyond the cases (no padding to a huge chunk)."""
    cases = -(-spec.cases // n_dev) * n_dev
    chunk = min(-(-spec.chunk // n_dev) * n_dev, cases)
    return chunk, -(-spec.cases // chunk)


def _sub_cases(chunk: int, points: int, n_dev: int, kind: str = "step") -> int:
    """Cases per call of the program: about :data:`SUB_PAIRS` pairs per device
    (:data:`LOOP_SUB_PAIRS` for closed loops), at least one case per device,
    splitting the chunk into equal calls."""
    pairs = LOOP_SUB_PAIRS if kind == "loop" else SUB_PAIRS
    per_call = max(1, pairs // points) * n_dev
    calls = -(-chunk // per_call)
    sub = -(-chunk // calls)
    return -(-sub // n_dev) * n_dev


def check_out(out: str | Path, spec: SweepSpec, n_dev: int, shard: Shard | None = None) -> None:
    """:func:`~ampc_jax.sweep.store.check_out` for ``spec`` on ``n_dev`` devices
    (``shard``: this run's): ValueError ``out: ...`` when ``out`` holds anything
    of another sweep or shard."""
    chunk, _ = shard_chunks(spec, n_dev, shard)
    store.check_out(
        out,
        _spec_dict(spec),
        cases=spec.cases,
        points=len(spec.rho),
        chunk=chunk,
        processes=jax.process_count(),
        shard=shard,
    )


def check_memory(
    spec: SweepSpec, kind: str, case_bytes: int, devs: list, *, available: int | None = None
) -> dict[str, int]:
    """:func:`~ampc_jax.sweep.memory.check_memory` for ``spec`` on ``devs`` (a case
    of ``case_bytes``; ``kind`` ``"step"`` or ``"loop"``): the estimates, or
    ValueError ``rho:``, ``chunk:`` or ``cases:``."""
    n_dev = len(devs)
    chunk, _ = _layout(spec, n_dev)
    P = len(spec.rho)
    return memory.check_memory(
        cases=spec.cases,
        points=P,
        chunk=chunk,
        call_cases=_sub_cases(chunk, P, n_dev, kind),
        kind=kind,
        case_bytes=case_bytes,
        devs=devs,
        available=available,
    )


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    progress: bool | None = None,
    figures: bool = True,
    devices: Any = None,
    shard: Shard | None = None,
) -> SweepSummary:
    """Run (or resume) the sweep ``spec`` into the directory ``out``; see the module docstring.

    ``progress``: a bar over the cases (cases/s, ETA; the compaction waste for
    single steps) on process 0, moved after every call of the program: None
    (default) on a terminal only, True always, False never. ``figures``: draw
    them (default True). ``devices``: the devices to shard over (default all,
    every process's). ``shard``: compute only that shard's chunks and join
    nothing (one process; ``table`` None). Before anything runs, ``out`` is
    checked (:func:`check_out`) and the memory estimated (:func:`check_memory`).
    """
    import pyarrow as pa
    import pyarrow.parquet as pq
    from tqdm import tqdm

    t_start = time.perf_counter()
    out = Path(out)
    lead = jax.process_index() == 0
    fam = family(spec.family)
    if fam.kind == "loop" and jax.process_count() > 1:
        raise ValueError(
            "family: closed-loop sweeps run in one process (its devices sharded); "
            "several machines run them as shards"
        )
    if shard is not None and jax.process_count() > 1:
        raise ValueError("shard: a shard runs in one process (its devices sharded)")
    devs = list(jax.devices() if devices is None else devices)
    n_dev = len(devs)
    chunk, ks = shard_chunks(spec, n_dev, shard)
    check_out(out, spec, n_dev, shard)
    P = len(spec.rho)
    sub = _sub_cases(chunk, P, n_dev, fam.kind)
    options = _sample_options(spec, fam)
    check_memory(spec, fam.kind, _case_bytes(spec, fam, options), devs)
    (out / "chunks").mkdir(parents=True, exist_ok=True)
    mine = store.spec_hash(_spec_dict(spec))
    meta = {
        "format": FORMAT,
        "spec": _spec_dict(spec),
        "spec_hash": mine,
        "chunk_cases": chunk,
        "call_cases": sub,
        "commit": git_commit(),
        "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "jax": jax.__version__,
        "devices": n_dev,
        "processes": jax.process_count(),
        "platform": devs[0].platform,
        **({} if shard is None else {"shard": list(shard)}),
    }
    if lead:
        (out / "sweep.json").write_text(json.dumps(meta, indent=2) + "\n")
    bar = tqdm(
        total=sum(min(chunk, spec.cases - k * chunk) for k in ks),
        unit="case",
        desc=f"sweep {spec.family}",
        disable=True if (progress is False or not lead) else (None if progress is None else False),
    )
    solve_s = ref_s = 0.0
    chunk_s: list[float] = []  # the first one compiles the program
    run = skipped = 0
    computed = needed = 0
    topology_names: tuple[str, ...] = ()
    for k in ks:
        start = k * chunk
        n = min(chunk, spec.cases - start)
        cases = fam.sample(n, spec.seed, start, **options)
        if _chunk_done(out, k):
            # a chunk's identity is its content: its rows must hold the cases
            # this spec draws for it, whatever its record says
            for name in _chunk_names(k):
                store.check_drawn(out / "chunks" / name, cases.columns, start, _tol(spec, cases))
            skipped += 1
            bar.update(n)
            continue
        parts: list[dict[str, Any]] = []
        chunk_s.append(0.0)
        for s0 in range(0, n, sub):
            m = min(sub, n - s0)
            part = _slice_cases(cases, s0, m)
            t0 = time.perf_counter()
            if fam.kind == "step":
                cols, names, work, ref_t = _step_rows(spec, part, m, sub, devs)
                computed += work[0]
                needed += work[1]
                ref_s += ref_t
            else:
                cols, names = _loop_rows(spec, part, m, sub)
                ref_t = 0.0
            chunk_s[-1] += time.perf_counter() - t0 - ref_t
            parts.append(cols)
            topology_names = names
            bar.update(m)
            if fam.kind == "step":  # a closed loop's work is not counted: no waste
                bar.set_postfix(waste=f"{Work(computed, needed).waste:.2f}")
        solve_s += chunk_s[-1]
        cols = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
        path = out / "chunks" / chunk_name(k, jax.process_index(), jax.process_count())
        tmp = path.with_suffix(".tmp")
        record = {"spec_hash": mine, "chunk": k, "cases": [start, start + n]}
        table_k = pa.table(cols).replace_schema_metadata({store.META_KEY: json.dumps(record)})
        pq.write_table(table_k, tmp)
        tmp.replace(path)  # a killed run leaves no half-written chunk behind
        run += 1
    bar.close()
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("ampc sweep: chunks written")
    table = None
    figs: list[Path] = []
    rows = 0
    if lead:
        check_out(out, spec, n_dev, shard)  # nothing foreign arrived while the chunks ran
        paths = [out / "chunks" / name for k in ks for name in _chunk_names(k)]
        ranges = [(k * chunk, min((k + 1) * chunk, spec.cases)) for k in ks]
        tab = store.join_chunks(paths, ranges, P, str(out / "chunks"))
        meta.update(
            {
                "objectives": list(topology_names),
                "wall_s": time.perf_counter() - t_start,
                "solve_s": solve_s,
                "steady_pairs_per_s": _steady_rate(chunk_s, chunk * P),
                "reference_s": ref_s,
                "pair_iterations_computed": computed,
                "pair_iterations_needed": needed,
                "chunks_run": run,
                "chunks_skipped": skipped,
            }
        )
        rows = tab.num_rows
        if shard is None:
            figs = store.write_table(tab, out, meta, figures=figures)
            table = out / "sweep.parquet"
        else:  # a shard's rows are joined by the merge
            (out / "sweep.json").write_text(json.dumps(meta, indent=2) + "\n")
    return SweepSummary(
        out=out,
        table=table,
        figures=figs,
        rows=rows,
        wall_s=time.perf_counter() - t_start,
        solve_s=solve_s,
        reference_s=ref_s,
        chunks_run=run,
        chunks_skipped=skipped,
        computed=computed,
        needed=needed,
        devices=n_dev,
        processes=jax.process_count(),
        steady_pairs_per_s=_steady_rate(chunk_s, chunk * P),
    )


def _case_bytes(spec: SweepSpec, fam: Any, options: dict[str, Any]) -> int:
    """Bytes of one case's problem data (float64; a closed loop's scenario), from
    case 0. A horizon given for a step family is first checked against the
    memory of the condensed forms (:func:`~ampc_jax.problem.limits.check_memory`)
    with the family's sizes at its own horizon, before any case of that horizon
    is built."""
    if fam.kind == "loop":
        one = fam.sample(1, spec.seed, 0, **options)
        return int(sum(np.asarray(x).nbytes for x in jax.tree.leaves(one.scenarios)))
    if spec.horizon is not None:
        own = {k: v for k, v in options.items() if k != "horizon"}
        T = fam.sample(1, spec.seed, 0, **own).topology
        check_problem_memory(
            horizon=int(spec.horizon), n_x=T.n_x, n_u=T.n_u, n_y=list(T.output_sizes)
        )
    one = fam.sample(1, spec.seed, 0, **options)
    return int(sum(8 * np.size(x) for x in jax.tree.leaves(one.data)))


def _slice_cases(cases: Any, s0: int, m: int) -> Any:
    """Cases ``s0 .. s0 + m - 1`` of a chunk's :class:`StepCases` or :class:`LoopCases`."""
    cols = {k: np.asarray(v)[s0 : s0 + m] for k, v in cases.columns.items()}
    if isinstance(cases, StepCases):
        return cases._replace(data=jax.tree.map(lambda x: x[s0 : s0 + m], cases.data), columns=cols)
    return cases._replace(
        scenarios=jax.tree.map(lambda x: x[s0 : s0 + m], cases.scenarios), columns=cols
    )


def _step_rows(
    spec: SweepSpec, cases: StepCases, n: int, chunk: int, devs: list
) -> tuple[dict[str, Any], tuple[str, ...], tuple[int, int], float]:
    """Rows of a chunk of single-step cases: solve every pair, the reference per case."""
    P = len(spec.rho)
    T = cases.topology
    solver = _solver(spec, T)
    tol = _tol(spec, cases)
    grid = solver.params(
        rho=np.asarray(spec.rho)[:, None] * np.ones((1, solver.n_rho)),
        relaxation=spec.relaxation,
        tol_primal=tol,
        tol_dual=tol,
        dtype=spec.dtype,
    )
    data = pad_cases(cases.data, chunk)
    pd_, pp = pair_data(data, P), pair_params(grid, chunk)
    res, work = sweep_solve(solver, pd_, pp, devices=devs, compaction=spec.compaction)
    idx, local = _local_rows(res)
    _, wk = _local_rows(work)
    keep = idx < n * P  # padding pairs dropped
    idx = idx[keep]
    local = jax.tree.map(lambda x: x[keep], local)
    work_done = (int(np.sum(wk.computed)), int(np.sum(local.iterations)))
    case_local = idx // P
    point = idx % P
    t0 = time.perf_counter()
    mine = np.unique(case_local)
    ref = np.full((n, T.n_u), np.nan)
    ref[mine] = reference_inputs(T, jax.tree.map(lambda x: np.asarray(x)[mine], cases.data))[:, 0]
    ref_t = time.perf_counter() - t0
    e_sub = np.max(np.abs(np.asarray(local.u0, np.float64) - ref[case_local]), axis=1)
    cols: dict[str, Any] = {
        "case": cases.columns["case"][case_local],
        "point": point.astype(np.int32),
        "rho_scale": np.asarray(spec.rho)[point],
        "iterations": np.asarray(local.iterations, np.int32),
        "converged": np.asarray(local.converged, bool),
        "status": np.asarray(local.status, np.int32),
        "status_name": np.array([STATUS.get(int(s), "unknown") for s in local.status]),
        "e_sub": e_sub,
        "violation": np.asarray(local.violation, np.float64),
        "primal_residual": np.asarray(local.primal, np.float64),
        "dual_residual": np.asarray(local.dual, np.float64),
    }
    rho = np.asarray(local.rho, np.float64)
    for j, name in enumerate(_rho_names(solver, T)):
        cols[f"rho_{name}"] = rho[:, j]
    _case_columns(cols, cases.columns, case_local, spec, tol)
    return cols, tuple(T.objective_names), work_done, ref_t


def _case_columns(
    cols: dict[str, Any],
    drawn: dict[str, np.ndarray],
    case_local: np.ndarray,
    spec: Any,
    tol: float,
) -> None:
    """The cases' drawn operating point and the run's settings as columns (tidy rows)."""
    for name, v in drawn.items():
        if name != "case":
            cols[name] = np.asarray(v)[case_local]
    m = len(case_local)
    cols["family"] = np.full(m, spec.family)
    cols["formulation"] = np.full(m, spec.formulation)
    cols["seed"] = np.full(m, spec.seed, np.int64)
    cols["tol"] = np.full(m, tol)


def _loop_rows(
    spec: SweepSpec, cases: Any, n: int, chunk: int
) -> tuple[dict[str, Any], tuple[str, ...]]:
    """Rows of a chunk of closed-loop cases (:func:`~ampc_jax.sweep.loops.loop_pairs`)."""
    from dataclasses import replace

    from ..closed_loop.config import check_duration
    from ..vehicle.params import CONTROL_DT
    from .loops import loop_pairs

    P = len(spec.rho)
    tol = spec.tol
    cfg = replace(
        cases.config,
        formulation=spec.formulation,
        relaxation=spec.relaxation,
        anderson=spec.anderson,
        max_iter=spec.max_iter,
        **({} if tol is None else {"tol_primal": tol, "tol_dual": tol}),
    )
    n_steps = cases.n_steps
    if spec.duration is not None:
        n_steps = int(round(check_duration(spec.duration) / CONTROL_DT))
    sc = pad_cases(jax.tree.map(jnp.asarray, cases.scenarios), chunk)
    rows = loop_pairs(cfg, sc, np.asarray(spec.rho), n_steps, dtype=spec.dtype)
    rows = jax.tree.map(lambda x: np.asarray(x)[: n * P], rows)
    idx = np.arange(n * P)
    case_local, point = idx // P, idx % P
    cols: dict[str, Any] = {
        "case": cases.columns["case"][case_local],
        "point": point.astype(np.int32),
        "rho_scale": np.asarray(spec.rho)[point],
    }
    for name, v in rows._asdict().items():
        cols[name] = np.asarray(v)
    cols["iterations"] = cols["iterations"].astype(np.float64)
    cols["e_sub"] = cols.pop("e_sub_max")
    cols["n_steps"] = np.full(len(idx), n_steps, np.int32)
    _case_columns(cols, cases.columns, case_local, spec, float(cfg.tol_primal))
    return cols, tuple(cfg.enabled)


def _steady_rate(chunk_s: list[float], pairs: int) -> float | None:
    """Pairs solved per second over the chunks after the first (which compiles),
    padding pairs included; None with fewer than two chunks run."""
    if len(chunk_s) < 2:
        return None
    return pairs * (len(chunk_s) - 1) / sum(chunk_s[1:])


def _rho_names(solver: Any, topology: Any) -> tuple[str, ...]:
    if solver.n_rho == topology.n_objectives:
        return tuple(topology.objective_names)
    return tuple(f"{k}" for k in range(solver.n_rho))


def _sample_options(spec: SweepSpec, fam: Any) -> dict[str, Any]:
    kw: dict[str, Any] = {}
    if "dtype" in fam.options:
        kw["dtype"] = spec.dtype
    if spec.groups is not None:
        if "groups" not in fam.options:
            raise ValueError(f"groups: family {spec.family!r} has no groups option")
        kw["groups"] = spec.groups
    if spec.horizon is not None:
        if "horizon" not in fam.options:
            raise ValueError(f"horizon: family {spec.family!r} has no horizon option")
        kw["horizon"] = int(spec.horizon)
    return kw
