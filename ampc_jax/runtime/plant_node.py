"""``ampc plant``: the simulated vehicle on the other end of the bus, in real time.

A separate process that integrates the nonlinear plant
(:func:`~ampc_jax.vehicle.plant.plant_step`) with the scenario's driver on its
own clock (``time.monotonic``), publishes the five state messages every 20 ms
(their DBC cycle time) with AUTOSAR E2E Profile 1 protection, and applies the
wheel-torque frames it receives. It talks CAN through python-can (the slcan
interface on the bridge's pseudo-terminal) and frames with cantools and the
``autosar-e2e`` package, never through can_bridge: the two ends of the bus are
independent implementations, so each checks the other.

The torque it applies: that of the last frame that passed its checks (CRC by
autosar-e2e, alive counter in sequence, every torque within the DBC's range),
whatever the frame's mode (in ``safe`` and ``fault`` the bridge releases the
torque toward zero itself); zero once no such frame has arrived for
``cmd_timeout_ms`` (silence is a fault: never a stale torque). The manoeuvre's
clock starts at the first ``active`` frame, so the driver and the controller
start together, as in :func:`~ampc_jax.closed_loop.simulate`.

Fault injection (tests of the safety chain): ``silent`` (send nothing),
``frozen`` (repeat the last frames unchanged, counter included) and ``corrupt``
(flip a payload bit after the CRC), each over a window of the manoeuvre's time.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..vehicle.actuators import ACTUATORS
from ..vehicle.manoeuvres import (
    DriverParams,
    driver_step,
    initial_driver_state,
    initial_plant_state,
)
from ..vehicle.manoeuvres import scenario as scenario_spec
from ..vehicle.params import CONTROL_DT, VehicleParams
from ..vehicle.plant import plant_step
from .faults import Fault, active_fault
from .files import named
from .signals import MESSAGES, bus_vector, message_values

__all__ = ["PLANT_TICK_S", "PlantNode", "PlantReport", "write_report"]

PLANT_TICK_S = 0.005
"""The plant's real-time step (s): received frames are applied at this grain."""

MODES = {0: "active", 1: "hold", 2: "safe", 3: "fault"}


class _Receiver(threading.Thread):
    """Reads the bus in a thread of its own, stamping each frame on arrival.

    Rule: frames are stamped where they are read, not where the plant's tick
    drains them; reason: the period statistics on the plant's clock must not
    carry the tick's 5 ms grain."""

    def __init__(self, bus: Any) -> None:
        super().__init__(name="plant-rx", daemon=True)
        self.bus = bus
        self.frames: queue.SimpleQueue[tuple[float, Any]] = queue.SimpleQueue()
        self.lost = False
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                m = self.bus.recv(timeout=0.02)
            except Exception:  # noqa: BLE001 -- python-can/pyserial raise several kinds on a lost pty
                self.lost = True
                return
            if m is not None:
                self.frames.put((time.monotonic(), m))

    def halt(self) -> None:
        self._halt.set()
        self.join(timeout=1.0)

    def drain(self) -> list[tuple[float, Any]]:
        out = []
        while True:
            try:
                out.append(self.frames.get_nowait())
            except queue.Empty:
                return out


class _CandumpLog:
    """The plant's candump log (python-can's writer); an I/O error names the file."""

    def __init__(self, path: Path) -> None:
        import can

        self.path = path
        with named(path, "create"):
            self._w = can.CanutilsLogWriter(path, channel="plant")

    def on_message_received(self, msg: Any) -> None:
        with named(self.path, "write"):
            self._w.on_message_received(msg)

    def stop(self) -> None:
        with named(self.path, "write"):
            self._w.stop()


def _db() -> Any:
    import cantools

    import can_bridge

    return cantools.database.load_file(can_bridge.dbc_path())


@dataclass
class PlantReport:
    """What the plant saw: its trajectory, the torque frames and the checks."""

    rows: list[dict[str, Any]] = field(default_factory=list)  # every 50 ms of plant time
    frames: list[dict[str, Any]] = field(default_factory=list)  # every torque frame received
    summary: dict[str, Any] = field(default_factory=dict)


class PlantNode:
    """The plant process's state and loop (see the module docstring).

    Parameters
    ----------
    channel : python-can channel of the slcan interface (a pty slave path, or
        ``slcan:PATH``).
    scenario : a registered scenario's name.
    duration : manoeuvre time to run (s; default the scenario's).
    cmd_timeout_ms : silence after which the plant applies zero torque (default
        ``ACTUATORS.timeout_ms``, 200: the actuator contract the bridge's ramp
        restart is derived from).
    start_timeout_s : longest wait for the first active frame (default 60).
    faults : injected sensor faults (:class:`~ampc_jax.runtime.faults.Fault`).
    log_path : the candump log of the bus as the plant sees it (None: no log).
    repeat : when the manoeuvre ends before ``duration``, start it again from
        its initial state (vehicle and driver reset; for long timing runs).
    """

    def __init__(
        self,
        channel: str,
        scenario: str,
        duration: float | None = None,
        *,
        cmd_timeout_ms: float = ACTUATORS.timeout_ms,
        start_timeout_s: float = 60.0,
        faults: tuple[Fault, ...] = (),
        log_path: Path | None = None,
        repeat: bool = False,
    ) -> None:
        path = channel.removeprefix("slcan:")
        path, _, baud = path.rpartition("@") if "@" in path else (path, "", "")
        if baud and not baud.isdigit():
            raise ValueError(f"channel: expected slcan:PATH[@BAUD], got {channel!r}")
        self.channel, self.baud = path, int(baud) if baud else 115200
        self.spec = scenario_spec(scenario)
        self.duration = float(self.spec.duration if duration is None else duration)
        self.cmd_timeout = cmd_timeout_ms * 1e-3
        self.start_timeout = start_timeout_s
        self.faults = faults
        self.log_path = log_path
        self.repeat = repeat
        self.lap = int(round(self.spec.duration / PLANT_TICK_S))  # plant ticks per manoeuvre
        self.db = _db()
        self.cmd = self.db.get_message_by_name("WheelTorqueCmd")
        self.data_ids = {m.name: int(m.dbc.attributes["E2EDataID"].value) for m in self.db.messages}
        # the state messages go out at their DBC cycle time (all 20 ms)
        cycles = {int(self.db.get_message_by_name(n).cycle_time or 0) for n in MESSAGES}
        tick_ms = round(1e3 * PLANT_TICK_S)
        if len(cycles) != 1 or next(iter(cycles)) % tick_ms or not next(iter(cycles)):
            raise ValueError(f"the DBC's state messages need one cycle time, got {sorted(cycles)}")
        self.publish_every = cycles.pop() // tick_ms
        self._stop = False

    # -- compiled pieces -------------------------------------------------------------
    def _compile(self) -> None:
        vp, dp = VehicleParams(), DriverParams()
        n_sub = int(round(PLANT_TICK_S / 1e-3))
        sc = jax.tree.map(jnp.asarray, self.spec.scenario)
        self._plant = jax.jit(
            lambda ps, steer, T, mu: plant_step(ps, steer, T, mu, vp, PLANT_TICK_S, n_sub)
        )
        self._driver = jax.jit(lambda ds, ps, t: driver_step(ds, ps, t, sc, dp))
        self.ps = self.ps0 = initial_plant_state(sc, vp, jnp.float64)
        self.ds = self.ds0 = initial_driver_state(jnp.float64)
        self.mu = sc.mu
        # trace and compile both before the clock starts
        jax.block_until_ready(self._plant(self.ps, 0.0, jnp.zeros(4), self.mu))
        jax.block_until_ready(self._driver(self.ds, self.ps, 0.0))

    # -- framing -----------------------------------------------------------------------
    def _encode(self, name: str, values: dict[str, float], counter: int) -> bytes:
        import e2e.p01

        msg = self.db.get_message_by_name(name)
        vals = {}
        for sig, v in values.items():  # a value beyond the DBC range is sent at its bound
            s = msg.get_signal_by_name(sig)
            vals[sig] = float(np.clip(v, s.minimum, s.maximum))
        data = bytearray(msg.encode({"CRC": 0, "Counter": counter, **vals}))
        e2e.p01.e2e_p01_protect(data, self.data_ids[name], increment_counter=False)
        return bytes(data)

    def _check_cmd(self, data: bytes, prev_counter: int | None) -> tuple[dict[str, Any], str]:
        """Decode and check a torque frame: (values, "" if usable else why not)."""
        import e2e.p01

        if len(data) != self.cmd.length:
            return {}, f"length {len(data)}"
        if not e2e.p01.e2e_p01_check(bytearray(data), self.data_ids["WheelTorqueCmd"]):
            return {}, "crc"
        counter = data[1] & 0x0F
        vals = self.cmd.decode(bytes(data), decode_choices=False)
        vals["counter"] = counter
        if counter > 14:
            return vals, "counter 15"
        if prev_counter is not None:
            step = (counter - prev_counter) % 15
            if step == 0:
                return vals, "repeated counter"
            if step > 3:
                return vals, f"counter jumped by {step}"
        names = ("TorqueFL", "TorqueFR", "TorqueRL", "TorqueRR")
        for k, lim in zip(names, ACTUATORS.wheels, strict=True):
            if not lim.min_nm <= vals[k] <= lim.max_nm:  # the actuator's range, not only the DBC's
                return vals, f"{k} = {vals[k]:g} Nm outside [{lim.min_nm:g}, {lim.max_nm:g}]"
        return vals, ""

    # -- the loop ----------------------------------------------------------------------
    def stop(self, *_: Any) -> None:
        self._stop = True

    def run(self, progress: Any = None) -> PlantReport:
        """Open the bus, wait for the controller, run the manoeuvre; returns the report."""
        import can

        self._compile()
        rep = PlantReport()
        signal.signal(signal.SIGTERM, self.stop)
        bus = can.Bus(
            interface="slcan",
            channel=self.channel,
            ttyBaudrate=self.baud,
            sleep_after_open=0,
            bitrate=500000,
        )
        parent = os.getppid()
        logger = _CandumpLog(self.log_path) if self.log_path else None
        counters = dict.fromkeys(self.data_ids, 0)
        last_frames: dict[str, bytes] = {}
        prev_counter: int | None = None
        torques = np.zeros(4)
        last_ok: float | None = None
        steer = T_drv = 0.0
        v_ref = float(self.spec.scenario.speed_v[0])
        started: float | None = None
        wall0 = time.monotonic()
        k = 0  # plant ticks since the manoeuvre started
        n_ticks = int(round(self.duration / PLANT_TICK_S))
        per_control = int(round(CONTROL_DT / PLANT_TICK_S))
        late = []
        timeouts = 0
        catch_up = 0  # plant ticks run late to keep the plant on the wall clock
        n_pub = 0  # state publications so far (a 20 ms grid from wall0)
        next_t = wall0
        bus_lost = False
        rx = _Receiver(bus)
        rx.start()
        try:
            while not self._stop and k < n_ticks:
                next_t += PLANT_TICK_S
                now = time.monotonic()
                # the manoeuvre's clock is the wall clock since the first active frame
                t_man = 0.0 if started is None else now - started
                # 1. received torque frames (a bus that fails is silence: zero torque)
                bus_lost |= rx.lost
                for arrival, m in rx.drain():
                    if logger is not None:
                        logger.on_message_received(m)
                    if m.arbitration_id != self.cmd.frame_id or m.is_extended_id:
                        continue
                    vals, why = self._check_cmd(bytes(m.data), prev_counter)
                    if vals.get("counter", 15) <= 14:  # CRC good: the counter re-anchors
                        prev_counter = vals["counter"]
                    mode = MODES.get(int(vals.get("Mode", -1)), "?") if vals else "?"
                    tq = [float(vals.get(f"Torque{w}", np.nan)) for w in ("FL", "FR", "RL", "RR")]
                    rep.frames.append(
                        {
                            "t_plant": arrival - wall0,
                            "t": 0.0 if started is None else arrival - started,
                            "mode": mode,
                            "ok": why == "",
                            "why": why,
                            "counter": int(vals.get("counter", -1)),
                            **{
                                f"T_{w}": x
                                for w, x in zip(("FL", "FR", "RL", "RR"), tq, strict=True)
                            },
                        }
                    )
                    if why == "":
                        torques = np.asarray(tq)
                        last_ok = arrival
                        if started is None and mode == "active":
                            started = arrival
                if started is None:
                    if os.getppid() != parent:  # the runtime that started us is gone
                        raise TimeoutError("the parent process exited before actuation started")
                    if now - wall0 > self.start_timeout:
                        raise TimeoutError(
                            f"no active torque frame within {self.start_timeout:g} s"
                        )
                silent = last_ok is None or now - last_ok > self.cmd_timeout
                if silent and started is not None:
                    timeouts += 1
                applied = np.zeros(4) if silent else torques
                # 2. driver every control period, plant every tick (after the start);
                # a process that fell behind catches up, so plant time stays wall time
                if started is not None:
                    k_target = min(n_ticks, int((now - started) / PLANT_TICK_S) + 1)
                    catch_up += max(0, k_target - k - 1)
                    while k < k_target:
                        if self.repeat and k > 0 and k % self.lap == 0:
                            self.ps, self.ds = self.ps0, self.ds0  # the next lap
                        t_k = (k % self.lap if self.repeat else k) * PLANT_TICK_S
                        if k % per_control == 0:
                            self.ds, st, td, vr = self._driver(self.ds, self.ps, t_k)
                            steer, T_drv, v_ref = float(st), float(td), float(vr)
                            rep.rows.append(
                                self._row(t_k, steer, T_drv, v_ref, applied, now - wall0)
                            )
                        self.ps = self._plant(self.ps, steer, jnp.asarray(applied), self.mu)
                        k += 1
                # 3. state messages on a 20 ms grid of the wall clock
                due = int((now - wall0) / (self.publish_every * PLANT_TICK_S))
                if due >= n_pub:
                    n_pub = due + 1
                    if not bus_lost:
                        bus_lost = not self._publish(
                            bus, logger, counters, last_frames, steer, T_drv, v_ref, t_man
                        )
                if progress is not None and started is not None and k % 100 == 0:
                    progress(k * PLANT_TICK_S)
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    late.append(-delay)
                    if -delay > PLANT_TICK_S:  # fell behind: restart the grid, count it
                        next_t = time.monotonic()
        finally:
            rx.halt()
            try:
                bus.shutdown()
            except Exception:  # noqa: BLE001 -- closing a pty whose other end is gone
                pass
            if logger is not None:
                logger.stop()
        rep.summary = self._summary(rep, late, timeouts, started is not None)
        rep.summary["catch_up_ticks"] = catch_up
        rep.summary["bus_lost"] = bus_lost
        return rep

    def _row(self, t, steer, T_drv, v_ref, applied, wall) -> dict[str, Any]:
        ps = self.ps
        om = np.asarray(ps.omega)
        row = {
            "t": t,
            "t_plant": wall,
            "X": float(ps.X),
            "Y": float(ps.Y),
            "psi": float(ps.psi),
            "v_x": float(ps.v_x),
            "v_y": float(ps.v_y),
            "yaw_rate": float(ps.r),
            "steer": steer,
            "driver_torque": T_drv,
            "v_ref": v_ref,
        }
        row.update(
            {f"omega_{w}": float(x) for w, x in zip(("FL", "FR", "RL", "RR"), om, strict=True)}
        )
        row.update(
            {f"T_{w}": float(x) for w, x in zip(("FL", "FR", "RL", "RR"), applied, strict=True)}
        )
        return row

    def _publish(self, bus, logger, counters, last_frames, steer, T_drv, v_ref, t_man) -> bool:
        """Send the state messages; False once the bus fails."""
        import can

        fault = active_fault(self.faults, t_man)
        if fault == "silent":
            return True
        vec = bus_vector(self.ps, steer, T_drv, v_ref, float(self.mu))
        for name, values in message_values(vec).items():
            if fault == "frozen" and name in last_frames:
                data = last_frames[name]
            else:
                data = self._encode(name, values, counters[name])
                counters[name] = (counters[name] + 1) % 15
                last_frames[name] = data
            if fault == "corrupt":
                data = bytes([data[0], data[1], data[2] ^ 0x01, *data[3:]])
            msg = can.Message(
                arbitration_id=self.db.get_message_by_name(name).frame_id,
                is_extended_id=False,
                data=data,
                timestamp=time.time(),
            )
            try:
                bus.send(msg)
            except Exception:  # noqa: BLE001 -- the pty's other end is gone
                return False
            if logger is not None:
                logger.on_message_received(msg)
        return True

    def _summary(self, rep: PlantReport, late: list[float], timeouts: int, started: bool):
        # the period of the steady stream: frames of a running command (active or
        # hold), not the start-up latch or the stop sequence, each stamped on
        # arrival by the receive thread (the receiving side's period, which
        # `ampc run --with-plant` reports beside its own)
        t = np.array([f["t_plant"] for f in rep.frames if f["mode"] in ("active", "hold")])
        periods = np.diff(t) * 1e3 if t.size > 1 else np.zeros(0)
        q = lambda a, p: float(np.percentile(a, p)) if a.size else None  # noqa: E731
        dev = np.abs(periods - 1e3 * CONTROL_DT)
        return {
            "scenario": self.spec.name,
            "started": started,
            "duration_s": self.duration,
            "frames": len(rep.frames),
            "frames_bad": int(sum(not f["ok"] for f in rep.frames)),
            "modes": {m: int(sum(f["mode"] == m for f in rep.frames)) for m in MODES.values()},
            "period_ms_median": q(periods, 50),
            "period_ms_p01": q(periods, 1),
            "period_ms_p99": q(periods, 99),
            "period_dev_ms_p50": q(dev, 50),
            "period_dev_ms_p99": q(dev, 99),
            "period_dev_ms_max": float(dev.max()) if dev.size else None,
            "timeout_ticks": timeouts,
            "plant_late_ticks": len(late),
            "plant_late_ms_max": 1e3 * max(late) if late else 0.0,
            "faults": [f.text for f in self.faults],
        }


def write_report(rep: PlantReport, out: Path) -> None:
    """``plant.parquet``, ``frames.parquet`` and ``plant.json`` in ``out``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    with named(out, "create the directory"):
        out.mkdir(parents=True, exist_ok=True)
    for name, rows in (("plant", rep.rows), ("frames", rep.frames)):
        if rows:
            cols = {k: [r[k] for r in rows] for k in rows[0]}
        else:
            cols = {"t": []}
        with named(out / f"{name}.parquet"):
            pq.write_table(pa.table(cols), out / f"{name}.parquet")
    with named(out / "plant.json"):
        (out / "plant.json").write_text(json.dumps(rep.summary, indent=1))
