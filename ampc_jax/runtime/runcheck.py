"""Whether a run's logs can be trusted: the checks ``ampc replay`` makes before it
replays anything.

Rule: a replay refuses a log it cannot vouch for, naming the first thing that
does not add up; reason: a determinism check on tampered or truncated ticks
would vouch for numbers the run never produced. In order:

1. ``run.json``: every field the replay reads, present and of its type
   (:func:`~.ticklog.read_run_json`), the scenario and formulation ones this
   version builds;
2. the ticks (:func:`~.ticklog.read_ticks`): numbered 0, 1, 2, ... on the 50 ms
   grid; a tick sent iff it has a sequence number, the numbers 1, 2, 3, ... in
   order; a tick that stepped has its bus vector, one that did not has no
   command; a tick that sent nothing says why;
3. the ticks against ``run.json``'s counts (ticks, sent, skipped by kind,
   misses): equal for a run that ended, at most the ticks' for one killed
   (``run.json`` is rewritten about once a second while it runs);
4. the ticks against the bridge's candump log, an independent record written
   by the bridge's own thread: each tick's ``framed_*`` and ``bridge_mode`` are
   the torques and mode of the frame the bridge had written last when they were
   read (``bridge_tx_frames``), decoded from the log by python-can's reader and
   cantools with the DBC, its CRC checked by autosar-e2e;
5. the digests ``run.json`` recorded: its own, and for a run that ended the
   SHA-256 of ``ticks.parquet`` and ``bridge.log``.

A killed run (``state: "running"``) is checked as far as its files reach:
frames the bridge had not yet flushed to its log when it was killed are
counted as unchecked, not refused.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..closed_loop.config import NO_MPC, loop_formulations
from ..vehicle import SCENARIOS
from ..vehicle.params import CONTROL_DT
from .ticklog import (
    BRIDGE_LOG,
    JOURNAL_FILE,
    LOG_LOSS_COUNTS,
    MODES,
    NOT_MEASURED,
    RUN_FILE,
    SKIP_KINDS,
    TICKS_FILE,
    RunLogError,
    file_sha256,
    read_journal_meta,
    read_run_json,
    read_ticks,
    run_digest,
)

__all__ = ["CheckedRun", "check_run"]

WHEELS = ("FL", "FR", "RL", "RR")


@dataclass(frozen=True)
class CheckedRun:
    """A run's logs that passed :func:`check_run`.

    meta : ``run.json``.
    cols : the tick log's columns (NumPy arrays).
    source : the file the ticks came from (``ticks.parquet``, or the journal
        ``ticks.jsonl`` of a run that did not finish).
    complete : the run ended (``state`` other than ``running``).
    frames_checked : ticks whose ``framed_*`` were compared with bridge.log's frame.
    frames_unchecked : ticks whose frame a killed bridge had not yet logged.
    notes : what the checks could not cover, said to the user.
    alive : for a run that did not finish, whether its process is still running
        on this machine (False: it was killed; None: not known, another machine).
    settings : the file the run's settings came from (``run.json``, or the
        journal's header for a run killed before ``run.json`` was written).
    """

    meta: dict[str, Any]
    cols: dict[str, np.ndarray]
    source: str
    complete: bool
    frames_checked: int
    frames_unchecked: int
    notes: tuple[str, ...]
    alive: bool | None = None
    settings: str = RUN_FILE


def _settings(log_dir: Path) -> tuple[dict[str, Any], str, list[str]]:
    """``run.json``, or for a run killed before it was written, the settings the
    journal's header holds: (meta, the file they came from, notes). Where both
    are there (a run that did not finish), they must agree."""
    run_file, journal = log_dir / RUN_FILE, log_dir / JOURNAL_FILE
    if not run_file.is_file() and journal.is_file():
        meta = read_journal_meta(journal)
        if meta is None:
            raise RunLogError(
                f"{log_dir}: no {RUN_FILE}, and its {JOURNAL_FILE} holds no run settings "
                "(written by an earlier version)"
            )
        return meta, JOURNAL_FILE, [f"no {RUN_FILE}: the run's settings are its journal's"]
    meta = read_run_json(run_file)
    if meta["state"] == "running" and journal.is_file():
        head = read_journal_meta(journal)
        for key in _SETTINGS:
            if head is not None and head.get(key) != meta.get(key):
                raise RunLogError(
                    f"{log_dir}: {RUN_FILE} and {JOURNAL_FILE} disagree on {key!r} "
                    f"({meta.get(key)!r:.40}, {head.get(key)!r:.40})"
                )
    return meta, RUN_FILE, []


_SETTINGS = ("scenario", "formulation", "dtype", "config_hash", "log_format", "pid")


def _process_alive(meta: dict[str, Any]) -> bool | None:
    """Whether the run's process is alive on this machine (None: not known)."""
    import os
    import socket

    pid, host = meta.get("pid"), meta.get("host")
    if not isinstance(pid, int) or host != socket.gethostname():
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: a process of another user has the id
        return True
    return True


def check_run(log_dir: Path) -> CheckedRun:
    """Check the run in ``log_dir`` (RunLogError, naming the first check that fails)."""
    log_dir = Path(log_dir)
    meta, settings, notes = _settings(log_dir)
    where = f"{log_dir}: {settings}"
    if meta["scenario"] not in SCENARIOS:
        raise RunLogError(f"{where}: 'scenario': {meta['scenario']!r:.60} is not a scenario")
    if meta["formulation"] not in loop_formulations() or meta["formulation"] == NO_MPC:
        raise RunLogError(
            f"{where}: 'formulation': {meta['formulation']!r:.60} is not a controller"
        )
    complete = meta["state"] != "running"
    cols, source = read_ticks(log_dir, complete)
    _check_rows(cols, f"{log_dir}: {source}")
    if "ticks" in meta:  # a run killed before run.json's first rewrite counted nothing
        _check_counts(meta, cols, complete, log_dir, source)
    bridge = meta.get("bridge", {})
    # lines the log left out (dropped, failed, or suppressed by its flood and
    # size bounds) mean its frames no longer line up with the bridge's count
    lost = sum(bridge.get(k, 0) for k in LOG_LOSS_COUNTS)
    if lost:
        checked, unchecked = 0, int((cols["bridge_tx_frames"] > 0).sum())
        notes.append(f"the bridge's log lost {lost} frames: framed_* not cross-checked against it")
    else:
        checked, unchecked = _check_frames(log_dir, cols, complete, source)
    if unchecked and not lost:
        notes.append(f"{unchecked} ticks' frames were not yet in {BRIDGE_LOG} when the run ended")
    if settings == RUN_FILE:
        _check_digests(log_dir, meta, complete)
    alive = None if complete else _process_alive(meta)
    return CheckedRun(
        meta, cols, source, complete, checked, unchecked, tuple(notes), alive, settings
    )


def _first(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def _check_rows(c: dict[str, np.ndarray], what: str) -> None:
    """The ticks agree with themselves (see the module docstring, 2)."""
    n = len(c["tick"])
    if not np.array_equal(c["tick"], np.arange(n)):
        i = _first(c["tick"] != np.arange(n))
        raise RunLogError(f"{what}: row {i} is tick {c['tick'][i]}, expected {i} (ticks missing)")
    if not np.array_equal(c["t"], np.arange(n) * CONTROL_DT):
        i = _first(c["t"] != np.arange(n) * CONTROL_DT)
        raise RunLogError(f"{what}: tick {i}: t {c['t'][i]!r}, expected {i * CONTROL_DT!r}")
    skip, sent, stepped, seq = c["skip"], c["sent"], c["stepped"], c["seq"]

    def bad(mask: np.ndarray, text: str) -> None:
        if mask.any():
            i = _first(mask)
            row = {k: v[i].item() for k, v in c.items()}
            raise RunLogError(f"{what}: tick {i}: {text.format(**row)}")

    bad(~np.isin(skip, ("", *SKIP_KINDS)), "skip {skip!r} is not a kind of skipped tick")
    bad(sent != (skip == ""), "sent {sent}, but skip {skip!r} ('' exactly when sent)")
    bad(sent & ~stepped, "sent, but it did not step")
    bad((skip == "step") & ~stepped, "skip 'step', but it did not step")
    bad(np.isin(skip, ("late", "state")) & stepped, "skip {skip!r}, but it stepped")
    bad(sent != (seq > 0), "sent {sent}, but seq {seq} (a sent command's number)")
    bad(~sent & (seq != -1), "sent {sent}, but seq {seq}")
    if not np.array_equal(seq[sent], np.arange(1, int(sent.sum()) + 1)):
        k = _first(seq[sent] != np.arange(1, int(sent.sum()) + 1))
        i = int(np.flatnonzero(sent)[k])
        raise RunLogError(
            f"{what}: tick {i}: seq {seq[i]}, expected {k + 1} (sent commands missing)"
        )
    bad(sent & (c["reason"] != ""), "sent, but a reason not to: {reason!r}")
    bad(~sent & (c["reason"] == ""), "nothing sent, and no reason")
    bus = np.stack([v for k, v in c.items() if k.startswith("bus_")], axis=1)
    cmd = np.stack([c[f"cmd_{w}"] for w in WHEELS], axis=1)
    bad(stepped & ~np.isfinite(bus).all(axis=1), "stepped on a bus vector with missing values")
    bad(~stepped & ~np.isnan(bus).all(axis=1), "did not step, but has a bus vector")
    bad(~stepped & ~np.isnan(cmd).all(axis=1), "did not step, but has a command")
    bad(stepped & (c["iterations"] < 0), "stepped, but iterations {iterations}")
    bad(
        ~stepped & ((c["iterations"] != NOT_MEASURED) | (c["status"] != NOT_MEASURED)),
        "did not step, but has a status",
    )
    frames = c["bridge_tx_frames"]
    framed = np.stack([c[f"framed_{w}"] for w in WHEELS], axis=1)
    read = frames >= 0
    bad(frames < NOT_MEASURED, "bridge_tx_frames {bridge_tx_frames}")
    bad(read & ~np.isfinite(framed).all(axis=1), "framed torques missing")
    bad(read & ~np.isin(c["bridge_mode"], MODES), "bridge_mode {bridge_mode!r}")
    bad(~read & ~(np.isnan(framed).all(axis=1) & (c["bridge_mode"] == "")), "framed, unread")
    if read.any() and np.any(np.diff(frames[read]) < 0):
        i = int(np.flatnonzero(read)[_first(np.diff(frames[read]) < 0) + 1])
        raise RunLogError(f"{what}: tick {i}: bridge_tx_frames {frames[i]} goes back")


def _counts(c: dict[str, np.ndarray]) -> dict[str, Any]:
    skipped = {k: int((c["skip"] == k).sum()) for k in SKIP_KINDS}
    late = skipped["late"]
    behind = int((c["sent"] & (c["margin_ms"] < 0)).sum())
    return {
        "ticks": len(c["tick"]),
        "sent": int(c["sent"].sum()),
        "misses": late + behind,
        "skipped": {k: v for k, v in skipped.items() if v},
    }


def _check_counts(
    meta: dict[str, Any], c: dict[str, np.ndarray], complete: bool, log_dir: Path, source: str
) -> None:
    """The ticks against run.json's counts (module docstring, 3)."""
    have = _counts(c)
    said = {k: meta[k] for k in ("ticks", "sent", "misses")}
    said["skipped"] = {k: v for k, v in meta["skipped"].items() if v}
    for key in ("ticks", "sent", "misses"):
        a, b = have[key], said[key]
        if a != b and (complete or b > a):
            rel = "" if complete else " (at most, for a run that did not finish)"
            raise RunLogError(
                f"{log_dir}: {source} holds {a} {'ticks' if key == 'ticks' else key + ' ticks'}, "
                f"{RUN_FILE} counts {b}{rel}"
            )
    for k in SKIP_KINDS:
        a, b = have["skipped"].get(k, 0), said["skipped"].get(k, 0)
        if a != b and (complete or b > a):
            raise RunLogError(
                f"{log_dir}: {source} holds {a} ticks skipped as {k!r}, {RUN_FILE} counts {b}"
            )


@functools.cache
def _torque_message() -> Any:
    """The DBC's torque command (cantools), loaded once."""
    import cantools

    import can_bridge

    return cantools.database.load_file(can_bridge.dbc_path()).get_message_by_name("WheelTorqueCmd")


def _torque_frames(path: Path, what: str) -> list[tuple[str, np.ndarray]]:
    """The torque frames the bridge logged sending, in order: (mode, torques [Nm])
    decoded by cantools from the DBC, each frame's E2E CRC checked by autosar-e2e."""
    import can
    import cantools
    import e2e.p01

    msg = _torque_message()
    data_id = int(msg.dbc.attributes["E2EDataID"].value)
    modes = dict(enumerate(MODES))
    out: list[tuple[str, np.ndarray]] = []
    try:
        reader = can.io.CanutilsLogReader(str(path))
        for m in reader:
            if m.is_rx or m.arbitration_id != msg.frame_id or m.is_extended_id:
                continue
            data = bytes(m.data or b"")
            at = f"{what}: torque frame {len(out) + 1}"
            if len(data) != msg.length or not e2e.p01.e2e_p01_check(bytearray(data), data_id):
                raise RunLogError(f"{at} ({data.hex()}) fails its E2E check")
            v = msg.decode(data, decode_choices=False)
            mode = modes.get(int(v["Mode"]), f"mode {int(v['Mode'])}")
            out.append((mode, np.array([float(v[f"Torque{w}"]) for w in WHEELS])))
    except RunLogError:
        raise
    except (
        ValueError,
        IndexError,
        TypeError,
        KeyError,
        OSError,
        cantools.database.DecodeError,
    ) as exc:
        raise RunLogError(
            f"{what}: not a candump log (after {len(out)} torque frames: {exc})"
        ) from None
    return out


def _check_frames(
    log_dir: Path, c: dict[str, np.ndarray], complete: bool, source: str
) -> tuple[int, int]:
    """Each tick's framed_* against the frame bridge.log holds (module docstring, 4)."""
    path = log_dir / BRIDGE_LOG
    what = f"{log_dir}: {BRIDGE_LOG}"
    if not path.is_file():
        raise RunLogError(f"{what}: missing (the bridge's candump log of the run)")
    frames = _torque_frames(path, what)
    checked = unchecked = 0
    for i in np.flatnonzero(c["bridge_tx_frames"] > 0):
        k = int(c["bridge_tx_frames"][i])
        if k > len(frames):
            if complete:
                raise RunLogError(
                    f"{what}: holds {len(frames)} torque frames; tick {i} of {source} was framed "
                    f"in frame {k}"
                )
            unchecked += 1
            continue
        mode, torques = frames[k - 1]
        framed = np.array([c[f"framed_{w}"][i] for w in WHEELS])
        if mode != c["bridge_mode"][i] or not np.array_equal(framed, torques):
            j = int(np.flatnonzero(framed != torques)[0]) if mode == c["bridge_mode"][i] else -1
            said = (
                f"framed_{WHEELS[j]} {framed[j]:g} Nm, frame {k} of {BRIDGE_LOG} carries "
                f"{torques[j]:g} Nm"
                if j >= 0
                else f"bridge_mode {c['bridge_mode'][i]!r}, frame {k} of {BRIDGE_LOG} is {mode!r}"
            )
            raise RunLogError(f"{log_dir}: {source}: tick {i}: {said}")
        checked += 1
    return checked, unchecked


def _check_digests(log_dir: Path, meta: dict[str, Any], complete: bool) -> None:
    """The digests run.json recorded (module docstring, 5)."""
    if run_digest(meta) != meta["digest"]:
        raise RunLogError(
            f"{log_dir}: {RUN_FILE} was modified after the run (its content does not hash to "
            f"its digest {meta['digest'][:12]}...)"
        )
    if not complete:
        return
    for name in (TICKS_FILE, BRIDGE_LOG):
        got = file_sha256(log_dir / name)
        if got != meta["files"][name]:
            raise RunLogError(
                f"{log_dir}: {name} was modified after the run (SHA-256 {got[:12]}..., "
                f"{RUN_FILE} recorded {meta['files'][name][:12]}...)"
            )
