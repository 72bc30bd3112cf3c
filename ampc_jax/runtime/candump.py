"""``ampc replay --candump FILE``: a drive's candump log through the controller.

A vehicle's log (``candump -l`` format, read by python-can's
``CanutilsLogReader``) holds the five state messages the controller reads
(:data:`~.signals.MESSAGES`) and, where the controller ran, the torque frames it
had framed (``WheelTorqueCmd``). Each frame is decoded with cantools from the
shipped DBC and its E2E Profile 1 CRC checked by autosar-e2e; a frame that
fails the check, or repeats its message's alive counter (a frozen sender), does
not refresh that message (as the bridge would not believe it).

Ticks: where the log has torque frames, one tick per frame, ``lead_ms`` before
it (the runtime reads the state ``--lead-ms`` before the bridge's tick, and the
frame at that tick carries the tick's command); otherwise every 50 ms from the
first moment every state message has arrived. At each tick the state is the
latest sound frame of each message that has stood the bridge's confirmation
time (``rx_confirm_ms`` of its shipped configuration, 25 ms: the bridge
believes a frame only then) by the tick; it steps the
controller from the first active torque frame on (before it, the bridge framed
no command; without torque frames, from the first tick), warm-started from the
previous stepped tick as ``ampc run`` does,
when every message is at most ``max_state_age_ms`` old, and the command it
would have framed is the bridge's limiter (:func:`~ampc_jax.vehicle.actuators.
bridge_actuators`) from the log's previous torque frame to the step's torques,
clamped to the actuators' ranges (:func:`~.step.clamp_to_limits`).

Where the log has a torque frame in mode ``active`` for a tick that stepped,
the two are compared bit for bit (the framed torques lie on the DBC's 2 Nm
grid). Rule: the replay feeds the log's frames at their own timestamps and
compares what it would have framed with what was framed; reason: a vehicle
engineer's question is "what would this controller have commanded on that
drive", and a log of the project's own run must come out the same.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..vehicle.params import CONTROL_DT
from .files import named
from .signals import BUS_FIELDS, MESSAGES, SIGNALS
from .step import StepReport, clamp_to_limits, command_problem

__all__ = ["CandumpError", "CandumpLog", "read_candump", "replay_candump"]

WHEELS = ("FL", "FR", "RL", "RR")
COMMAND = "WheelTorqueCmd"
MODE_NAMES = {0: "active", 1: "hold", 2: "safe", 3: "fault"}


class CandumpError(ValueError):
    """A candump log that cannot be replayed (the message names the file)."""


@dataclass
class Stream:
    """One state message's sound frames in the log: times (s) and values
    (frames x signals, in :data:`~.signals.MESSAGES` order)."""

    times: list[float] = field(default_factory=list)
    values: list[list[float]] = field(default_factory=list)


@dataclass
class CandumpLog:
    """What a candump log holds for the controller (:func:`read_candump`)."""

    path: Path
    streams: dict[str, Stream]
    cmd_times: np.ndarray  # (m,) s
    cmd_modes: list[str]
    cmd_torques: np.ndarray  # (m, 4) Nm
    frames: int = 0
    by_message: dict[str, int] = field(default_factory=dict)
    bad: dict[str, int] = field(default_factory=dict)
    other: int = 0


def _db() -> Any:
    import cantools

    import can_bridge

    return cantools.database.load_file(can_bridge.dbc_path())


def read_candump(path: str | Path) -> CandumpLog:
    """Decode the log's state and torque frames (CandumpError naming the file when
    it is not a candump log)."""
    import can
    import cantools
    import e2e.p01

    path = Path(path)
    what = f"--candump {path}"
    if not path.is_file():
        raise CandumpError(f"{what}: no such file")
    db = _db()
    wanted = {db.get_message_by_name(n).frame_id: n for n in (*MESSAGES, COMMAND)}
    ids = {
        n: int(db.get_message_by_name(n).dbc.attributes["E2EDataID"].value) for n in wanted.values()
    }
    streams = {n: Stream() for n in MESSAGES}
    last_counter: dict[str, int] = {}
    cmd_t: list[float] = []
    cmd_mode: list[str] = []
    cmd_tq: list[list[float]] = []
    log = CandumpLog(path, streams, np.zeros(0), [], np.zeros((0, 4)))
    bad: dict[str, int] = {}
    try:
        with named(path, "read"):
            reader = can.io.CanutilsLogReader(str(path))
            for m in reader:
                log.frames += 1
                name = None if m.is_extended_id else wanted.get(m.arbitration_id)
                if name is None:
                    log.other += 1
                    continue
                msg = db.get_message_by_name(name)
                data = bytes(m.data or b"")
                if len(data) != msg.length or not e2e.p01.e2e_p01_check(bytearray(data), ids[name]):
                    bad[f"{name} e2e"] = bad.get(f"{name} e2e", 0) + 1
                    continue
                log.by_message[name] = log.by_message.get(name, 0) + 1
                v = msg.decode(data, decode_choices=False)
                if name == COMMAND:
                    cmd_t.append(float(m.timestamp))
                    cmd_mode.append(MODE_NAMES.get(int(v["Mode"]), f"mode {int(v['Mode'])}"))
                    cmd_tq.append([float(v[f"Torque{w}"]) for w in WHEELS])
                    continue
                counter = int(v["Counter"])
                if last_counter.get(name) == counter:  # a frozen sender: not believed
                    bad[f"{name} repeated counter"] = bad.get(f"{name} repeated counter", 0) + 1
                    continue
                last_counter[name] = counter
                s = streams[name]
                s.times.append(float(m.timestamp))
                s.values.append([float(v[sig]) for sig in MESSAGES[name]])
    except CandumpError:
        raise
    except (
        ValueError,
        IndexError,
        TypeError,
        KeyError,
        OSError,
        cantools.database.DecodeError,
    ) as exc:
        raise CandumpError(
            f"{what}: not a candump log (after {log.frames} frames: {str(exc)[:160]})"
        ) from None
    log.cmd_times = np.asarray(cmd_t, np.float64)
    log.cmd_modes = cmd_mode
    log.cmd_torques = np.asarray(cmd_tq, np.float64).reshape(-1, 4)
    log.bad = bad
    missing = [n for n, s in streams.items() if not s.times]
    if missing:
        need = ", ".join(f"{n} (0x{db.get_message_by_name(n).frame_id:03X})" for n in MESSAGES)
        gone = ", ".join(f"{n} (0x{db.get_message_by_name(n).frame_id:03X})" for n in missing)
        raise CandumpError(
            f"{what}: no sound {gone} frame in its {log.frames} frames; the controller "
            f"needs every one of {need}"
        )
    return log


def confirm_s() -> float:
    """How long a sound frame stands before the bridge believes it (its shipped
    configuration's ``rx_confirm_ms``; ``docs/bus-safety.md``), s."""
    import can_bridge

    return 1e-3 * float(can_bridge.load_config(can_bridge.default_config_path())["rx_confirm_ms"])


def _state_at(
    log: CandumpLog, t: float, max_age_s: float, confirm: float
) -> tuple[np.ndarray | None, str]:
    """The bus vector the bridge gives at ``t``: of each message, the latest sound
    frame that has stood ``confirm`` by then (the bridge believes a frame only
    then); (None, why) when one has none yet or it is older than ``max_age_s``."""
    bus = np.empty(len(BUS_FIELDS))
    where = {sig.field: i for i, sig in enumerate(SIGNALS)}
    for name, s in log.streams.items():
        times = np.asarray(s.times)
        k = int(np.searchsorted(times, t - confirm, side="right")) - 1
        if k < 0:
            return None, f"no {name} yet"
        age = t - times[k]
        if age > max_age_s:
            return None, f"state stale ({name} {1e3 * age:.0f} ms old)"
        for sig, value in zip(MESSAGES[name].values(), s.values[k], strict=True):
            bus[where[sig]] = value
    return bus, ""


def _ticks(log: CandumpLog, lead_s: float) -> tuple[np.ndarray, bool]:
    """The ticks' times, and whether they are the log's torque frames (one each)."""
    if log.cmd_times.size:
        return log.cmd_times - lead_s, True
    start = max(s.times[0] for s in log.streams.values())
    stop = max(s.times[-1] for s in log.streams.values())
    return start + CONTROL_DT * np.arange(int((stop - start) / CONTROL_DT) + 1), False


def replay_candump(
    path: str | Path,
    scenario: str,
    out: Path,
    *,
    formulation: str | None = None,
    lead_ms: float = 25.0,
    max_state_age_ms: float = 100.0,
    figure: bool = True,
    progress: Callable[[str], Any] | None = None,
) -> dict[str, Any]:
    """Replay the candump log ``path`` through the controller set up for ``scenario``;
    write ``candump_replay.json``, ``candump_replay.parquet`` and (``figure``)
    ``candump_replay.png`` to ``out``; returns the summary (see the module docstring)."""
    import jax
    import jax.numpy as jnp

    from ..closed_loop import config_for
    from ..vehicle.actuators import ACTUATORS, TORQUE_STEP_NM, bridge_actuators
    from .step import RuntimeStep

    say = progress or (lambda _: None)
    log = read_candump(path)
    tick_t, on_frames = _ticks(log, lead_ms * 1e-3)
    confirm = confirm_s()
    kw = {"shadow": False} | ({"formulation": formulation} if formulation else {})
    step = RuntimeStep(config_for(scenario, **kw), "float64")
    t0 = time.perf_counter()
    fn = step.compiled()
    limiter = jax.jit(lambda prev, target: bridge_actuators(prev, target, ACTUATORS)[0])
    limiter(jnp.zeros(4, jnp.int32), jnp.zeros(4))
    say(f"compiled the step in {time.perf_counter() - t0:.1f} s; replaying {len(tick_t)} ticks")
    leaves = step.init_leaves()
    n = len(tick_t)
    rows: dict[str, list[Any]] = {"t": [], "stepped": [], "sent": [], "reason": []}
    rows.update({f"bus_{f}": [] for f in BUS_FIELDS})
    for prefix in ("cmd", "framed", "logged"):
        rows.update({f"{prefix}_{w}": [] for w in WHEELS})
    rows.update({"logged_mode": [], "compared": [], "identical": []})
    prev_steps = np.zeros(4, np.int32)
    t_first = float(tick_t[0]) if n else 0.0
    last = time.perf_counter()
    nan4 = [float("nan")] * 4
    # the controller starts with the first active frame: before it, the bridge
    # framed no command of its own (its start-up), and a replay warmed up on
    # those ticks would not start from the run's cold state
    active = [i for i, m in enumerate(log.cmd_modes) if m == "active"] if on_frames else [0]
    start = active[0] if active else n
    for i, t in enumerate(tick_t):
        if i < start:
            bus, why = None, "before the first active frame (the controller had not started)"
        else:
            bus, why = _state_at(log, float(t), max_state_age_ms * 1e-3, confirm)
        cmd = framed = nan4
        sent = False
        if bus is not None:
            torques, leaves, rep = fn(leaves, jnp.asarray(bus, step.jnp_dtype))
            raw = np.asarray(torques, np.float64)
            cmd = raw.tolist()
            why = command_problem(raw, StepReport(*(np.asarray(x) for x in rep))) or ""
            if not why:
                sent = True
                target, _ = clamp_to_limits(raw, ACTUATORS)
                steps = np.asarray(limiter(jnp.asarray(prev_steps), jnp.asarray(target)))
                framed = (steps * TORQUE_STEP_NM).astype(np.float64).tolist()
        logged, mode = nan4, ""
        if on_frames:
            logged, mode = log.cmd_torques[i].tolist(), log.cmd_modes[i]
            # the bridge's limiter goes on from what it framed last
            prev_steps = np.round(log.cmd_torques[i] / TORQUE_STEP_NM).astype(np.int32)
        elif sent:
            prev_steps = np.round(np.asarray(framed) / TORQUE_STEP_NM).astype(np.int32)
        compared = on_frames and sent and mode == "active"
        rows["t"].append(float(t) - t_first)
        rows["stepped"].append(bus is not None)
        rows["sent"].append(sent)
        rows["reason"].append(why)
        for j, f in enumerate(BUS_FIELDS):
            rows[f"bus_{f}"].append(float("nan") if bus is None else float(bus[j]))
        for j, w in enumerate(WHEELS):
            rows[f"cmd_{w}"].append(cmd[j])
            rows[f"framed_{w}"].append(framed[j])
            rows[f"logged_{w}"].append(logged[j])
        rows["logged_mode"].append(mode)
        rows["compared"].append(compared)
        rows["identical"].append(bool(compared and framed == logged))
        if time.perf_counter() - last >= 1.0:
            last = time.perf_counter()
            say(f"replayed {i + 1}/{n} ticks")
    summary = _summary(log, rows, on_frames, scenario, step, lead_ms, max_state_age_ms)
    summary["confirm_ms"] = 1e3 * confirm
    import pyarrow as pa
    import pyarrow.parquet as pq

    with named(out, "create the directory"):
        out.mkdir(parents=True, exist_ok=True)
    with named(out / "candump_replay.parquet"):
        pq.write_table(pa.table(rows), out / "candump_replay.parquet")
    if figure:
        png = out / "candump_replay.png"
        with named(png):
            _figure(rows, summary, png)
        summary["figure"] = str(png)
    with named(out / "candump_replay.json"):
        (out / "candump_replay.json").write_text(json.dumps(summary, indent=1))
    return summary


def _summary(
    log: CandumpLog,
    rows: dict[str, list[Any]],
    on_frames: bool,
    scenario: str,
    step: Any,
    lead_ms: float,
    max_age_ms: float,
) -> dict[str, Any]:
    compared = np.asarray(rows["compared"], bool)
    same = np.asarray(rows["identical"], bool)
    framed = np.array([rows[f"framed_{w}"] for w in WHEELS]).T.reshape(-1, 4)
    logged = np.array([rows[f"logged_{w}"] for w in WHEELS]).T.reshape(-1, 4)
    diff = np.abs(framed - logged)[compared]
    skipped: dict[str, int] = {}
    for st, why in zip(rows["stepped"], rows["reason"], strict=True):
        if not st:
            kind = (
                "stale"
                if why.startswith("state stale")
                else "before the start"
                if why.startswith("before the first")
                else "waiting"
            )
            skipped[kind] = skipped.get(kind, 0) + 1
    first = None
    if (compared & ~same).any():
        i = int(np.flatnonzero(compared & ~same)[0])
        j = int(np.flatnonzero(framed[i] != logged[i])[0])
        first = {
            "tick": i,
            "t": rows["t"][i],
            "wheel": WHEELS[j],
            "logged_nm": float(logged[i, j]),
            "replayed_nm": float(framed[i, j]),
        }
    return {
        "log": str(log.path),
        "scenario": scenario,
        "formulation": step.config.formulation,
        "config_hash": step.config_hash(),
        "lead_ms": lead_ms,
        "max_state_age_ms": max_age_ms,
        "frames": log.frames,
        "frames_by_message": log.by_message,
        "frames_refused": log.bad,
        "frames_other": log.other,
        "ticks_on": "the log's torque frames" if on_frames else "a 50 ms grid",
        "ticks": len(rows["t"]),
        "stepped": int(np.sum(rows["stepped"])),
        "sent": int(np.sum(rows["sent"])),
        "skipped": skipped,
        "compared": int(compared.sum()),
        "identical": int(same.sum()),
        "differ": int((compared & ~same).sum()),
        "max_abs_diff_nm": float(diff.max()) if diff.size else 0.0,
        "first_difference": first,
    }


def _figure(rows: dict[str, list[Any]], summary: dict[str, Any], path: Path) -> None:
    """The commands the replay would have framed against the log's, per wheel, and
    their difference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(rows["t"])
    fig, axes = plt.subplots(5, 1, figsize=(9, 10), sharex=True)
    for ax, w in zip(axes[:4], WHEELS, strict=True):
        logged = np.asarray(rows[f"logged_{w}"])
        if np.isfinite(logged).any():
            ax.step(t, logged, where="post", color="0.3", lw=1.6, label="in the log")
        ax.step(t, rows[f"framed_{w}"], where="post", color="C1", lw=0.9, ls="--",
                label="replayed (framed)")  # fmt: skip
        ax.set_ylabel(f"T_{w} [Nm]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    d = np.abs(
        np.array([rows[f"framed_{w}"] for w in WHEELS])
        - np.array([rows[f"logged_{w}"] for w in WHEELS])
    ).max(axis=0)
    axes[4].plot(t, d, ".", ms=3, color="C3")
    axes[4].set_ylabel("max |dT| [Nm]")
    axes[4].set_xlabel("time since the first tick [s]")
    axes[4].grid(alpha=0.3)
    axes[0].set_title(
        f"{Path(summary['log']).name}: {summary['scenario']} ({summary['formulation']}); "
        f"{summary['identical']} of {summary['compared']} active frames identical"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
