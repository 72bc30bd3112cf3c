"""The safety chain over the bus: sensor faults at the plant and controller faults
at the runtime take the torque frames to hold and then safe within the bridge's
watchdog times, measured on the plant's clock, and they recover when the fault
clears; a latched fault recovers only after an explicit reset (SIGUSR1)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

import can_bridge
from ampc_jax.testing.budget import budget

# Two runs of 12 and 7 s over the pty: behind the slow marker, so that the
# default suite stays under 10 minutes on 2 cores (`pytest -m slow` runs them).
pytestmark = [pytest.mark.both_cores, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = "cruise_lane_change"
CFG = can_bridge.load_config()
HOLD = CFG["hold_after_ms"] * 1e-3
SAFE = CFG["safe_after_ms"] * 1e-3
FAULT = CFG["fault_after_ms"] * 1e-3
STATE_TIMEOUT = CFG["state_timeout_ms"] * 1e-3
TICK = 0.05
# What the runtime needs to see a fault: a silent sensor is invalid after
# state_timeout; a frozen (repeating) or corrupted one after rx_max_error_valid + 1
# bad frames of 20 ms; a controller fault at once.
DETECT = {"silent": STATE_TIMEOUT, "frozen": 0.1, "corrupt": 0.1, "nan": 0.0, "fail": 0.0}
# slack for the tick grid, the lead time and the pty (one control period and a bit)
SLACK = 0.08


def _run(out: Path, rt_args: list[str], *args: str, reset_at: float | None = None) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "ampc_jax.cli", "run", *rt_args, "--channel", "slcan-pty:"]
    cmd += ["--scenario", SCENARIO, "--with-plant", "--out", str(out), *args]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True, cwd=ROOT
    )
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:
        lines.append(line)
        if reset_at is not None and line.startswith("t ") and "sent" in line:
            if float(line.split()[1].split("/")[0]) >= reset_at:
                os.kill(proc.pid, signal.SIGUSR1)
                reset_at = None
    assert proc.wait(timeout=budget(60)) == 0, "".join(lines[-30:])
    frames = pq.read_table(out / "plant" / "frames.parquet").to_pydict()
    return {
        "run": json.loads((out / "run.json").read_text()),
        "t": np.asarray(frames["t"]),
        "mode": np.asarray(frames["mode"]),
        "ok": np.asarray(frames["ok"]),
        "T": np.stack([frames[f"T_{w}"] for w in ("FL", "FR", "RL", "RR")], axis=1),
    }


def _check_window(f: dict, kind: str, a: float, b: float, recover: float) -> None:
    t, mode, T = f["t"], f["mode"], f["T"]
    d = DETECT[kind]
    before = (t > a - 0.3) & (t < a)
    assert np.all(mode[before] == "active"), (kind, "not active before the fault")
    hold = np.flatnonzero((t >= a) & (mode == "hold"))
    safe = np.flatnonzero((t >= a) & (mode == "safe"))
    assert hold.size and safe.size, (kind, "no hold or no safe frame")
    t_hold, t_safe = t[hold[0]], t[safe[0]]
    # hold starts when the last command is hold_after old: never before the
    # fault is detectable, at most one tick (and the pty's slack) after
    assert a + HOLD - SLACK <= t_hold <= a + d + HOLD + TICK + SLACK, (kind, t_hold - a)
    assert a + SAFE - SLACK <= t_safe <= a + d + SAFE + TICK + SLACK, (kind, t_safe - a)
    # hold freezes the output; safe releases toward zero without a step up
    i0 = hold[0]
    j = i0
    while mode[j] == "hold":
        np.testing.assert_array_equal(T[j], T[i0 - 1])
        j += 1
    k = safe[0]
    while k + 1 < len(mode) and mode[k + 1] == "safe":
        assert np.all(np.abs(T[k + 1]) <= np.abs(T[k])), (kind, T[k], T[k + 1])
        k += 1
    # no active frame while the fault lasts (after detection), active again after it
    # (a frame landing on the fault's end itself may be either: half a tick apart)
    during = (t > a + d + TICK + SLACK) & (t < b - TICK / 2)
    assert not np.any(mode[during] == "active"), (kind, "active during the fault")
    after = np.flatnonzero((t > b) & (mode == "active"))
    assert after.size and t[after[0]] <= b + recover, (kind, "no recovery")


@pytest.mark.timeout(300)
def test_sensor_and_controller_faults_hold_then_safe_then_recover(tmp_path: Path, rt_args) -> None:
    windows = [
        ("silent", 1.5, 2.5),
        ("frozen", 3.5, 4.5),
        ("corrupt", 5.5, 6.5),
        ("nan", 7.5, 8.3),
        ("fail", 9.5, 10.3),
    ]
    args = ["--duration", "11.5", "--quiet"]
    for kind, a, b in windows:
        flag = "--plant-fault" if kind in ("silent", "frozen", "corrupt") else "--fault"
        args += [flag, f"{kind}@{a}:{b}"]
    f = _run(tmp_path, rt_args, *args)
    reasons = f["run"]["skipped"]
    assert reasons.get("state", 0) > 0 and reasons.get("step", 0) > 0, reasons
    # the plant corrupts what it sends; every torque frame it receives is sound
    assert f["ok"].all()
    for kind, a, b in windows:
        # a sensor recovers once its window of 16 frames is clean again (0.32 s)
        recover = 0.6 if kind in ("frozen", "corrupt") else 0.3
        _check_window(f, kind, a, b, recover + STATE_TIMEOUT)


@pytest.mark.timeout(300)
def test_a_latched_fault_recovers_only_after_an_explicit_reset(tmp_path: Path, rt_args) -> None:
    a, b, reset = 1.0, 1.0 + FAULT + 0.8, 1.0 + FAULT + 2.0
    f = _run(
        tmp_path,
        rt_args,
        "--duration",
        f"{reset + 1.5:g}",
        "--plant-fault",
        f"silent@{a}:{b}",
        reset_at=reset,
    )
    t, mode = f["t"], f["mode"]
    t_fault = t[np.flatnonzero((t > a) & (mode == "fault"))[0]]
    # latched once the last command (sent until the state went invalid) is fault_after old
    assert a + FAULT - SLACK <= t_fault <= a + STATE_TIMEOUT + FAULT + TICK + SLACK
    resets = f["run"]["resets_t"]
    assert len(resets) == 1
    # the sensor is back at b, commands flow again, but the bridge stays latched
    latched = (t > b + 0.5) & (t < resets[0])
    assert latched.any() and np.all(mode[latched] == "fault")
    after = np.flatnonzero((t > resets[0]) & (mode == "active"))
    assert after.size and t[after[0]] <= resets[0] + 0.3
