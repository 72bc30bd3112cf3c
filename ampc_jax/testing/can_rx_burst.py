"""A sender that bursts: the peer side of the pace rule's tests
(``test_can_bridge_rx_burst.py``) and of the burst case of
``bench/bench_can_bridge_faults.py``. Frames are framed by cantools and
``autosar-e2e`` (``ampc_jax.testing.can_peers.state_message``), never by the bridge.

A burst is ``n`` frames of one message sent back to back (or ``spacing`` s
apart), each with the alive counter ``step`` ahead of the one before and a
payload signal ``delta`` further on: each frame on its own is within the
signal's rate limit for the time its counter step claims (``step`` x 20 ms),
so only the time that actually passed can tell the burst from a sound
stream. The rule it checks (``docs/bus-safety.md``, "In: what is believed"):
a frame may claim no more time than has passed since the last believed
frame plus one cycle; frames faster than their cycle are counted faults
(``stats()["rx_faster_than_cycle"]``).

``Burst.motion`` plays the report's case in the bench's ``_sensor_case``
(``motion(k)`` -> the VehicleMotion frames of cycle ``k``); ``schedule``
gives every frame of every message for this module's own player, ``play``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import can

from .can_peers import SENSORS, send_sensors, state_message

CYCLE = 0.02  # the received messages' cycle (the DBC's GenMsgCycleTime)

# The burst of the report: 90 VehicleMotion frames within 11 ms, counter +2,
# speed +0.8 m/s each (12.34 -> 84.34 m/s).
REPORT = {"n": 90, "step": 2, "delta": 0.8}


@dataclass(frozen=True)
class Burst:
    """One sender's burst on ``message``: after ``before`` sound cycles (and
    ``gap`` s of silence on that message), ``n`` frames ``spacing`` s apart
    with the counter ``step`` and each of ``signals`` ``delta`` further on;
    then the sender goes on every cycle, counter +1, at the burst's last
    values (``back=False``) or its sound ones (``back=True``). The other
    messages stay sound throughout."""

    message: str = "VehicleMotion"
    signals: tuple[str, ...] = ("LongSpeed",)
    n: int = 90
    step: int = 2
    delta: float = 0.8
    spacing: float = 0.0
    before: int = 15
    gap: float = 0.0
    back: bool = False

    def base(self) -> dict[str, float]:
        return dict(dict(SENSORS)[self.message])

    def values(self, j: int) -> dict[str, float]:
        """The burst's ``j``-th frame's values (``j`` = 0: the sound ones)."""
        v = self.base()
        for s in self.signals:
            v[s] += self.delta * j
        return v

    @property
    def start(self) -> float:
        """When the burst starts, s after the first cycle."""
        return (self.before - 1) * CYCLE + 0.001 + self.gap

    @property
    def end(self) -> float:
        return self.start + self.n * self.spacing

    def frames(self, cycles: int) -> list[tuple[float, dict[str, float], int, bool]]:
        """The bursting message's frames: (time, values, counter, in the
        burst), ``cycles`` cycles in all."""
        out = [(k * CYCLE, self.base(), k, False) for k in range(self.before)]
        c = self.before - 1
        for j in range(1, self.n + 1):
            c += self.step
            out.append((self.start + (j - 1) * self.spacing, self.values(j), c, True))
        after = self.base() if self.back else self.values(self.n)
        k = 1
        while self.end + k * CYCLE < cycles * CYCLE:
            c += 1
            out.append((self.end + k * CYCLE, after, c, False))
            k += 1
        return out

    def motion(self, k0: int = 20) -> Callable[[int], list[tuple[float, dict[str, float], int]]]:
        """For the bench's ``_sensor_case(motion)``: the VehicleMotion frames
        of cycle ``k`` as (time after the cycle's start, values, counter),
        the burst 1 ms after cycle ``k0``'s frame (``before`` is ignored)."""
        assert self.message == "VehicleMotion" and self.gap == 0.0
        b = Burst(**{**self.__dict__, "before": k0 + 1})
        frames = b.frames(k0 + 200)

        def motion(k: int) -> list[tuple[float, dict[str, float], int]]:
            lo, hi = k * CYCLE, (k + 1) * CYCLE
            return [(t - lo, v, c) for t, v, c, _ in frames if lo <= t < hi]

        return motion


def schedule(b: Burst, cycles: int) -> list[tuple[float, str, dict[str, float] | None, int, bool]]:
    """Every frame to send: (time, message, values, counter, in the burst),
    in time order; the other messages' sound frames as (time, "rest", None,
    counter, False)."""
    ev = [(t, b.message, v, c, burst) for t, v, c, burst in b.frames(cycles)]
    ev += [(k * CYCLE, "rest", None, k, False) for k in range(cycles)]
    ev.sort(key=lambda e: e[0])
    return ev


def line(name: str, values: dict[str, float], counter: int) -> bytes:
    """One SLCAN ``t`` line of ``name``, framed by cantools and autosar-e2e."""
    m = state_message(name, values, counter)
    return f"t{m.arbitration_id:03X}{len(m.data)}{bytes(m.data).hex().upper()}\r".encode()


def play(
    bus: can.BusABC | None,
    fd: int | None,
    b: Burst,
    cycles: int,
    sample: Callable[[], tuple],
    *,
    one_write: bool = False,
) -> tuple[list[tuple[float, tuple]], float]:
    """Send ``schedule(b, cycles)`` in real time through python-can (``bus``)
    or as raw SLCAN lines written to the pty (``fd``; ``one_write``: the
    whole burst in one write), sampling ``sample()`` every half millisecond
    meanwhile. Returns the samples as (time since the start, sample) and the
    time the burst was actually sent, both on ``time.monotonic()``."""
    events = schedule(b, cycles)
    done = threading.Event()
    sent_at: list[float] = []
    t0 = time.monotonic()

    def send(name: str, values, c: int) -> None:
        if name == "rest":
            if bus is not None:
                send_sensors(bus, c % 15, skip=(b.message,))
            else:
                os.write(
                    fd,
                    b"".join(line(n, v, c % 15) for n, v in SENSORS if n != b.message),
                )
        elif bus is not None:
            bus.send(state_message(name, values, c % 15))
        else:
            os.write(fd, line(name, values, c % 15))

    def run() -> None:
        i = 0
        while i < len(events):
            t, name, values, c, burst = events[i]
            time.sleep(max(0.0, t0 + t - time.monotonic()))
            if burst and not sent_at:
                sent_at.append(time.monotonic() - t0)
            if burst and one_write and fd is not None:
                j = i
                while j < len(events) and events[j][4]:
                    j += 1
                os.write(fd, b"".join(line(b.message, e[2], e[3] % 15) for e in events[i:j]))
                i = j
                continue
            send(name, values, c)
            i += 1
        done.set()

    player = threading.Thread(target=run, daemon=True)
    player.start()
    samples = []
    while not done.is_set():
        samples.append((time.monotonic() - t0, sample()))
        time.sleep(0.0005)
    player.join(5)
    time.sleep(0.05)
    samples.append((time.monotonic() - t0, sample()))
    return samples, (sent_at[0] if sent_at else float("nan"))
