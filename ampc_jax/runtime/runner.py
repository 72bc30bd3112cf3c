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

Nothing compiles inside the loop: the step is compiled (or an artefact loaded
and checked) and called once before the bridge starts.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..vehicle.actuators import ACTUATORS, bridge_kwargs
from ..vehicle.params import CONTROL_DT
from .faults import Fault, active_fault
from .signals import BUS_FIELDS, bus_from_bridge
from .step import StepReport, clamp_to_limits, command_problem

__all__ = ["RunOptions", "TickLog", "environment", "run_controller"]

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
    rt_priority : None (default), or a SCHED_FIFO priority 2..99 for the
        bridge's transmit thread, with one less for the runtime's loop (needs
        root or CAP_SYS_NICE; the step then runs in the loop's thread).
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
    """One row per tick (see :meth:`columns`) and the run's summary."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)

    def table(self) -> Any:
        import pyarrow as pa

        if not self.rows:
            return pa.table({"tick": pa.array([], pa.int64())})
        return pa.table({k: [r[k] for r in self.rows] for k in self.rows[0]})


def environment() -> dict[str, Any]:
    """What a bit-for-bit replay needs to match: versions and XLA's flags."""
    import jaxlib

    return {
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


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


def run_controller(
    step_fn: Any,
    init_leaves: tuple[Any, ...],
    channel: str,
    out: Path,
    options: RunOptions,
    *,
    meta: dict[str, Any],
    plant_cmd: list[str] | None = None,
    progress: Any = None,
    dtype: Any = jnp.float64,
) -> TickLog:
    """Run the controller next to a bridge on ``channel``; write the logs to ``out``.

    ``step_fn(leaves, bus) -> (torques, leaves, report)`` must be compiled
    already. ``plant_cmd``: a command started once the bridge is up, with
    ``{pty}`` replaced by the bridge's pseudo-terminal (``ampc run --with-plant``).
    ``progress(text)`` gets a status line about once a second.
    """
    import can_bridge

    out.mkdir(parents=True, exist_ok=True)
    log = TickLog()
    # Rule: the step gets NumPy arrays of its own dtype (a jnp conversion would
    # compile a small program at the first tick: 50 ms measured in float32), and
    # it is called once before actuation and again on the first valid state,
    # so the first tick runs warm.
    np_dtype = np.dtype(dtype)
    cold = tuple(init_leaves)
    _, _, _ = step_fn(cold, np.zeros((len(BUS_FIELDS),), np_dtype))
    stop = {"flag": False}
    reset = {"flag": False}
    bridge = can_bridge.Bridge(
        channel,
        **bridge_kwargs(ACTUATORS),
        log_path=str(out / "bridge.log"),
        log_overwrite=True,
        trace_capacity=1,
        rt_priority=options.rt_priority,
    )
    period_ns = int(round(1e9 * CONTROL_DT))
    lead_ns = int(options.lead_ms * 1e6)
    n_ticks = int(round(options.duration / CONTROL_DT))
    plant = None
    leaves = cold
    seq = 0
    compute: list[float] = []
    misses = 0
    sent = 0
    skipped: dict[str, int] = {}
    resets: list[float] = []
    ended_early = True
    error: str | None = None
    old_term = signal.signal(signal.SIGTERM, lambda *_: stop.update(flag=True))
    old_usr1 = signal.signal(signal.SIGUSR1, lambda *_: reset.update(flag=True))
    try:
        bridge.start()
        if plant_cmd is not None:
            cmd = [c.replace("{pty}", bridge.pty_path or "") for c in plant_cmd]
            plant = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=sys.stderr)
        elif progress is not None and bridge.pty_path:
            progress(
                f"bridge pty: {bridge.pty_path} (ampc plant --channel slcan:{bridge.pty_path})"
            )
        d0 = _first_deadline(bridge)
        # the first valid state starts actuation
        t_wait = time.monotonic()
        while not bridge.latest_state()["valid"]:
            if stop["flag"] or time.monotonic() - t_wait > options.start_timeout_s:
                why = bridge.latest_state()["reason"]
                raise TimeoutError(
                    f"no valid vehicle state within {options.start_timeout_s:g} s ({why})"
                )
            if plant is not None and plant.poll() is not None:
                raise RuntimeError(f"the plant process exited with code {plant.returncode}")
            time.sleep(0.01)
        first, _ = bus_from_bridge(bridge.latest_state())
        if first is not None:  # warm again, on real data (the result is not used)
            jax.block_until_ready(step_fn(cold, first.astype(np_dtype)))
        # The bridge latches a fault when no command came for fault_after_ms,
        # which the wait for the first state (the plant's start) may exceed:
        # starting actuation is the explicit reset of that start-up latch.
        # The bridge applies a reset at its next tick and ignores commands that
        # arrived before it: actuation starts once the reset has taken effect.
        if bridge.stats()["safety_state"] == "fault":
            bridge.reset_fault()
            log.summary["start_reset"] = True
            t_reset = time.monotonic()
            while bridge.stats()["safety_state"] == "fault":
                if time.monotonic() - t_reset > 1.0:
                    raise RuntimeError("the bridge did not leave its start-up fault after a reset")
                time.sleep(0.005)
        # tick 0: the first bridge deadline whose wake-up (deadline - lead) is ahead
        k0 = -((d0 - time.monotonic_ns() - lead_ns) // period_ns)
        if options.rt_priority is not None:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(options.rt_priority - 1))
        last_print = time.monotonic()
        for i in range(n_ticks):
            if stop["flag"]:
                break
            if plant is not None and plant.poll() is not None:
                error = f"the plant process exited with code {plant.returncode}"
                break
            if reset["flag"]:  # SIGUSR1: the operator's explicit reset of a latched fault
                reset["flag"] = False
                bridge.reset_fault()
                # on the clock of the frames: 0 at the first actuated bridge tick
                resets.append((time.monotonic_ns() - (d0 + k0 * period_ns)) * 1e-9)
            deadline = d0 + (k0 + i) * period_ns
            wake = deadline - lead_ns
            if time.monotonic_ns() > deadline:  # this tick's bridge deadline already passed
                misses += 1
                skipped["late"] = skipped.get("late", 0) + 1
                log.rows.append(_row(i, wake, None, None, None, None, "late", False))
            else:
                _sleep_until(wake)
                row = _tick(i, wake, bridge, step_fn, leaves, np_dtype, options, deadline, seq)
                leaves = row.pop("_leaves")
                if row.pop("_stepped"):
                    compute.append(row["compute_ms"])
                if row["sent"]:
                    seq, sent = row["seq"], sent + 1
                    misses += row["margin_ms"] < 0
                else:
                    kind = row.pop("_skip")
                    skipped[kind] = skipped.get(kind, 0) + 1
                row.pop("_skip", None)
                _frame_of_previous(log.rows, bridge)
                log.rows.append(row)
            if progress is not None and time.monotonic() - last_print >= 1.0:
                last_print = time.monotonic()
                p99 = float(np.percentile(compute, 99)) if compute else float("nan")
                progress(
                    f"t {i * CONTROL_DT:5.1f}/{options.duration:g} s  ticks {i + 1}  sent {sent}  "
                    f"misses {misses}  compute p99 {p99:.2f} ms  bridge "
                    f"{bridge.stats()['tx_mode']}  last {log.rows[-1]['reason'] or 'sent'}"
                )
        else:
            ended_early = False
        if log.rows and not ended_early:  # the last command's frame, one tick later
            _sleep_until(d0 + (k0 + n_ticks) * period_ns + 5_000_000)
            _frame_of_previous(log.rows, bridge)
    finally:
        if options.rt_priority is not None:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        stats = bridge.stats() if bridge.running else None
        bridge.stop()
        stats = stats or bridge.stats()
        signal.signal(signal.SIGTERM, old_term)
        signal.signal(signal.SIGUSR1, old_usr1)
        if plant is not None:
            _end_plant(plant, wait_s=5.0 if ended_early else 30.0)
    if error is not None:
        log.summary["error"] = error
    c = np.asarray(compute)
    q = lambda p: float(np.percentile(c, p)) if c.size else None  # noqa: E731
    log.summary = {
        **meta,
        "start_reset": log.summary.get("start_reset", False),
        "resets_t": resets,
        "ticks": len(log.rows),
        "sent": sent,
        "misses": misses,
        "skipped": skipped,
        "compute_ms_median": q(50),
        "compute_ms_p99": q(99),
        "compute_ms_max": float(c.max()) if c.size else None,
        "margin_ms_min": min((r["margin_ms"] for r in log.rows if r["sent"]), default=None),
        "bridge": {k: stats[k] for k in _BRIDGE_STATS},
        "plant_returncode": None if plant is None else plant.returncode,
        "pid": os.getpid(),
        "environment": environment(),
    }
    import pyarrow.parquet as pq

    pq.write_table(log.table(), out / "ticks.parquet")
    (out / "run.json").write_text(json.dumps(log.summary, indent=1, default=str))
    return log


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
    ``_leaves`` (the next warm state), ``_stepped`` and ``_skip`` for the loop."""
    import can_bridge

    woke = time.monotonic_ns()
    st = bridge.latest_state()
    got_state = time.monotonic_ns()
    bus, why = bus_from_bridge(st)
    age = st.get("age_ms")
    if bus is not None and (age is None or age > options.max_state_age_ms):
        bus, why = None, f"state stale ({age} ms)"
    if bus is None:
        row = _row(i, woke, st, None, None, None, why, False)
        row.update(_leaves=leaves, _stepped=False, _skip="state")
        row["wake_late_ms"] = (woke - wake) * 1e-6
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
        report = report._replace(status=np.int32(4), fallback=np.bool_(True))
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
    row = _row(i, woke, st, bus, raw, report, problem, ok)
    row.update(
        compute_ms=dt_ms,
        margin_ms=margin if ok else float("nan"),
        state_call_ms=(got_state - woke) * 1e-6,
        set_call_ms=set_ms,
        wake_late_ms=(woke - wake) * 1e-6,
        seq=seq + 1 if ok else -1,
        fault=fault or "",
        clamped=clamped or "",
    )
    row.update(_leaves=new_leaves, _stepped=True, _skip="step")
    return row


def _frame_of_previous(rows: list[dict[str, Any]], bridge: Any) -> None:
    """What the bridge framed at the tick the previous row's command was for:
    read after that tick (the rows' ``framed_*`` and ``bridge_mode``)."""
    if not rows:
        return
    s = bridge.stats()
    rows[-1]["bridge_mode"] = s["tx_mode"]
    for j, w in enumerate(WHEEL_NAMES):
        rows[-1][f"framed_{w}"] = float(s["applied_torques_nm"][j])


def _end_plant(plant: subprocess.Popen, wait_s: float) -> None:
    """Wait for the plant to finish its run; terminate it, then kill it, if it does not."""
    try:
        plant.wait(timeout=wait_s)
        return
    except subprocess.TimeoutExpired:
        plant.terminate()
    try:
        plant.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        plant.kill()
        plant.wait(timeout=5.0)


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
    "safety_state",
    "transport_losses",
)


def _row(
    i: int,
    woke_ns: int,
    st: dict[str, Any] | None,
    bus: np.ndarray | None,
    torques: np.ndarray | None,
    report: StepReport | None,
    why: str | None,
    sent: bool,
) -> dict[str, Any]:
    nan = float("nan")
    row: dict[str, Any] = {
        "tick": i,
        "t": i * CONTROL_DT,
        "t_wake_ns": int(woke_ns),
        "state_valid": bool(st["valid"]) if st else False,
        "state_age_ms": float(st["age_ms"]) if st and st.get("age_ms") is not None else nan,
        "stepped": torques is not None,
        "sent": sent,
        "reason": why or "",
        "compute_ms": nan,
        "margin_ms": nan,
        "state_call_ms": nan,
        "set_call_ms": nan,
        "wake_late_ms": nan,
        "seq": -1,
        "fault": "",
        "iterations": int(report.iterations) if report is not None else -1,
        "status": int(report.status) if report is not None else -1,
        "fallback": bool(report.fallback) if report is not None else False,
        "primal_residual": float(report.primal_residual) if report is not None else nan,
        "dual_residual": float(report.dual_residual) if report is not None else nan,
    }
    for j, name in enumerate(BUS_FIELDS):
        row[f"bus_{name}"] = float(bus[j]) if bus is not None else nan
    for j, w in enumerate(WHEEL_NAMES):
        row[f"cmd_{w}"] = float(torques[j]) if torques is not None else nan
    row["clamped"] = ""
    row["bridge_mode"] = ""
    for w in WHEEL_NAMES:
        row[f"framed_{w}"] = nan
    return row
