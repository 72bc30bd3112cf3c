"""The run's logs on disk: the tick journal written as the ticks run, ``ticks.parquet``
and ``run.json`` (docs/runtime.md, "Record and replay").

Rule: every tick is on disk before the next one starts; reason: a run killed
(SIGKILL, a power cut of the process, a crash) keeps every tick up to the kill
and stays replayable. While the loop runs, each tick's row is one line of
``ticks.jsonl`` (JSON, flushed to the kernel at once: a killed process loses
nothing the kernel has), and what the bridge framed for it, read one tick
later, one more line; ``run.json`` is rewritten (atomically) about once a
second with the counts so far and ``state: "running"``. When the run ends, in
whatever way it ends short of being killed, the rows go to ``ticks.parquet``,
``run.json`` gets its final counts, the SHA-256 of ``ticks.parquet`` and of the
bridge's candump log, and the journal is removed.

``run.json`` carries a ``digest``: the SHA-256 of the rest of its content
(:func:`run_digest`), so an edit of any field is seen. Like the artefact's
manifest it is not signed: the digests catch a modified or truncated file, and
the cross-checks (:mod:`~.runcheck`: ticks against the counts, ``framed_*``
against the frames the bridge logged) catch a forger who reseals them, as far
as the independent record reaches.

Readers refuse with :class:`RunLogError` naming the file and the field, never
with another exception, whatever the bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..vehicle.params import CONTROL_DT
from .files import named
from .signals import BUS_FIELDS

__all__ = [
    "BRIDGE_LOG",
    "COLUMNS",
    "JOURNAL_FILE",
    "LOG_FORMAT",
    "LOG_LOSS_COUNTS",
    "MODES",
    "NOT_MEASURED",
    "RUN_FILE",
    "SKIP_KINDS",
    "STATES",
    "TICKS_FILE",
    "RunLogError",
    "TickJournal",
    "check_meta",
    "file_sha256",
    "new_row",
    "read_journal_meta",
    "read_run_json",
    "remove_logs",
    "read_ticks",
    "run_digest",
    "write_run_json",
]

LOG_FORMAT = 2
"""Version of the run's log layout (``run.json["log_format"]``)."""

TICKS_FILE = "ticks.parquet"
JOURNAL_FILE = "ticks.jsonl"
RUN_FILE = "run.json"
BRIDGE_LOG = "bridge.log"

WHEELS = ("FL", "FR", "RL", "RR")
STATES = ("running", "finished", "stopped", "error")
"""``run.json["state"]``: still running (or killed), ran its duration, stopped by a
signal (SIGTERM, SIGINT), ended by an error (``run.json["error"]`` says which)."""
SKIP_KINDS = ("late", "state", "step")
LOG_LOSS_COUNTS = ("log_dropped", "log_errors", "log_suppressed")
"""The bridge's counts of candump lines its log left out (dropped behind, failed
to write, suppressed by its flood and size bounds): any of them means the log
no longer holds every transmitted frame."""
"""Why a tick sent nothing: its bridge deadline had passed, no usable state, a step
that may not be sent (the row's ``reason`` says more)."""
MODES = ("active", "hold", "safe", "fault")

# Largest files a reader takes in whole (a run of hours is well below).
_MAX_JSON_BYTES = 16 << 20
_MAX_JOURNAL_BYTES = 1 << 30

_COUNTED = ("ticks", "sent", "misses", "skipped", "bridge")
"""``run.json``'s counts: all or none (none only while it runs, before its first rewrite)."""

_FRAMED = {
    "bridge_mode": "str",
    **{f"framed_{w}": "float" for w in WHEELS},
    "bridge_tx_frames": "int",
}

COLUMNS: dict[str, str] = {
    "tick": "int",
    "t": "float",
    "t_wake_ns": "int",
    "state_valid": "bool",
    "state_age_ms": "float",
    "stepped": "bool",
    "sent": "bool",
    "reason": "str",
    "skip": "str",
    "compute_ms": "float",
    "margin_ms": "float",
    "state_call_ms": "float",
    "set_call_ms": "float",
    "wake_late_ms": "float",
    "seq": "int",
    "fault": "str",
    "iterations": "int",
    "status": "int",
    "fallback": "bool",
    "primal_residual": "float",
    "dual_residual": "float",
    **{f"bus_{n}": "float" for n in BUS_FIELDS},
    **{f"cmd_{w}": "float" for w in WHEELS},
    "clamped": "str",
    **_FRAMED,
}
"""The tick log's columns and their kinds (int64, float64, bool, string).

``skip``: "" for a sent tick, else one of :data:`SKIP_KINDS`. ``framed_*``,
``bridge_mode``: what the bridge framed at the tick the command was for, read
after that tick; ``bridge_tx_frames``: how many torque frames the bridge had
written then (so the frame is that one of its candump log's; 0: none yet, -1:
not read)."""


class RunLogError(ValueError):
    """A run's logs that cannot be trusted or read (the message names the file)."""


NOT_MEASURED = -1
"""An integer column's value where nothing was measured: the iterations and status
of a tick that did not step, the frame count of a tick that read none."""


def new_row(tick: int, woke_ns: int, why: str = "", skip: str = "") -> dict[str, Any]:
    """A tick's row with nothing measured yet: NaN numbers, :data:`NOT_MEASURED`
    counts, empty strings."""
    nan = float("nan")
    empty = {"int": NOT_MEASURED, "float": nan, "bool": False, "str": ""}
    row = {k: empty[kind] for k, kind in COLUMNS.items()}
    row.update(tick=tick, t=tick * CONTROL_DT, t_wake_ns=int(woke_ns), reason=why, skip=skip)
    return row


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with named(path, "read"), open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _canonical(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=True).encode()


def run_digest(meta: dict[str, Any]) -> str:
    """SHA-256 of ``run.json``'s content other than its ``digest`` (keys sorted)."""
    return hashlib.sha256(_canonical({k: v for k, v in meta.items() if k != "digest"})).hexdigest()


def write_run_json(path: Path, meta: dict[str, Any]) -> dict[str, Any]:
    """Write ``meta`` with its digest to ``path`` atomically (a reader never sees half
    a file); returns what was written (as JSON reads it back)."""
    plain = json.loads(json.dumps(meta, default=str))
    plain.pop("digest", None)
    plain["digest"] = run_digest(plain)
    tmp = path.with_name(path.name + ".tmp")
    with named(tmp, "write"):
        tmp.write_text(json.dumps(plain, indent=1))
    with named(path, "replace"):
        os.replace(tmp, path)
    return plain


def _json_line(obj: dict[str, Any]) -> str:
    return json.dumps(obj, separators=(",", ":")) + "\n"


def _header(meta: dict[str, Any] | None) -> dict[str, Any]:
    """The journal's first line: its format, its columns and the run's settings."""
    head: dict[str, Any] = {"ampc_ticks": LOG_FORMAT, "columns": COLUMNS}
    if meta is not None:
        head["run"] = meta
    return head


def remove_logs(out: Path) -> None:
    """Remove the logs of an earlier run in ``out`` (``ticks.parquet``, ``run.json``,
    the journal): a run that starts there and is killed before its first tick
    must not leave another run's logs passing for its own."""
    for name in (TICKS_FILE, RUN_FILE, JOURNAL_FILE, RUN_FILE + ".tmp", TICKS_FILE + ".tmp"):
        with named(out / name, "remove"):
            (out / name).unlink(missing_ok=True)


class TickJournal:
    """The tick log while the run runs: ``ticks.jsonl`` and a running ``run.json``.

    Opening it removes the logs of an earlier run in the same directory (their
    ticks must not pass for this run's). Each :meth:`append` and :meth:`framed`
    is one line handed to the kernel at once; :meth:`finish` writes the final
    ``ticks.parquet`` and ``run.json`` and removes the journal.
    """

    def __init__(self, out: Path, meta: dict[str, Any]) -> None:
        self.out = out
        remove_logs(out)
        self.meta = {**meta, "log_format": LOG_FORMAT}
        self.path = out / JOURNAL_FILE
        with named(self.path, "create"):
            self._f = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 (closed in finish)
        # the run's settings in the header: the journal alone is enough to replay
        # a run killed before run.json held anything more than them
        self._write(_json_line(_header(json.loads(json.dumps(self.meta, default=str)))))
        self.status({"state": "running"})

    def _write(self, line: str) -> None:
        with named(self.path, "write"):
            self._f.write(line)
            self._f.flush()

    def append(self, row: dict[str, Any]) -> None:
        """A tick's row (the keys of :data:`COLUMNS`)."""
        self._write(_json_line({k: row[k] for k in COLUMNS}))

    def framed(self, row: dict[str, Any]) -> None:
        """What the bridge framed for the row's tick (its ``framed_*`` columns), read later."""
        self._write(_json_line({"framed": row["tick"], **{k: row[k] for k in _FRAMED}}))

    def close(self) -> None:
        """Close the journal as it is (what a killed run leaves behind)."""
        with named(self.path, "close"):
            self._f.close()

    def status(self, summary: dict[str, Any]) -> None:
        """``run.json`` with the counts so far (``state: "running"``)."""
        write_run_json(self.out / RUN_FILE, {**self.meta, **summary, "state": "running"})

    def finish(self, rows: list[dict[str, Any]], summary: dict[str, Any]) -> dict[str, Any]:
        """The final logs: ``ticks.parquet``, then ``run.json`` with the files' digests
        (``summary["state"]`` says how the run ended), then the journal goes."""
        import pyarrow.parquet as pq

        ticks = self.out / TICKS_FILE
        tmp = ticks.with_name(TICKS_FILE + ".tmp")
        with named(tmp, "write"):
            pq.write_table(_table(rows), tmp)
        with named(ticks, "replace"):
            os.replace(tmp, ticks)
        files = {TICKS_FILE: file_sha256(ticks)}
        if (self.out / BRIDGE_LOG).is_file():
            files[BRIDGE_LOG] = file_sha256(self.out / BRIDGE_LOG)
        written = write_run_json(self.out / RUN_FILE, {**self.meta, **summary, "files": files})
        self.close()
        with named(self.path, "remove"):
            self.path.unlink(missing_ok=True)
        return written


_ARROW = {"int": "int64", "float": "float64", "bool": "bool_", "str": "string"}


def _table(rows: list[dict[str, Any]]) -> Any:
    import pyarrow as pa

    schema = pa.schema([(k, getattr(pa, _ARROW[kind])()) for k, kind in COLUMNS.items()])
    return pa.table({k: [r[k] for r in rows] for k in COLUMNS}, schema=schema)


# -- reading -------------------------------------------------------------------------


def _loads(text: bytes | str, what: str) -> Any:
    try:
        return json.loads(text)
    except RecursionError:
        raise RunLogError(f"{what}: nested too deeply to be a log") from None
    except (ValueError, TypeError) as exc:  # JSONDecodeError, UnicodeDecodeError
        raise RunLogError(f"{what}: not JSON ({exc})") from None


def _is_int(x: Any) -> bool:
    return type(x) is int


def _is_hex64(x: Any) -> bool:
    return isinstance(x, str) and len(x) == 64 and all(c in "0123456789abcdef" for c in x)


def read_run_json(path: Path) -> dict[str, Any]:
    """``run.json``, its fields checked for presence and type (RunLogError naming
    the first that is wrong); the digest is checked by :mod:`~.runcheck`.

    A run that is still running (or was killed: ``state: "running"``) may lack
    its counts and the bridge's statistics: ``run.json`` holds only the run's
    settings until its first rewrite, about a second into actuation."""
    what = f"{path.parent}: {path.name}"
    if not path.is_file():
        raise RunLogError(
            f"{path.parent}: no {path.name} (expected an `ampc run` output directory)"
        )
    try:
        if path.stat().st_size > _MAX_JSON_BYTES:
            raise RunLogError(f"{what}: larger than {_MAX_JSON_BYTES >> 20} MiB")
        raw = path.read_bytes()
    except OSError as exc:
        raise RunLogError(f"{what}: cannot be read ({exc.strerror or exc})") from None
    meta = _loads(raw, what)
    if not isinstance(meta, dict):
        raise RunLogError(f"{what}: not a JSON object")
    return check_meta(meta, what)


def read_journal_meta(path: Path) -> dict[str, Any] | None:
    """The run's settings from the journal's header (None: a header without them,
    as a journal of an earlier version has), checked as ``run.json``'s fields are;
    ``state`` is ``"running"``: a journal is what a run leaves while it runs."""
    what = f"{path.parent}: {path.name}"
    header = _journal_header(path, what)
    meta = header.get("run")
    if meta is None:
        return None
    if not isinstance(meta, dict):
        raise RunLogError(f"{what} line 1: 'run': not a JSON object")
    return check_meta({**meta, "state": "running"}, f"{what} line 1", digest=False)


def check_meta(meta: dict[str, Any], what: str, *, digest: bool = True) -> dict[str, Any]:
    """A run's settings and counts (``run.json``'s fields), checked for presence and
    type; ``digest``: ``run.json``'s own digest must be there (a journal's header
    has none)."""

    def need(key: str, ok: Any, expected: str) -> Any:
        if key not in meta:
            raise RunLogError(f"{what}: {key!r}: missing")
        if not ok(meta[key]):
            raise RunLogError(f"{what}: {key!r}: expected {expected}, got {meta[key]!r:.80}")
        return meta[key]

    need("log_format", _is_int, "an integer")
    if meta["log_format"] != LOG_FORMAT:
        raise RunLogError(
            f"{what}: 'log_format': {meta['log_format']}, this version reads {LOG_FORMAT} "
            "(the run was made by another version of `ampc run`)"
        )
    state = need("state", lambda x: x in STATES, f"one of {list(STATES)}")
    need("scenario", lambda x: isinstance(x, str), "a scenario's name")
    need("formulation", lambda x: isinstance(x, str), "a formulation's name")
    need("dtype", lambda x: x in ("float64", "float32"), "'float64' or 'float32'")
    need("config_hash", _is_hex64, "64 hex digits")
    if digest:
        need("digest", _is_hex64, "64 hex digits")
    # a running (or killed) run's run.json holds its counts from its first
    # rewrite on; before that, none: nothing is claimed, the journal says it all
    counted = state != "running" or any(k in meta for k in _COUNTED)
    if counted:
        for key in ("ticks", "sent", "misses"):
            need(key, lambda x: _is_int(x) and x >= 0, "a count >= 0")
        need(
            "skipped",
            lambda x: (
                isinstance(x, dict)
                and all(k in SKIP_KINDS and _is_int(v) and v >= 0 for k, v in x.items())
            ),
            f"counts by kind ({', '.join(SKIP_KINDS)})",
        )
        need(
            "bridge",
            lambda x: (
                isinstance(x, dict)
                and all(_is_int(x.get(k)) and x[k] >= 0 for k in ("log_dropped", "log_errors"))
                and all(_is_int(x[k]) and x[k] >= 0 for k in LOG_LOSS_COUNTS[2:] if k in x)
            ),
            "the bridge's statistics with counts 'log_dropped' and 'log_errors'"
            " (and 'log_suppressed' a count where given)",
        )
    if "pid" in meta:
        need("pid", lambda x: _is_int(x) and x > 0, "a process id")
    if "host" in meta:
        need("host", lambda x: isinstance(x, str), "a host name")
    if "environment" in meta:
        need(
            "environment",
            lambda x: isinstance(x, dict) and all(isinstance(v, str) for v in x.values()),
            "versions as strings",
        )
    if state != "running":
        need(
            "files",
            lambda x: (
                isinstance(x, dict)
                and _is_hex64(x.get(TICKS_FILE))
                and _is_hex64(x.get(BRIDGE_LOG))
            ),
            f"the SHA-256 of {TICKS_FILE} and {BRIDGE_LOG}",
        )
    if state == "error":
        need("error", lambda x: isinstance(x, str), "the error's text")
    return meta


def read_ticks(log_dir: Path, complete: bool) -> tuple[dict[str, np.ndarray], str]:
    """The tick log's columns (:data:`COLUMNS`, NumPy arrays) and the file they came
    from: ``ticks.parquet`` for a run that ended, the journal for one that is
    running or was killed (``ticks.parquet`` if the kill came after it was written)."""
    journal, ticks = log_dir / JOURNAL_FILE, log_dir / TICKS_FILE
    if not complete and journal.is_file():
        return _read_journal(journal), JOURNAL_FILE
    if not ticks.is_file():
        raise RunLogError(f"{log_dir}: no {TICKS_FILE} (expected an `ampc run` output directory)")
    return _read_parquet(ticks), TICKS_FILE


def _read_parquet(path: Path) -> dict[str, np.ndarray]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    what = f"{path.parent}: {path.name}"
    try:
        table = pq.read_table(path)
    except (pa.ArrowException, OSError, ValueError, TypeError, IndexError) as exc:
        raise RunLogError(f"{what}: not a readable Parquet file ({exc})") from None
    names = set(table.column_names)
    missing = [k for k in COLUMNS if k not in names]
    if missing or len(names) != len(COLUMNS):
        extra = sorted(names - set(COLUMNS))
        raise RunLogError(f"{what}: columns missing {missing[:5]}, unknown {extra[:5]}")
    cols = {}
    for k, kind in COLUMNS.items():
        col = table.column(k)
        want = getattr(pa, _ARROW[kind])()
        if not (col.type == want or (kind == "str" and col.type == pa.large_string())):
            raise RunLogError(f"{what}: column {k!r} is {col.type}, expected {want}")
        if col.null_count:
            raise RunLogError(f"{what}: column {k!r} has {col.null_count} missing values")
        cols[k] = _column(col.to_pylist(), kind)
    return cols


def _kind_ok(kind: str, v: Any) -> bool:
    int64 = type(v) is int and -(2**63) <= v < 2**63
    if kind == "int":
        return int64
    if kind == "float":
        return type(v) is float or int64
    if kind == "bool":
        return type(v) is bool
    return type(v) is str


def _check_header(header: Any, what: str) -> dict[str, Any]:
    plain = json.loads(json.dumps(_header(None)))
    if (
        not isinstance(header, dict)
        or set(header) - {"run"} != set(plain)
        or any(header[k] != v for k, v in plain.items())
    ):
        raise RunLogError(f"{what} line 1: not the header of a version {LOG_FORMAT} tick journal")
    return header


def _journal_header(path: Path, what: str) -> dict[str, Any]:
    """The journal's first line (its header), read alone."""
    try:
        with open(path, "rb") as f:
            line = f.readline(_MAX_JSON_BYTES)
    except OSError as exc:
        raise RunLogError(f"{what}: cannot be read ({exc.strerror or exc})") from None
    if not line.endswith(b"\n"):
        raise RunLogError(f"{what}: empty (no header)")
    return _check_header(_loads(line, f"{what} line 1"), what)


def _read_journal(path: Path) -> dict[str, np.ndarray]:
    """The journal's rows: a last line without its newline (cut by a kill) is left
    out; any other line that is not a row or a framed update is refused."""
    what = f"{path.parent}: {path.name}"
    try:
        if path.stat().st_size > _MAX_JOURNAL_BYTES:
            raise RunLogError(f"{what}: larger than {_MAX_JOURNAL_BYTES >> 30} GiB")
        lines = path.read_bytes().split(b"\n")
    except OSError as exc:
        raise RunLogError(f"{what}: cannot be read ({exc.strerror or exc})") from None
    lines.pop()  # "" after the last newline, or a line the kill cut short
    if not lines:
        raise RunLogError(f"{what}: empty (no header)")
    _check_header(_loads(lines[0], f"{what} line 1"), what)
    rows: list[dict[str, Any]] = []
    for no, line in enumerate(lines[1:], start=2):
        at = f"{what} line {no}"
        obj = _loads(line, at)
        if not isinstance(obj, dict):
            raise RunLogError(f"{at}: not a JSON object")
        if "framed" in obj:
            keys, tick = {"framed", *_FRAMED}, obj["framed"]
            if set(obj) != keys:
                raise RunLogError(f"{at}: a framed update needs exactly {sorted(keys)}")
            if (
                not (_is_int(tick) and 0 <= tick < len(rows))
                or rows[tick]["bridge_tx_frames"] != -1
            ):
                raise RunLogError(f"{at}: a framed update of tick {tick!r}, not one awaiting it")
            target, kinds = rows[tick], _FRAMED
        else:
            if set(obj) != set(COLUMNS):
                diff = sorted(set(obj) ^ set(COLUMNS))[:5]
                raise RunLogError(f"{at}: not a tick row (keys differ: {diff})")
            if obj["tick"] != len(rows):
                raise RunLogError(f"{at}: tick {obj['tick']!r}, expected {len(rows)}")
            target, kinds = obj, COLUMNS
            rows.append(obj)
        for k, kind in kinds.items():
            v = obj[k]
            if not _kind_ok(kind, v):
                raise RunLogError(f"{at}: {k!r}: expected {kind}, got {v!r:.40}")
            target[k] = float(v) if kind == "float" else v
    return {k: _column([r[k] for r in rows], kind) for k, kind in COLUMNS.items()}


_NUMPY = {"int": np.int64, "float": np.float64, "bool": np.bool_, "str": np.str_}


def _column(values: list[Any], kind: str) -> np.ndarray:
    return np.asarray(values, dtype=_NUMPY[kind])
