"""Shards of a sweep joined into the table an unsharded run writes (``ampc sweep-merge``).

A sweep split as ``ampc sweep --shard I/N`` (array jobs: Slurm, or a Dask or
Ray cluster) leaves N directories, each holding the chunks ``I, I + N, ...``
of the sweep's chunk layout (:class:`~ampc_jax.sweep.store.Shard`) and a
``sweep.json`` naming its shard. :func:`merge_shards` joins them.

Rule: nothing is joined until every shard is accounted for: each directory
is a shard of the one spec (the spec's hash; a shard of another sweep is
refused naming the directory and what differs), each of shards 0 .. N-1 is
given exactly once (a missing or duplicated shard is refused naming it),
each shard holds all of its chunks and nothing else (the checks a resume
makes, :func:`~ampc_jax.sweep.store.check_out`), and every chunk's rows are
the cases the spec draws for it (:func:`~ampc_jax.sweep.store.check_drawn`);
the joined rows hold each (case, point) exactly once. Reason: a table must
never mix two sweeps, miss a shard that failed or count one twice, and the
merged table is then the unsharded run's (``tests/sweep/test_sweep_shards.py``
checks it bit for bit against one, with the shards run as parallel processes).
"""

from __future__ import annotations

import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import jax

from . import store
from .run import FORMAT, SweepSpec, SweepSummary, drawn, git_commit, shard_chunks
from .store import Shard

__all__ = ["merge_shards", "read_shards"]

_SUMS = (
    "solve_s",
    "reference_s",
    "pair_iterations_computed",
    "pair_iterations_needed",
    "chunks_run",
    "chunks_skipped",
)


def read_shards(dirs: list[str | Path]) -> list[tuple[Path, dict[str, Any], Shard]]:
    """(directory, ``sweep.json``, shard) of each directory, after the checks of
    one split: one spec, one N, each shard 0 .. N-1 once (ValueError ``shards:``
    naming the directory or the shard)."""
    if not dirs:
        raise ValueError("shards: expected the directories of a sweep's shards")
    got = []
    for d in map(Path, dirs):
        if not d.is_dir():
            raise ValueError(f"shards: {d} is not a directory")
        if not (d / "sweep.json").is_file():
            raise ValueError(
                f"shards: {d} holds no sweep.json (not the --out of an `ampc sweep --shard`)"
            )
        doc = store.read_manifest(d / "sweep.json", "shards")
        shard = store.shard_of(doc)
        if shard is None:
            raise ValueError(
                f"shards: {d} holds a whole sweep, not a shard (its sweep.parquet is the table)"
            )
        got.append((d, doc, shard))
    hashes = [store.spec_hash(doc["spec"]) for _, doc, _ in got]
    # the reference: the spec most directories hold (ties: the first given)
    ref = max(hashes, key=lambda h: (Counter(hashes)[h], -hashes.index(h)))
    d0, doc0, s0 = got[hashes.index(ref)]
    foreign = [(d, doc) for (d, doc, _), h in zip(got, hashes, strict=True) if h != ref]
    if foreign:
        d, doc = foreign[0]
        spec, have = doc0["spec"], doc["spec"]
        diff = sorted(str(k) for k in set(spec) | set(have) if have.get(k) != spec.get(k))
        more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
        raise ValueError(
            f"shards: {d}{more} is a shard of another sweep ({', '.join(diff)[:200]} differ "
            f"from {d0}'s); merge the shards of one sweep"
        )
    for d, _, s in got:
        if s.count != s0.count:
            raise ValueError(
                f"shards: {d} is shard {s}, {d0} shard {s0}: the shards of one split share N"
            )
    by_index: dict[int, list[Path]] = {}
    for d, _, s in got:
        by_index.setdefault(s.index, []).append(d)
    for i, ds in sorted(by_index.items()):
        if len(ds) > 1:
            raise ValueError(
                f"shards: shard {i}/{s0.count} given {len(ds)} times ({', '.join(map(str, ds))})"
            )
    missing = [f"{i}/{s0.count}" for i in range(s0.count) if i not in by_index]
    if missing:
        raise ValueError(
            f"shards: shard {', '.join(missing)} missing (the --out of `ampc sweep --shard "
            f"{missing[0]}` with the same settings)"
        )
    return sorted(got, key=lambda g: g[2].index)


def _check_shard(d: Path, spec: SweepSpec, shard: Shard, doc: dict[str, Any]) -> range:
    """The shard's chunks, each there and of this sweep (ValueError ``shards:``)."""
    from .run import check_out

    chunk, ks = shard_chunks(spec, 1, shard)
    if doc.get("chunk_cases", chunk) != chunk:
        raise ValueError(
            f"shards: {d} holds chunks of {doc['chunk_cases']} cases, the sweep's layout is "
            f"{chunk}; rerun shard {shard} into an empty --out"
        )
    if doc.get("processes", 1) != 1:
        raise ValueError(f"shards: {d} was run by {doc['processes']} processes, a shard by one")
    try:
        check_out(d, spec, 1, shard)
    except ValueError as exc:
        raise ValueError(
            f"shards: shard {shard} in {d}: {str(exc).removeprefix('out: ')}"
        ) from None
    for k in ks:
        path = d / "chunks" / store.chunk_name(k)
        if not path.exists():
            start, stop = k * chunk, min((k + 1) * chunk, spec.cases)
            raise ValueError(
                f"shards: shard {shard} in {d} is not finished: chunk {k} (cases "
                f"{start}..{stop - 1}) missing; rerun its `ampc sweep --shard {shard} --out {d}`"
            )
    return ks


def merge_shards(
    dirs: list[str | Path], out: str | Path, *, figures: bool = True, progress: Any = None
) -> SweepSummary:
    """Join the shards in ``dirs`` (in any order) into ``out``: ``sweep.parquet``,
    ``sweep.json`` and the figures (``figures``, default True), as an unsharded
    run of their spec writes them; see the module docstring for the checks
    (ValueError ``shards:`` naming the directory or shard; nothing is written
    then). ``progress(text)``: a line per shard checked (default none).
    The drawn operating points are checked by drawing every case again (JAX's
    float64 mode as the spec's ``float32`` says)."""
    t0 = time.perf_counter()
    out = Path(out)
    shards = read_shards(dirs)
    doc0 = shards[0][1]
    try:
        spec = SweepSpec(**doc0["spec"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"shards: {shards[0][0]}: not a spec of this ampc sweep ({exc})") from None
    if spec.float32 == jax.config.jax_enable_x64:
        raise ValueError(
            f"shards: the sweep ran in {'float32' if spec.float32 else 'float64'}: merge with "
            f"jax_enable_x64 {'off' if spec.float32 else 'on'} (its cases are drawn again)"
        )
    for d, _, _ in shards:
        if out.resolve() == d.resolve():
            raise ValueError(f"out: {out} is one of the shards; merge into another directory")
    chunk, _ = shard_chunks(spec, 1, shards[0][2])
    paths: dict[int, Path] = {}
    for d, doc, shard in shards:
        for k in _check_shard(d, spec, shard, doc):
            path = d / "chunks" / store.chunk_name(k)
            start = k * chunk
            cols, tol = drawn(spec, start, min(chunk, spec.cases - start))
            try:
                store.check_drawn(path, cols, start, tol)
            except ValueError as exc:
                msg = str(exc).removeprefix("out: ")
                raise ValueError(f"shards: shard {shard} in {d}: {msg}") from None
            paths[k] = path
        if progress is not None:
            progress(f"shard {shard} ({d}): {len(paths)} chunk(s) checked so far")
    ks = sorted(paths)
    ranges = [(k * chunk, min((k + 1) * chunk, spec.cases)) for k in ks]
    where = ", ".join(str(d / "chunks") for d, _, _ in shards)
    tab = store.join_chunks([paths[k] for k in ks], ranges, len(spec.rho), where)
    runs = [
        {
            "shard": list(s),
            "dir": str(d),
            **{k: doc.get(k) for k in ("commit", "date", "devices", "platform", "wall_s")},
        }
        for d, doc, s in shards
    ]
    meta: dict[str, Any] = {
        "format": FORMAT,
        "spec": doc0["spec"],
        "spec_hash": store.spec_hash(doc0["spec"]),
        "chunk_cases": chunk,
        "commit": git_commit(),
        "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "jax": jax.__version__,
        "shards": len(shards),
        "devices": sum(int(doc.get("devices") or 0) for _, doc, _ in shards),
        "processes": len(shards),
        "platform": doc0.get("platform"),
        "objectives": doc0.get("objectives", []),
        **{k: sum(doc.get(k) or 0 for _, doc, _ in shards) for k in _SUMS},
        "wall_s": max(float(doc.get("wall_s") or 0.0) for _, doc, _ in shards),
        "shard_runs": runs,
    }
    out.mkdir(parents=True, exist_ok=True)
    figs = store.write_table(tab, out, meta, figures=figures)
    return SweepSummary(
        out=out,
        table=out / "sweep.parquet",
        figures=figs,
        rows=tab.num_rows,
        wall_s=time.perf_counter() - t0,
        solve_s=float(meta["solve_s"]),
        reference_s=float(meta["reference_s"]),
        chunks_run=int(meta["chunks_run"]),
        chunks_skipped=int(meta["chunks_skipped"]),
        computed=int(meta["pair_iterations_computed"]),
        needed=int(meta["pair_iterations_needed"]),
        devices=int(meta["devices"]),
        processes=len(shards),
    )
