"""A sweep's memory, estimated before it runs and compared with what the machine has.

Rule: a sweep whose call of the compiled program, chunk of rows or joined
table would not fit in the memory available is refused before anything runs,
naming the flag to change (``--rho``, ``--chunk``, ``--cases``) and the
estimate; reason: 10^7 rho points ran into XLA's ``RESOURCE_EXHAUSTED``
(184 GB) and ``--chunk 10**9`` padded a chunk to 10^9 cases (72 GB) before
(``tests/sweep/test_sweep_run.py``). The per-pair and per-row figures are
measured peaks with a margin; on an accelerator a call is compared with the
devices' free memory, the rows with the host's.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..problem.limits import available_memory, format_bytes, format_count

__all__ = [
    "LOOP_PAIR_BYTES",
    "MIN_PAIR_BYTES",
    "ROW_BYTES",
    "STEP_PAIR_FACTOR",
    "check_memory",
    "check_points",
    "device_free",
]

STEP_PAIR_FACTOR = 32
"""Bytes a single-step pair needs in a call, per byte of its case's data
(problem data, float64). Measured peak growth: 20 KB per pair on cruise_step
(976 B of data) and 21 KB on generated (1,992 B), 256 cases x 4 to 32 points."""

LOOP_PAIR_BYTES = 1_000_000
"""Bytes a closed-loop pair needs in a call (measured 0.39 MB per pair on
cruise_lane_change, 8 to 64 pairs; the runs keep reductions, not trajectories)."""

ROW_BYTES = 512
"""Bytes of one table row in memory (measured 154 to 218 B in Arrow)."""

MIN_PAIR_BYTES = 16_000
"""The fewest bytes any family's pair needs (below every measurement above):
the grid's bound before any case is drawn (:func:`check_points`)."""


def check_points(n: int, available: int | None = None) -> None:
    """ValueError (no field name: the caller's flag) when ``n`` grid points, all of
    which a call holds for at least one case, cannot fit at :data:`MIN_PAIR_BYTES`."""
    avail = available_memory() if available is None else available
    need = n * MIN_PAIR_BYTES
    if avail is not None and need > avail:
        raise ValueError(
            f"{format_count(n)} points: every call of the program holds all points of at least one "
            f"case, at least {format_bytes(need)} at {MIN_PAIR_BYTES // 1000} kB per "
            f"case-point pair, more than the {format_bytes(avail)} this machine has "
            "available; use fewer points"
        )


def device_free(devs: Sequence[Any]) -> int | None:
    """The least free memory of the accelerators ``devs`` (None on CPU, or when a
    device does not say)."""
    if not devs or devs[0].platform == "cpu":
        return None
    free = []
    for d in devs:
        try:
            st = d.memory_stats() or {}
        except Exception:  # noqa: BLE001 -- a backend without memory statistics
            return None
        if "bytes_limit" not in st:
            return None
        free.append(int(st["bytes_limit"]) - int(st.get("bytes_in_use", 0)))
    return min(free)


def check_memory(
    *,
    cases: int,
    points: int,
    chunk: int,
    call_cases: int,
    kind: str,
    case_bytes: int,
    devs: Sequence[Any],
    available: int | None = None,
) -> dict[str, int]:
    """The estimates (bytes) of a call, a chunk's rows and the joined table;
    ValueError ``rho:``, ``chunk:`` or ``cases:`` when one does not fit.

    A call holds ``call_cases`` x ``points`` pairs (:data:`STEP_PAIR_FACTOR` x
    ``case_bytes`` each, :data:`LOOP_PAIR_BYTES` for ``kind="loop"``), a chunk
    ``chunk`` x ``points`` rows until written, the join every row twice (read
    and sorted; :data:`ROW_BYTES`). ``available``: the host's bytes (default
    :func:`~ampc_jax.problem.limits.available_memory`).
    """
    n_dev = len(devs)
    pair = LOOP_PAIR_BYTES if kind == "loop" else STEP_PAIR_FACTOR * int(case_bytes)
    call = call_cases * points * pair
    rows = chunk * points * ROW_BYTES
    table = 2 * cases * points * ROW_BYTES
    est = {"call": call, "chunk_rows": rows, "table": table, "cases_per_call": call_cases}
    dev = device_free(devs)
    if dev is not None and call / n_dev > dev:
        raise ValueError(
            f"rho: one call of the program holds {call_cases} case(s) x {points:,} points, "
            f"about {format_bytes(call / n_dev)} per device, more than the "
            f"{format_bytes(dev)} free on a device; use fewer points"
        )
    host = available_memory() if available is None else available
    if host is None:
        return est
    on_host = call if dev is None else 0
    if on_host > host or (on_host + rows > host and call_cases <= n_dev):
        raise ValueError(
            f"rho: one call of the program holds {call_cases} case(s) x {points:,} points, "
            f"about {format_bytes(on_host)} ({format_bytes(pair)} per pair), more than the "
            f"{format_bytes(host)} this machine has available; use fewer points"
        )
    if on_host + rows > host:
        fits = max(n_dev, int((host - on_host) // (points * ROW_BYTES)) // n_dev * n_dev)
        raise ValueError(
            f"chunk: a chunk of {chunk:,} cases x {points:,} points keeps about "
            f"{format_bytes(rows)} of rows until written, with the solves more than the "
            f"{format_bytes(host)} this machine has available; use --chunk {fits:,} or less"
        )
    if table > host:
        raise ValueError(
            f"cases: the joined table of {cases:,} cases x {points:,} points needs about "
            f"{format_bytes(table)} to sort and write, more than the {format_bytes(host)} "
            "this machine has available; split the sweep (fewer cases, or other seeds)"
        )
    return est
