"""A sweep's chunk files: their names, the record each carries, the check before a resume.

Rule: every chunk a sweep writes carries the hash of the spec that wrote it
and the cases it holds (Parquet metadata key :data:`META_KEY`), and a sweep
starts only on an output directory that holds nothing of another sweep
(:func:`check_out`); reason: a resume used to skip any file with a chunk's
name, so a rerun with another grid after ``sweep.json`` was deleted, or a
valid chunk of another sweep copied in, was joined silently under the new
spec (``tests/sweep/test_sweep_run.py``). The check reads only
``sweep.json`` and the Parquet files, so refusing costs no solve.

Rule: a chunk's identity is its content, not its label: the record can be
copied onto another sweep's chunk. :func:`check_out` checks each chunk's rows
against the spec (every case of the chunk at every rho point exactly once,
``rho_scale`` the spec's point, ``family``, ``formulation`` and ``seed`` the
spec's), and a resumed sweep checks a chunk it skips against the cases it
draws for it (:func:`check_drawn`: every drawn operating point, bit for bit);
reason: a chunk of another seed's sweep given this sweep's record was
accepted, and ``sweep.parquet`` mixed two seeds' operating points.

Rule: a shard (:class:`Shard`, ``ampc sweep --shard I/N``) is the chunks
``I, I + N, I + 2N, ...`` of the sweep's chunk layout, computed into a
directory of its own under the spec's hash; its ``sweep.json`` says which
shard it is, and a directory holding another shard, or the whole sweep, is
refused (:func:`check_out`); reason: shards are array jobs on machines that
share nothing but the spec, and their union must be the unsharded sweep
(:mod:`~ampc_jax.sweep.merge` checks it before joining).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

__all__ = [
    "META_KEY",
    "Shard",
    "check_drawn",
    "check_out",
    "chunk_info",
    "chunk_name",
    "join_chunks",
    "read_chunk",
    "read_manifest",
    "shard_of",
    "spec_hash",
    "write_table",
]

META_KEY = b"ampc_sweep"
"""The Parquet metadata key of a chunk's record: ``{"spec_hash", "chunk", "cases"}``."""


class Shard(NamedTuple):
    """Shard ``index`` of ``count`` (``ampc sweep --shard I/N``): the chunks
    ``index, index + count, ...`` of the sweep's layout."""

    index: int
    count: int

    @classmethod
    def parse(cls, text: str) -> Shard:
        """``I/N`` with 0 <= I < N (ValueError ``shard: ...`` otherwise)."""
        i, sep, n = str(text).strip().partition("/")
        try:
            shard = cls(int(i), int(n)) if sep else None
        except ValueError:
            shard = None
        if shard is None or not 0 <= shard.index < shard.count:
            raise ValueError(
                f"shard: expected I/N, shard I of N counted from 0 (0 <= I < N), got {text!r}"
            )
        return shard

    def chunks(self, n_chunks: int, chunk: int) -> range:
        """This shard's chunks of a layout of ``n_chunks`` chunks of ``chunk`` cases;
        ValueError ``shard:`` when there are fewer chunks than shards (a shard
        would compute nothing)."""
        if self.count > n_chunks:
            raise ValueError(
                f"shard: {self.count} shards of a sweep of {n_chunks} chunk(s) of {chunk} "
                f"cases: at most {n_chunks} shards (a smaller chunk makes more chunks)"
            )
        return range(self.index, n_chunks, self.count)

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def chunk_name(k: int, part: int = 0, parts: int = 1) -> str:
    """``chunk_NNNNN.parquet``, or ``chunk_NNNNN.pKofN.parquet`` for process K of N."""
    suffix = "" if parts == 1 else f".p{part}of{parts}"
    return f"chunk_{k:05d}{suffix}.parquet"


def spec_hash(spec: Mapping[str, Any]) -> str:
    """16 hex digits of the SHA-256 of a sweep's spec (as sorted JSON)."""
    text = json.dumps(dict(spec), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _why(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:160] if text else type(exc).__name__


def chunk_info(path: Path) -> dict[str, Any]:
    """A chunk's record and its row count (``rows``); ValueError ``out: ...`` naming
    the file when it is unreadable or carries no record."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        meta = pq.read_metadata(path)
        raw = (meta.metadata or {}).get(META_KEY)
        info = json.loads(raw) if raw is not None else None
    except (OSError, ValueError, RecursionError, pa.ArrowException) as exc:
        raise ValueError(
            f"out: {path} is not a readable sweep chunk ({_why(exc)}); remove it to compute "
            "it again"
        ) from None
    if not isinstance(info, dict) or not isinstance(info.get("spec_hash"), str):
        raise ValueError(
            f"out: {path} carries no sweep spec hash (not written by this ampc sweep); "
            "remove it or choose another --out"
        )
    info["rows"] = meta.num_rows
    return info


def read_chunk(path: Path) -> Any:
    """A chunk's rows as a pyarrow Table, without its record (ValueError ``out:``)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path).replace_schema_metadata(None)
    except (OSError, ValueError, pa.ArrowException) as exc:
        raise ValueError(
            f"out: {path} is not a readable sweep chunk ({_why(exc)}); remove it to compute "
            "it again"
        ) from None


def read_manifest(path: Path, field: str = "out") -> dict[str, Any]:
    """A ``sweep.json``: a JSON object with a ``spec`` object and, for a shard, a
    ``shard`` ``[I, N]``; ValueError ``<field>: ...`` naming the file otherwise."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # UnicodeDecodeError: a ValueError
        raise ValueError(
            f"{field}: {path} is not a sweep manifest ({_why(exc)}); remove it or choose "
            "another --out"
        ) from None
    have = doc.get("spec") if isinstance(doc, dict) else None
    if not isinstance(have, dict):
        raise ValueError(
            f"{field}: {path} is not a sweep manifest (no 'spec' object); remove it or choose "
            "another --out"
        )
    shard = doc.get("shard")
    if shard is not None:
        ok = isinstance(shard, list) and len(shard) == 2
        ok = ok and all(isinstance(x, int) and not isinstance(x, bool) for x in shard)
        if not (ok and 0 <= shard[0] < shard[1]):
            raise ValueError(
                f"{field}: {path} is not a sweep manifest ('shard' {shard!r} is not [I, N] "
                "with 0 <= I < N)"
            )
    return doc


def shard_of(doc: Mapping[str, Any]) -> Shard | None:
    """The shard a manifest (:func:`read_manifest`) records, None for a whole sweep."""
    shard = doc.get("shard")
    return None if shard is None else Shard(*shard)


def _what(shard: Shard | None) -> str:
    return "the whole sweep" if shard is None else f"shard {shard}"


def check_out(
    out: str | Path,
    spec: Mapping[str, Any],
    *,
    cases: int,
    points: int,
    chunk: int,
    processes: int = 1,
    shard: Shard | None = None,
) -> None:
    """Refuse (ValueError ``out: ...``) an output directory holding anything of another
    sweep: a ``sweep.json`` of another spec, of another shard (``shard``: this
    run's, None for the whole sweep) or unreadable; under ``chunks/`` a file
    that is not one of this sweep's (this shard's) chunks (``cases`` in chunks of
    ``chunk``, written by ``processes``), unreadable, of another spec hash, of
    other cases, or (one process) short of its ``cases x points`` rows."""
    out = Path(out)
    m = out / "sweep.json"
    if m.exists():
        doc = read_manifest(m)
        have = doc["spec"]
        if have != dict(spec):
            diff = sorted(str(k) for k in set(spec) | set(have) if have.get(k) != spec.get(k))
            raise ValueError(
                f"out: {out} holds a different sweep ({', '.join(diff)[:200]} differ); "
                "choose another --out or remove it"
            )
        if shard_of(doc) != shard:
            raise ValueError(
                f"out: {out} holds {_what(shard_of(doc))} of this sweep, this run is "
                f"{_what(shard)}; give each shard, and the whole sweep, an --out of its own"
            )
    folder = out / "chunks"
    if not folder.is_dir():
        return
    n_chunks = -(-cases // chunk)
    ks = range(n_chunks) if shard is None else shard.chunks(n_chunks, chunk)
    expected = {chunk_name(k, p, processes): k for k in ks for p in range(processes)}
    mine = spec_hash(spec)
    for path in sorted(folder.glob("chunk_*.parquet")):
        k = expected.get(path.name)
        if k is None:
            raise ValueError(
                f"out: {path} is not a chunk of {'' if shard is None else f'shard {shard} of '}"
                f"this sweep ({n_chunks} chunk(s) of {chunk} cases in {processes} "
                "process(es)); remove it or choose another --out"
            )
        info = chunk_info(path)
        if info["spec_hash"] != mine:
            raise ValueError(
                f"out: {path} was written by another sweep (spec hash "
                f"{info['spec_hash'][:16]!r}, this sweep {mine!r}); remove {folder} or "
                "choose another --out"
            )
        start, stop = k * chunk, min((k + 1) * chunk, cases)
        if info.get("cases") != [start, stop]:
            raise ValueError(
                f"out: {path} holds cases {_range(info.get('cases'))}, chunk {k} of this "
                f"sweep is cases {start}..{stop - 1} (another chunk size or device count); "
                "rerun as before or choose another --out"
            )
        if processes == 1 and info["rows"] != (stop - start) * points:
            raise ValueError(
                f"out: {path} has {info['rows']} rows, not {(stop - start) * points} "
                f"({stop - start} cases x {points} points); remove it to compute it again"
            )
        _check_rows(path, spec, start, stop, whole=processes == 1)


_SPEC_COLUMNS = ("family", "formulation", "seed")


def _columns(path: Path, names: list[str]) -> dict[str, Any]:
    """Columns of a chunk as NumPy arrays (ValueError ``out:`` naming the file)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
        missing = [n for n in names if n not in schema.names]
        if missing:
            raise ValueError(
                f"out: {path} is not a chunk of this sweep (no column {missing[0]!r}); "
                "remove it or choose another --out"
            )
        table = pq.read_table(path, columns=names)
    except (OSError, pa.ArrowException) as exc:
        raise ValueError(
            f"out: {path} is not a readable sweep chunk ({_why(exc)}); remove it to compute "
            "it again"
        ) from None
    return {n: table.column(n).to_numpy(zero_copy_only=False) for n in names}


def _py(x: Any) -> Any:
    """A NumPy scalar as the Python value it holds (for messages)."""
    return x.item() if hasattr(x, "item") else x


def _foreign(path: Path, what: str) -> ValueError:
    return ValueError(
        f"out: {path} holds rows of another sweep ({what}); remove it or choose another --out"
    )


def _check_rows(path: Path, spec: Mapping[str, Any], start: int, stop: int, *, whole: bool) -> None:
    """The chunk's rows against the spec: its cases ``start .. stop - 1`` at the spec's
    rho points (every pair exactly once where ``whole``, else each at most once),
    and the spec's family, formulation and seed in every row."""
    import numpy as np

    rho = np.asarray(spec["rho"], np.float64)
    c = _columns(path, ["case", "point", "rho_scale", *_SPEC_COLUMNS])
    case, point = c["case"].astype(np.int64), c["point"].astype(np.int64)
    if case.size and not (np.all((start <= case) & (case < stop))):
        bad = case[(case < start) | (case >= stop)][0]
        raise _foreign(path, f"case {_py(bad)}, this chunk is cases {start}..{stop - 1}")
    if case.size and not np.all((0 <= point) & (point < rho.size)):
        raise _foreign(path, f"point {_py(point[(point < 0) | (point >= rho.size)][0])}")
    pairs = (case - start) * rho.size + point
    if np.unique(pairs).size != pairs.size:
        raise _foreign(path, "a (case, point) pair twice")
    if whole and pairs.size != (stop - start) * rho.size:
        raise _foreign(path, f"{pairs.size} of its {(stop - start) * rho.size} pairs")
    got = np.asarray(c["rho_scale"], np.float64)
    if not np.array_equal(got, rho[point]):
        i = int(np.flatnonzero(got != rho[point])[0])
        raise _foreign(
            path,
            f"rho_scale {_py(got[i])!r} at point {_py(point[i])}, this sweep's is "
            f"{_py(rho[point[i]])!r}",
        )
    for name in _SPEC_COLUMNS:
        want = spec[name]
        values = c[name]
        same = values == np.asarray(want, values.dtype) if values.size else np.ones(0, bool)
        if not np.all(same):
            i = int(np.flatnonzero(~same)[0])
            raise _foreign(path, f"{name} {_py(values[i])!r}, this sweep's is {want!r}")


def check_drawn(path: Path, drawn: Mapping[str, Any], start: int, tol: float | None = None) -> None:
    """A chunk's drawn operating points against the cases drawn for it (``drawn``:
    the family's columns of cases ``start ..``, ``"case"`` among them), bit for
    bit, and its ``tol`` column against ``tol``; ValueError ``out:`` naming the
    file and the first column that differs."""
    import numpy as np

    names = [n for n in drawn if n != "case"]
    c = _columns(path, ["case", *names, *(["tol"] if tol is not None else [])])
    idx = c["case"].astype(np.int64) - start
    n = len(np.asarray(drawn["case"]))
    if idx.size and not np.all((0 <= idx) & (idx < n)):
        raise _foreign(path, "cases outside the chunk")
    for name in names:
        want = np.asarray(drawn[name])[idx]
        got = c[name]
        same = (
            got == want if want.dtype.kind != "f" else (got == want) | (got != got) & (want != want)
        )
        if got.shape != want.shape or not np.all(same):
            i = int(np.flatnonzero(~same)[0]) if got.shape == want.shape else 0
            raise _foreign(
                path,
                f"case {_py(c['case'][i])}: {name} {_py(got[i])!r}, this sweep draws "
                f"{_py(want[i])!r}",
            )
    if tol is not None and not np.all(c["tol"] == tol):
        raise _foreign(path, f"tol {_py(c['tol'][0])!r}, this sweep's is {tol!r}")


def _range(cases: Any) -> str:
    if isinstance(cases, list) and len(cases) == 2 and all(isinstance(c, int) for c in cases):
        return f"{cases[0]}..{cases[1] - 1}"
    return "(none recorded)"


def join_chunks(paths: list[Path], ranges: list[tuple[int, int]], points: int, where: str) -> Any:
    """The rows of the chunk files ``paths`` as one pyarrow Table sorted by (case,
    point), which must hold each case of ``ranges`` (``[start, stop)`` pairs) at
    each of the ``points`` points exactly once; ValueError ``out:`` naming
    ``where`` otherwise."""
    import numpy as np
    import pyarrow as pa

    tab = pa.concat_tables([read_chunk(p) for p in paths])
    tab = tab.sort_by([("case", "ascending"), ("point", "ascending")])
    pairs = tab.column("case").to_numpy() * points + tab.column("point").to_numpy()
    cases = np.concatenate([np.arange(a, b) for a, b in sorted(ranges)])
    want = (cases[:, None] * points + np.arange(points)).ravel()
    if not np.array_equal(pairs, want):  # the parts' union
        raise ValueError(
            f"out: the chunks under {where} hold {pairs.size} rows, not each of the "
            f"{cases.size} cases x {points} points once; remove them to compute them again"
        )
    return tab


def write_table(table: Any, out: Path, meta: Mapping[str, Any], *, figures: bool) -> list[Path]:
    """``out/sweep.parquet`` (``meta`` in its schema metadata, key ``ampc``),
    ``out/sweep.json`` and, where ``figures``, the figures; returns their paths."""
    import pyarrow.parquet as pq

    tab = table.replace_schema_metadata({"ampc": json.dumps(dict(meta))})
    pq.write_table(tab, out / "sweep.parquet")
    (out / "sweep.json").write_text(json.dumps(dict(meta), indent=2) + "\n")
    if not figures:
        return []
    from .figures import sweep_figures

    return sweep_figures(tab, out)
