"""The simulated limiter (vehicle.actuators.bridge_actuators) against the real
bridge: frames read back over a pseudo-terminal with python-can and decoded
with cantools follow it step for step."""

from __future__ import annotations

import time

import cantools
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import can_bridge
from ampc_jax.vehicle.actuators import ACTUATORS, bridge_actuators, bridge_kwargs

pytestmark = [pytest.mark.timeout(60), pytest.mark.both_cores]


def test_frames_on_the_wire_follow_the_simulated_limiter() -> None:
    import can

    limits = ACTUATORS._replace(period_ms=20.0)  # 200 Nm rise, 400 Nm release per tick
    db = cantools.database.load_file(can_bridge.dbc_path())
    msg = db.get_message_by_name("WheelTorqueCmd")
    targets = [
        [-700.0, -1999.0, 1203.0, -901.0],
        [0.0, -300.0, -1500.0, 2500.0],  # RR beyond its range: clamped
        [-2000.0, 0.0, 700.0, -2000.0],
        [-50.0, -51.0, 3.0, -3.0],  # half steps: round half to even
    ]
    bridge = can_bridge.Bridge("slcan-pty:", **bridge_kwargs(limits))
    bridge.start()
    bus = can.Bus(interface="slcan", channel=bridge.pty_path, sleep_after_open=0, bitrate=500000)
    frames: list[tuple[float, list[float], str]] = []
    changes: list[float] = []
    seq = 0
    try:
        for target in targets:
            changes.append(time.monotonic())
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                seq += 1
                bridge.set_command(target, seq)
                t_stop = time.monotonic() + 0.03
                while time.monotonic() < t_stop:
                    m = bus.recv(timeout=0.01)
                    if m is not None and m.arbitration_id == msg.frame_id:
                        v = msg.decode(bytes(m.data), decode_choices=False)
                        T = [v[f"Torque{w}"] for w in ("FL", "FR", "RL", "RR")]
                        frames.append((time.monotonic(), T, int(v["Mode"])))
    finally:
        bus.shutdown()
        bridge.stop()
    f = jax.jit(lambda p, t: bridge_actuators(p, t, limits))
    checked = 0
    for (_, T1, _), (t2, T2, mode) in zip(frames, frames[1:], strict=False):
        if mode != 0:  # only active frames follow a command
            continue
        prev = jnp.asarray(np.round(np.asarray(T1) / 2).astype(np.int32))
        # the target in force at that tick: the last change before the frame
        # (or the one before it, for the tick right at a change)
        k = max(i for i, c in enumerate(changes) if c <= t2)
        cands = [targets[k]] + ([targets[k - 1]] if k > 0 else [])
        outs = [np.asarray(f(prev, jnp.asarray(c))[1]).tolist() for c in cands]
        assert T2 in outs, (T1, T2, cands, outs)
        checked += 1
    assert checked > 60
    # every target was reached in the end (on the grid, within the range)
    assert frames[-1][1] == [-50.0, -52.0, 4.0, -4.0]
