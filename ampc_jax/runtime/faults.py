"""Injected faults for testing the safety chain: ``KIND@START:END`` (seconds).

Sensor faults (``ampc plant --fault``): ``silent`` (no state messages),
``frozen`` (the last frames repeated unchanged, alive counter included),
``corrupt`` (a payload bit flipped after the CRC). Controller faults (``ampc
run --fault``): ``nan`` (the step's torques replaced by NaN) and ``fail`` (the
step's status replaced by a failure). Times are of the manoeuvre (plant) or of
actuation (run), from its start.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CONTROLLER_FAULTS", "SENSOR_FAULTS", "Fault", "active_fault", "parse_fault"]

SENSOR_FAULTS = ("silent", "frozen", "corrupt")
CONTROLLER_FAULTS = ("nan", "fail")


@dataclass(frozen=True)
class Fault:
    """One injected fault: ``kind`` over ``start <= t < end`` (s)."""

    kind: str
    start: float
    end: float

    @property
    def text(self) -> str:
        return f"{self.kind}@{self.start:g}:{self.end:g}"


def parse_fault(text: str, kinds: tuple[str, ...]) -> Fault:
    """``"silent@3:4.5"`` -> Fault; ValueError naming what is wrong."""
    kind, sep, window = text.partition("@")
    start, sep2, end = window.partition(":")
    if kind not in kinds or not sep or not sep2:
        raise ValueError(f"expected KIND@START:END with KIND one of {kinds}, got {text!r}")
    try:
        a, b = float(start), float(end)
    except ValueError:
        raise ValueError(f"expected START and END in seconds, got {text!r}") from None
    if not 0.0 <= a < b:
        raise ValueError(f"expected 0 <= START < END, got {text!r}")
    return Fault(kind, a, b)


def active_fault(faults: tuple[Fault, ...], t: float) -> str | None:
    """The kind of the first fault active at ``t``, or None."""
    for f in faults:
        if f.start <= t < f.end:
            return f.kind
    return None
