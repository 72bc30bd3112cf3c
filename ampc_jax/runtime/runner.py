"""``ampc run``: the compiled controller at 20 Hz next to the CAN bridge.

Every 50 ms, a lead time before the bridge's own tick: take the latest state
from the bridge (:meth:`can_bridge.Bridge.latest_state`), build the bus vector,
call the compiled step warm-started from the previous tick, and hand the
first-step torques to the bridge with a sequence number. Rule: a tick sends
nothing new when the state is invalid or stale, or the step failed, or its
torques are not finite or leave a wheel's range (:func:`~.step.command_problem`);
reason: the bridge's watchdog then holds and releases the wheels on its own
clock (hold, safe, a latched fault), which is the one safe reaction, and a
torque computed from bad data is never the right one. The tick log says why.

The channel opens first (a missing device is refused at once), then the step
is compiled (or an artefact compiled and checked) and called once; nothing
compiles inside the loop. Each tick is on disk before the next starts
(:mod:`~.ticklog`): a killed run keeps its ticks up to the kill.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from ..results import Status
from ..vehicle.actuators import ACTUATORS, bridge_kwargs
from ..vehicle.params import CONTROL_DT
from .faults import Fault, active_fault
from .files import named
from .signals import BUS_FIELDS, bus_from_bridge
from .step import StepReport, clamp_to_limits, command_problem
from .ticklog import COLUMNS, TickJournal, new_row, remove_logs

__all__ = [
    "RT_PRIORITY",
    "ChannelError",
    "Prepared",
    "RunOptions",
    "TickLog",
    "environment",
    "fifo_refusal",
    "open_bridge",
    "run_controller",
]

WHEEL_NAMES = ("FL", "FR", "RL", "RR")


@dataclass(frozen=True)
class RunOptions:
    """Settings of a run (defaults as ``ampc run``'s flags).

    duration : seconds of actuation after the first valid state.
    lead_ms : how long before each bridge tick the runtime's tick starts (25):
        room for the state read, the step and the hand-over on a shared machine
        (docs/runtime.md, "Timing").
    max_state_age_ms : older state counts as stale (100).
    start_timeout_s : longest wait for the first valid state (60).
    faults : injected controller faults (``nan``, ``fail``).
    rt_priority : None (normal scheduling), or a SCHED_FIFO priority 2..99 for
        the bridge's transmit thread, with one less for the runtime's loop (needs
        root or CAP_SYS_NICE; the step then runs in the loop's thread; ``ampc
        run`` asks for :data:`RT_PRIORITY` where the system allows it).
    """

    duration: float = 16.0
    lead_ms: float = 25.0
    max_state_age_ms: float = 100.0
    start_timeout_s: float = 60.0
    faults: tuple[Fault, ...] = ()
    rt_priority: int | None = None

    def __post_init__(self) -> None:
        period_ms = 1e3 * CONTROL_DT
        if not 0.0 < self.lead_ms < period_ms - 5.0:
            raise ValueError(
                f"lead_ms: expected a lead time in (0, {period_ms - 5.0:g}) ms, got {self.lead_ms!r}"
            )
        if not 0.0 < self.duration:
            raise ValueError(f"duration: expected a positive time, got {self.duration!r}")


@dataclass
class TickLog:
    """One row per tick (:data:`~.ticklog.COLUMNS`) and the run's summary (``run.json``)."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)

    def table(self) -> Any:
        import pyarrow as pa

        return pa.table({k: [r[k] for r in self.rows] for k in COLUMNS})


class ChannelError(RuntimeError):
    """The bridge could not open its channel (a missing device, a refused connection)."""


class Prepared(NamedTuple):
    """What :func:`run_controller`'s ``prepare`` returns: the compiled step, its cold
    state and its dtype."""

    step_fn: Any
    leaves: tuple[Any, ...]
    dtype: Any


def environment() -> dict[str, Any]:
    """What a bit-for-bit replay needs to match: versions and XLA's flags."""
    import jaxlib

    return {
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


RT_PRIORITY = 50
"""``ampc run``'s default SCHED_FIFO priority for the bridge's transmit thread (the
loop runs at one less). Rule: ask for real-time scheduling by default; reason:
under load the period error seen by an independent receiver is almost all the
transmit thread waking late (p99 3.4 to 5.4 ms on a busy machine, 10 to 28 ms
with two extra busy loops), and with SCHED_FIFO 50 the bridge's own part is
0.04 ms at p99 (can_bridge/README.md; docs/runtime.md, "Timing")."""


def fifo_refusal(priority: int) -> str | None:
    """Why this process may not run a thread under SCHED_FIFO at ``priority``
    (None: it may). Tried on the calling thread and undone at once."""
    if not hasattr(os, "SCHED_FIFO"):
        return "SCHED_FIFO does not exist on this system"
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return f"{exc.strerror or exc}; needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO of {priority}"
    os.sched_setscheduler(0, policy, param)
    return None


def _first_deadline(bridge: Any, timeout: float = 2.0) -> int:
    """The bridge's first tick deadline (ns, CLOCK_MONOTONIC)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        trace = bridge.tick_trace()
        if trace:
            return int(trace[0][1])
        time.sleep(0.005)
    raise RuntimeError("the bridge reported no tick within 2 s")


def _sleep_until(t_ns: int) -> None:
    while True:
        d = (t_ns - time.monotonic_ns()) * 1e-9
        if d <= 0:
            return
        time.sleep(min(d, 0.05))


def open_bridge(channel: str, out: Path, options: RunOptions) -> Any:
    """The bridge on ``channel``, started (its channel open, its candump log
    ``out/bridge.log`` begun); ChannelError when the channel cannot be opened."""
    import can_bridge

    try:
        bridge = can_bridge.Bridge(
            channel,
            **bridge_kwargs(ACTUATORS),
            log_path=str(out / "bridge.log"),
            log_overwrite=True,
            trace_capacity=1,
            rt_priority=options.rt_priority,
        )
        bridge.start()
    except can_bridge.CanBridgeError as exc:
        raise ChannelError(f"{channel}: {exc}") from None
    return bridge


def _plant_exit(returncode: int, tick: int, n_ticks: int) -> str:
    if returncode < 0:
        try:
            name = f" ({signal.Signals(-returncode).name})"
        except ValueError:
            name = ""
        how = f"was killed by signal {-returncode}{name}"
    else:
        how = f"exited with code {returncode}"
    return f"the plant process {how} at tick {tick} of {n_ticks}"


def run_controller(
    prepare: Callable[[], Prepared],
    channel: str,
    out: Path,
    options: RunOptions,
    *,
    meta: dict[str, Any],
    plant_cmd: list[str] | None = None,
    plant_out: Path | None = None,
    progress: Any = None,
) -> TickLog:
    """Run the controller next to a bridge on ``channel``; write the logs to ``out``.

    The channel is opened first (ChannelError: a missing device is refused
    before anything compiles), then ``plant_cmd`` started (``ampc run
    --with-plant``: ``{pty}`` is replaced by the bridge's pseudo-terminal; it
    compiles its plant meanwhile; ``plant_out``: where it writes ``plant.json``,
    whose receive period goes to ``run.json["receive_period"]``), then
    ``prepare()`` compiles the step
    (:class:`Prepared`; ``f(leaves, bus) -> (torques, leaves, report)``, calls
    never trace). ``progress(text)`` gets a status line about once a second.

    The tick log is on disk as the ticks run (:class:`~.ticklog.TickJournal`);
    however the run ends short of being killed (its duration, SIGTERM or SIGINT,
    an error, the plant's exit), ``ticks.parquet`` and ``run.json`` are written,
    ``run.json["state"]`` saying how it ended and ``["error"]`` why, if it did.
    """
    with named(out, "create the directory"):
        out.mkdir(parents=True, exist_ok=True)
    remove_logs(out)  # an earlier run's logs must not pass for this one's if it is killed
    log = TickLog()
    bridge = open_bridge(channel, out, options)
    stop = {"by": None}
    reset = {"flag": False}
    period_ns = int(round(1e9 * CONTROL_DT))
    lead_ns = int(options.lead_ms * 1e6)
    n_ticks = int(round(options.duration / CONTROL_DT))
    plant = None
    journal: TickJournal | None = None
    compute: list[float] = []
    resets: list[float] = []
    ended_early = True
    error: str | None = None
    handlers: dict[int, Any] = {}
    stats: dict[str, Any] | None = None

    def summary() -> dict[str, Any]:
        s = stats or bridge.stats()
        return {"resets_t": resets, **_counts(log.rows, compute), "bridge": _bridge_stats(s)}

    try:
        if plant_cmd is not None:
            cmd = [c.replace("{pty}", bridge.pty_path or "") for c in plant_cmd]
            plant = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=sys.stderr)
        elif progress is not None and bridge.pty_path:
            progress(
                f"bridge pty: {bridge.pty_path} (ampc plant --channel slcan:{bridge.pty_path})"
            )
        step_fn, cold, dtype = prepare()
        # Rule: the step gets NumPy arrays of its own dtype (a jnp conversion would
        # compile a small program at the first tick, about a whole 50 ms tick), and
        # it is called once before actuation and again on the first valid state,
        # so the first tick runs warm.
        np_dtype = np.dtype(dtype)
        cold = tuple(cold)
        jax.block_until_ready(step_fn(cold, np.zeros((len(BUS_FIELDS),), np_dtype)))
        for sig, act in (
            (signal.SIGTERM, lambda *_: stop.update(by=stop["by"] or "SIGTERM")),
            (signal.SIGINT, lambda *_: stop.update(by=stop["by"] or "SIGINT")),
            (signal.SIGUSR1, lambda *_: reset.update(flag=True)),
        ):
            handlers[sig] = signal.signal(sig, act)
        d0 = _first_deadline(bridge)
        # the first valid state starts actuation
        t_wait = time.monotonic()
        while not bridge.latest_state()["valid"]:
            if stop["by"]:
                raise RuntimeError(f"stopped by {stop['by']} before actuation started")
            if time.monotonic() - t_wait > options.start_timeout_s:
                why = bridge.latest_state()["reason"]
                raise TimeoutError(
                    f"no valid vehicle state within {options.start_timeout_s:g} s ({why})"
                )
            if plant is not None and plant.poll() is not None:
                raise RuntimeError(_plant_exit(plant.returncode, 0, n_ticks))
            time.sleep(0.01)
        first, _ = bus_from_bridge(bridge.latest_state())
        if first is not None:  # warm again, on real data (the result is not used)
            jax.block_until_ready(step_fn(cold, first.astype(np_dtype)))
        # The bridge latches a fault when no command came for fault_after_ms,
        # which the wait for the first state (the plant's start) may exceed:
        # starting actuation is the explicit reset of that start-up latch.
        # The bridge applies a reset at its next tick and ignores commands that
        # arrived before it: actuation starts once the reset has taken effect.
        start_reset = bridge.stats()["safety_state"] == "fault"
        if start_reset:
            bridge.reset_fault()
            t_reset = time.monotonic()
            while bridge.stats()["safety_state"] == "fault":
                if time.monotonic() - t_reset > 1.0:
                    raise RuntimeError("the bridge did not leave its start-up fault after a reset")
                time.sleep(0.005)
        # tick 0: the first bridge deadline whose wake-up (deadline - lead) is ahead
        k0 = -((d0 - time.monotonic_ns() - lead_ns) // period_ns)
        journal = TickJournal(
            out,
            {**meta, "start_reset": start_reset, "pid": os.getpid(), "host": socket.gethostname()},
        )
        if options.rt_priority is not None:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(options.rt_priority - 1))
        last_print = time.monotonic()
        leaves, seq = cold, 0
        for i in range(n_ticks):
            if stop["by"]:
                break
            deadline = d0 + (k0 + i) * period_ns
            if plant is not None and plant.poll() is not None:
                # a plant that finished its manoeuvre within the last two ticks
                # (its clock started one tick after ours) is the normal end
                end = d0 + (k0 + n_ticks - 2) * period_ns
                if plant.returncode != 0 or time.monotonic_ns() < end:
                    error = _plant_exit(plant.returncode, i, n_ticks)
                    break
            if reset["flag"]:  # SIGUSR1: the operator's explicit reset of a latched fault
                reset["flag"] = False
                bridge.reset_fault()
                # on the clock of the frames: 0 at the first actuated bridge tick
                resets.append((time.monotonic_ns() - (d0 + k0 * period_ns)) * 1e-9)
            wake = deadline - lead_ns
            if time.monotonic_ns() > deadline:  # this tick's bridge deadline already passed
                row = new_row(i, wake, "late", "late")
            else:
                _sleep_until(wake)
                row = _tick(i, wake, bridge, step_fn, leaves, np_dtype, options, deadline, seq)
                leaves = row.pop("_leaves")
                if row["stepped"]:
                    compute.append(row["compute_ms"])
                if row["sent"]:
                    seq = row["seq"]
                if log.rows:
                    _frame_of(log.rows[-1], bridge)
                    journal.framed(log.rows[-1])
            log.rows.append(row)
            journal.append(row)
            if time.monotonic() - last_print >= 1.0:
                last_print = time.monotonic()
                stats = None
                journal.status(summary())
                if progress is not None:
                    c = summary()
                    p99 = f"{c['compute_ms_p99']:.2f} ms" if compute else "-"
                    progress(
                        f"t {i * CONTROL_DT:5.1f}/{options.duration:g} s  ticks {i + 1}  "
                        f"sent {c['sent']}  misses {c['misses']}  compute p99 {p99}  bridge "
                        f"{bridge.stats()['tx_mode']}  last {row['reason'] or 'sent'}"
                    )
        else:
            ended_early = False
        if log.rows and not ended_early:  # the last command's frame, one tick later
            _sleep_until(d0 + (k0 + n_ticks) * period_ns + 5_000_000)
            _frame_of(log.rows[-1], bridge)
            journal.framed(log.rows[-1])
    except BaseException as exc:
        if journal is not None and error is None:  # recorded in run.json, then raised
            error = f"{type(exc).__name__}: {exc}"
        raise
    finally:
        if options.rt_priority is not None:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        stats = bridge.stats() if bridge.running else None
        bridge.stop()
        stats = stats or bridge.stats()
        for sig, old in handlers.items():
            signal.signal(sig, old)
        if plant is not None:
            ended = _end_plant(plant, wait_s=5.0 if ended_early else 30.0)
            if error is None and not ended_early and (ended != "exited" or plant.returncode):
                error = (
                    f"the plant process exited with code {plant.returncode} after the run"
                    if ended == "exited"
                    else f"the plant process did not end within 30 s of the run's end ({ended})"
                )
        if journal is not None:
            state = "error" if error else ("stopped" if stop["by"] else "finished")
            final = {
                **summary(),
                "state": state,
                "plant_returncode": None if plant is None else plant.returncode,
                "pid": os.getpid(),
                "environment": environment(),
            }
            if plant_out is not None:
                final["receive_period"] = receive_period(plant_out / "plant.json")
            if error:
                final["error"] = error
            if stop["by"]:
                final["stopped_by"] = stop["by"]
            in_flight = sys.exc_info()[1]
            try:
                log.summary = journal.finish(log.rows, final)
            except OSError:
                # the final logs could not be written (a full disk): the journal
                # stays, replayable as a killed run's; the error that ended the
                # run, if one did, is the one reported
                if in_flight is None:
                    raise
    return log


def receive_period(plant_json: Path) -> dict[str, Any] | None:
    """The period of the torque frames as the receiving side saw them (``ampc
    plant``'s receive thread, python-can, stamped on arrival): frames, median
    period and |period - 50 ms| at p50, p99 and max (ms); None without a report."""
    import json

    try:
        rep = json.loads(plant_json.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(rep, dict):
        return None
    keys = {
        "frames": "frames",
        "period_ms_median": "period_ms_median",
        "error_ms_p50": "period_dev_ms_p50",
        "error_ms_p99": "period_dev_ms_p99",
        "error_ms_max": "period_dev_ms_max",
    }
    return {k: rep.get(v) for k, v in keys.items()}


def _counts(rows: list[dict[str, Any]], compute: list[float]) -> dict[str, Any]:
    """The run's counts and compute statistics from its rows (run.json's fields)."""
    c = np.asarray(compute)
    q = lambda p: float(np.percentile(c, p)) if c.size else None  # noqa: E731
    skipped: dict[str, int] = {}
    for r in rows:
        if r["skip"]:
            skipped[r["skip"]] = skipped.get(r["skip"], 0) + 1
    sent = [r for r in rows if r["sent"]]
    return {
        "ticks": len(rows),
        "sent": len(sent),
        "misses": skipped.get("late", 0) + sum(r["margin_ms"] < 0 for r in sent),
        "skipped": skipped,
        "compute_ms_median": q(50),
        "compute_ms_p99": q(99),
        "compute_ms_max": float(c.max()) if c.size else None,
        "margin_ms_min": min((r["margin_ms"] for r in sent), default=None),
    }


def _bridge_stats(s: dict[str, Any]) -> dict[str, Any]:
    return {k: s[k] for k in _BRIDGE_STATS}


def _tick(
    i: int,
    wake: int,
    bridge: Any,
    step_fn: Any,
    leaves: tuple[Any, ...],
    np_dtype: Any,
    options: RunOptions,
    deadline: int,
    seq: int,
) -> dict[str, Any]:
    """One tick from its wake-up: state, step, checks, hand-over. The row, with
    ``_leaves`` (the next warm state) for the loop."""
    import can_bridge

    woke = time.monotonic_ns()
    st = bridge.latest_state()
    got_state = time.monotonic_ns()
    bus, why = bus_from_bridge(st)
    age = st.get("age_ms")
    if bus is not None and (age is None or age > options.max_state_age_ms):
        bus, why = None, f"state stale ({age} ms)"
    if bus is None:
        row = _state_row(new_row(i, woke, why or "no state", "state"), st)
        row.update(_leaves=leaves, wake_late_ms=(woke - wake) * 1e-6)
        return row
    t0 = time.perf_counter()
    torques, new_leaves, rep = step_fn(leaves, bus.astype(np_dtype))
    torques = np.asarray(torques, np.float64)
    dt_ms = (time.perf_counter() - t0) * 1e3
    report = StepReport(*(np.asarray(x) for x in rep))
    raw = torques.copy()
    fault = active_fault(options.faults, i * CONTROL_DT)
    if fault == "nan":
        torques = np.full(4, np.nan)
    elif fault == "fail":
        report = report._replace(status=np.int32(Status.SOLVER_ERROR), fallback=np.bool_(True))
    problem = command_problem(torques, report)
    clamped = None
    margin = set_ms = float("nan")
    if problem is None:
        torques, clamped = clamp_to_limits(torques, ACTUATORS)
        t_set = time.monotonic_ns()
        try:
            bridge.set_command(torques.tolist(), seq + 1)
        except can_bridge.CanBridgeError as exc:  # refused (a "refuse" limit rule, a stop)
            problem = f"bridge refused the command: {exc}"
        t_done = time.monotonic_ns()
        set_ms = (t_done - t_set) * 1e-6
        margin = (deadline - t_done) * 1e-6
    ok = problem is None
    row = _state_row(new_row(i, woke, problem or "", "" if ok else "step"), st)
    row.update(
        stepped=True,
        sent=ok,
        compute_ms=dt_ms,
        margin_ms=margin if ok else float("nan"),
        state_call_ms=(got_state - woke) * 1e-6,
        set_call_ms=set_ms,
        wake_late_ms=(woke - wake) * 1e-6,
        seq=seq + 1 if ok else -1,
        fault=fault or "",
        clamped=clamped or "",
        iterations=int(report.iterations),
        status=int(report.status),
        fallback=bool(report.fallback),
        primal_residual=float(report.primal_residual),
        dual_residual=float(report.dual_residual),
        _leaves=new_leaves,
    )
    for j, name in enumerate(BUS_FIELDS):
        row[f"bus_{name}"] = float(bus[j])
    for j, w in enumerate(WHEEL_NAMES):
        row[f"cmd_{w}"] = float(raw[j])
    return row


def _state_row(row: dict[str, Any], st: dict[str, Any]) -> dict[str, Any]:
    row["state_valid"] = bool(st["valid"])
    if st.get("age_ms") is not None:
        row["state_age_ms"] = float(st["age_ms"])
    return row


def _frame_of(row: dict[str, Any], bridge: Any) -> None:
    """What the bridge framed at the tick the row's command was for, read after
    that tick: ``framed_*``, ``bridge_mode``, and ``bridge_tx_frames`` (which of
    its logged frames that was), from one snapshot of its statistics."""
    s = bridge.stats()
    row["bridge_mode"] = s["tx_mode"]
    row["bridge_tx_frames"] = int(s["tx_frames"])
    for j, w in enumerate(WHEEL_NAMES):
        row[f"framed_{w}"] = float(s["applied_torques_nm"][j])


def _end_plant(plant: subprocess.Popen, wait_s: float) -> str:
    """Wait for the plant to finish its run; terminate it, then kill it, if it does
    not. Returns "exited", "terminated" or "killed"."""
    try:
        plant.wait(timeout=wait_s)
        return "exited"
    except subprocess.TimeoutExpired:
        plant.terminate()
    try:
        plant.wait(timeout=5.0)
        return "terminated"
    except subprocess.TimeoutExpired:
        plant.kill()
        plant.wait(timeout=5.0)
        return "killed"


_BRIDGE_STATS = (
    "ticks",
    "overruns",
    "skipped_ticks",
    "lateness_p50_ms",
    "lateness_p99_ms",
    "lateness_max_ms",
    "mean_period_ms",
    "tx_frames",
    "tx_errors",
    "limit_events",
    "rate_limited_ticks",
    "rx_frames",
    "rx_crc_errors",
    "rx_counter_errors",
    "rx_two_sources",
    "rx_implausible",
    "rx_inconsistent",
    "rx_discarded",
    "ramp_restarts",
    "tx_stale_dropped",
    "safety_state",
    "transport_losses",
    "log_dropped",
    "log_errors",
    "log_suppressed",
    "last_log_error",
    "tx_safe_only",
)
