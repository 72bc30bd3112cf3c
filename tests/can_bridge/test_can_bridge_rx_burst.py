"""The pace rule over the SLCAN pty: a frame may claim no more time than has
passed since the last believed frame plus one cycle, and frames faster than
their cycle are counted faults. An independent peer (python-can's slcan
interface, or raw SLCAN lines written to the pty; cantools and autosar-e2e
frame every message, ``ampc_jax.testing.can_rx_burst``) sends the bursts while the state is
sampled every half millisecond. The report's case failed on the bridge
before the rule: the speed was valid at > 80 m/s within 36 ms and
``rx_implausible_rate`` stayed 0."""

from __future__ import annotations

import math
import os
import time

import can
import pytest

import can_bridge
from ampc_jax.testing.can_fault_peers import open_raw_host
from ampc_jax.testing.can_peers import MOTION, WHEELS, send_sensors, state_message
from ampc_jax.testing.can_rx_burst import CYCLE, REPORT, Burst, play

pytestmark = pytest.mark.timeout(60)

V0 = MOTION["LongSpeed"]
RATE = 20.0  # LongSpeed's rx_max_rate, m/s^2


def _bridge() -> can_bridge.Bridge:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=50)
    bridge.start()
    return bridge


def _bus(bridge: can_bridge.Bridge) -> can.BusABC:
    return can.Bus(interface="slcan", channel=bridge.pty_path, sleep_after_open=0, bitrate=500000)


def _speed(bridge: can_bridge.Bridge):
    return lambda: (lambda s: (s["valid"], s["long_speed_mps"]))(bridge.latest_state())


def _run(b: Burst, cycles: int, *, raw: bool = False, one_write: bool = False):
    """Play ``b`` on a fresh bridge; (samples, burst start, stats, last state)."""
    bridge = _bridge()
    bus = fd = None
    try:
        if raw:
            fd = open_raw_host(bridge.pty_path)
        else:
            bus = _bus(bridge)
        samples, t_burst = play(bus, fd, b, cycles, _speed(bridge), one_write=one_write)
        return samples, t_burst, bridge.stats(), bridge.latest_state()
    finally:
        if bus is not None:
            bus.shutdown()
        if fd is not None:
            os.close(fd)
        bridge.stop()


def _faster_than_rate(samples, t_ref: float) -> list:
    """Samples whose believed speed moved from the sound one faster than 20
    m/s^2 over the real time since ``t_ref`` (a frame sent before the burst
    and believed by then), with the DBC's resolution as slack."""
    return [
        (t, v)
        for t, (_, v) in samples
        if v is not None and abs(v - V0) > RATE * max(0.0, t - t_ref) + 0.1
    ]


@pytest.mark.parametrize("how", ["python-can", "one write"])
def test_rx_the_reported_burst_is_never_believed(how: str) -> None:
    """90 VehicleMotion frames back to back (python-can), or in one write to
    the pty, each counter +2 and +0.8 m/s (12.34 -> 84.34 m/s), then the
    sender goes on at 84.34 m/s: no sample believes more than one frame of
    it, none is valid above 13.5 m/s, the frames are counted faster than
    their cycle and the later ones implausible."""
    b = Burst(**REPORT)
    samples, t_burst, stats, end = _run(b, 45, raw=how == "one write", one_write=True)
    assert not math.isnan(t_burst)
    assert any(valid for t, (valid, _) in samples if t < t_burst), "never valid before"
    believed = [v for _, (_, v) in samples if v is not None]
    assert max(believed) <= V0 + REPORT["delta"] + 0.01, max(believed)
    fast_valid = [(t, v) for t, (valid, v) in samples if valid and v > 13.5]
    assert not fast_valid, fast_valid[:5]
    assert stats["rx_faster_than_cycle"] >= 60, stats
    assert stats["rx_implausible_rate"] >= 5, stats
    assert not end["valid"] and end["status"]["VehicleMotion"] != "ok", end


@pytest.mark.parametrize(
    ("name", "burst"),
    [
        # each frame 0.35 m/s on, within the 0.4 m/s a 20 ms counter step allows
        ("counter +1, +0.35 m/s", Burst(n=90, step=1, delta=0.35)),
        ("counter +2, +0.75 m/s, 2 ms apart", Burst(n=40, step=2, delta=0.75, spacing=0.002)),
        ("counter +1, 10 ms apart", Burst(n=40, step=1, delta=0.35, spacing=0.01)),
        # after 150 ms of silence: the first frames claim time that passed
        ("after a 150 ms gap", Burst(n=30, step=1, delta=0.35, gap=0.15)),
    ],
)
def test_rx_no_burst_moves_the_speed_faster_than_real_time_allows(name: str, burst: Burst) -> None:
    """Bursts the report did not name: every believed speed (valid or not)
    stays within 20 m/s^2 of real time since the last frame believed before
    the burst, and the burst is counted."""
    samples, t_burst, stats, _ = _run(burst, 45)
    t_ref = burst.start - burst.gap - 3 * CYCLE
    bad = _faster_than_rate(samples, t_ref)
    assert not bad, (name, bad[:5], stats)
    assert stats["rx_faster_than_cycle"] >= 1, (name, stats)


def test_rx_a_burst_on_the_wheel_speeds_is_never_valid() -> None:
    """The rear wheels (driven: no bound from the vehicle speed) +2.5 rad/s a
    frame, 60 frames back to back, then sound again: no valid sample shows a
    rear wheel above one frame of the burst, and the burst is counted."""
    b = Burst(
        message="WheelSpeeds",
        signals=("WheelSpeedRL", "WheelSpeedRR"),
        n=60,
        step=1,
        delta=2.5,
        back=True,
    )
    bridge = _bridge()
    bus = _bus(bridge)
    try:

        def sample():
            s = bridge.latest_state()
            w = s["wheel_speeds_radps"]
            return s["valid"], None if w is None else w[2]

        samples, t_burst = play(bus, None, b, 40, sample)
        stats = bridge.stats()
        end = bridge.latest_state()
    finally:
        bus.shutdown()
        bridge.stop()
    w0 = WHEELS["WheelSpeedRL"]
    assert any(valid for t, (valid, _) in samples if t < t_burst)
    high = [(t, w) for t, (valid, w) in samples if valid and w > w0 + 2.6]
    assert not high, high[:5]
    assert stats["rx_faster_than_cycle"] >= 20, stats
    assert end["valid"], end  # sound again after a window


@pytest.mark.parametrize(("period", "faults"), [(CYCLE, False), (CYCLE / 2, True)])
def test_rx_frames_at_the_cycle_keep_pace_faster_ones_are_faults(
    period: float, faults: bool
) -> None:
    """VehicleMotion every 20 ms (the cycle) is never counted faster than its
    cycle and stays valid; every 10 ms (each frame counter +1) is counted and
    the state is invalid."""
    # (time, VehicleMotion's counter or None for the other four messages)
    events = [(k * CYCLE, None) for k in range(60)]
    events += [(j * period, j) for j in range(int(60 * CYCLE / period))]
    events.sort(key=lambda e: (e[0], e[1] is not None))
    bridge = _bridge()
    bus = _bus(bridge)
    counts = []
    try:
        t0 = time.monotonic()
        for t, c in events:
            time.sleep(max(0.0, t0 + t - time.monotonic()))
            if c is None:
                send_sensors(bus, round(t / CYCLE) % 15, skip=("VehicleMotion",))
            else:
                bus.send(state_message("VehicleMotion", MOTION, c % 15))
            if not counts and t >= 15 * CYCLE:
                counts.append(bridge.stats()["rx_faster_than_cycle"])
        time.sleep(0.03)
        counts.append(bridge.stats()["rx_faster_than_cycle"])
        end = bridge.latest_state()
    finally:
        bus.shutdown()
        bridge.stop()
    if faults:
        assert counts[-1] - counts[0] >= 15, counts
        assert not end["valid"], end
    else:
        # after the start (a sender catching up then may come early once)
        assert counts[-1] - counts[0] == 0, counts
        assert end["valid"], end
