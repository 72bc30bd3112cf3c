"""A sweep's chunk files: their names, the record each carries, the check before a resume.

Rule: every chunk a sweep writes carries the hash of the spec that wrote it
and the cases it holds (Parquet metadata key :data:`META_KEY`), and a sweep
starts only on an output directory that holds nothing of another sweep
(:func:`check_out`); reason: a resume used to skip any file with a chunk's
name, so a rerun with another grid after ``sweep.json`` was deleted, or a
valid chunk of another sweep copied in, was joined silently under the new
spec (``tests/sweep/test_sweep_run.py``). The check reads only
``sweep.json`` and the Parquet footers, so refusing costs no solve.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["META_KEY", "check_out", "chunk_info", "chunk_name", "read_chunk", "spec_hash"]

META_KEY = b"ampc_sweep"
"""The Parquet metadata key of a chunk's record: ``{"spec_hash", "chunk", "cases"}``."""


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


def _manifest_spec(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # UnicodeDecodeError: a ValueError
        raise ValueError(
            f"out: {path} is not a sweep manifest ({_why(exc)}); remove it or choose another --out"
        ) from None
    have = doc.get("spec") if isinstance(doc, dict) else None
    if not isinstance(have, dict):
        raise ValueError(
            f"out: {path} is not a sweep manifest (no 'spec' object); remove it or choose "
            "another --out"
        )
    return have


def check_out(
    out: str | Path,
    spec: Mapping[str, Any],
    *,
    cases: int,
    points: int,
    chunk: int,
    processes: int = 1,
) -> None:
    """Refuse (ValueError ``out: ...``) an output directory holding anything of another
    sweep: a ``sweep.json`` of another spec or unreadable; under ``chunks/`` a file
    that is not one of this sweep's chunks (``cases`` in chunks of ``chunk``,
    written by ``processes``), unreadable, of another spec hash, of other cases, or
    (one process) short of its ``cases x points`` rows."""
    out = Path(out)
    m = out / "sweep.json"
    if m.exists():
        have = _manifest_spec(m)
        if have != dict(spec):
            diff = sorted(str(k) for k in set(spec) | set(have) if have.get(k) != spec.get(k))
            raise ValueError(
                f"out: {out} holds a different sweep ({', '.join(diff)[:200]} differ); "
                "choose another --out or remove it"
            )
    folder = out / "chunks"
    if not folder.is_dir():
        return
    n_chunks = -(-cases // chunk)
    expected = {chunk_name(k, p, processes): k for k in range(n_chunks) for p in range(processes)}
    mine = spec_hash(spec)
    for path in sorted(folder.glob("chunk_*.parquet")):
        k = expected.get(path.name)
        if k is None:
            raise ValueError(
                f"out: {path} is not a chunk of this sweep ({n_chunks} chunk(s) of {chunk} "
                f"cases in {processes} process(es)); remove it or choose another --out"
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


def _range(cases: Any) -> str:
    if isinstance(cases, list) and len(cases) == 2 and all(isinstance(c, int) for c in cases):
        return f"{cases[0]}..{cases[1] - 1}"
    return "(none recorded)"
