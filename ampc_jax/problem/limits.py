"""What the machine and the number formats hold: sizes and magnitudes refused up front.

Rule: a problem (or a sweep) whose arrays would not fit in the memory the
machine has, or whose numbers would overflow what the solver forms from them,
is refused before any work, naming the field and the estimate; reason: the
alternative is minutes of compiling followed by an out-of-memory kill, an XLA
``RESOURCE_EXHAUSTED`` traceback or a LAPACK error that names nothing
(``tests/problem/test_problem_spec.py``).

* :func:`available_memory`: what this process may still allocate (the
  kernel's ``MemAvailable``, capped by a cgroup limit), without psutil.
* :func:`condensed_bytes`: the bytes of the largest arrays a solve forms from
  a problem's sizes (the condensed prediction and cost matrices, eq.F3_primal_1).
* :data:`MAX_MAGNITUDE`: the largest number a field may hold.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .errors import ProblemError

__all__ = [
    "MAX_MAGNITUDE",
    "available_memory",
    "check_memory",
    "condensed_bytes",
    "format_bytes",
    "format_count",
    "log10_norm",
    "max_power_log10",
]

MAX_MAGNITUDE = 1e150
"""Largest magnitude of any entry of a problem, and of the condensed Hessian H_j
its entries make. Reason: eq.Convergence compares squared norms, and H_j =
2 (Y_u' Qbar_j Y_u + Rbar) multiplies the model's entries pairwise; a number
above sqrt(float64's largest, 1.8e308) = 1.3e154 overflows to inf once squared.
1e150 leaves the sums of a few thousand such squares finite."""

_FLOAT_BYTES = 8  # the estimates are for float64, the default; float32 halves them


def available_memory() -> int | None:
    """Bytes this process may still allocate: Linux's ``MemAvailable`` (free
    memory plus what the kernel can reclaim), capped by a cgroup v2 or v1
    memory limit less its usage; ``os.sysconf``'s free pages elsewhere; None
    when the platform says nothing."""
    found: list[int] = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
                break
    except (OSError, ValueError, IndexError):
        pass
    if not found:
        try:
            found.append(int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE")))
        except (AttributeError, OSError, ValueError):
            pass
    for limit, usage in (
        ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
        (
            "/sys/fs/cgroup/memory/memory.limit_in_bytes",
            "/sys/fs/cgroup/memory/memory.usage_in_bytes",
        ),
    ):
        try:
            cap = Path(limit).read_text().strip()
            if cap != "max" and int(cap) < 2**60:
                found.append(max(0, int(cap) - int(Path(usage).read_text().strip())))
            break
        except (OSError, ValueError):
            continue
    return min(found) if found else None


def format_bytes(n: float) -> str:
    """``n`` bytes in decimal units: ``"2.3 GB"``, ``"64 EB"``, ``"6.4e+22 B"`` beyond
    (``"about 10^400 B"`` for an integer beyond float64)."""
    if isinstance(n, int) and n >= 10**300:
        return f"about 10^{math.floor(math.log10(n))} B"
    n = float(n)
    for unit, scale in (("EB", 1e18), ("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}" if n < 1000 * 1e18 else f"{n:.2g} B"
    return f"{n / 1e3:.3g} kB" if n >= 1e3 else f"{n:.0f} B"


def condensed_bytes(*, horizon: int, n_x: int, n_u: int, n_y: Sequence[int]) -> int:
    """Bytes (float64) of the largest arrays a solve of one problem forms, from its sizes.

    With N = N_p, U = n_u, Y = max n_y and J objectives (``n_y`` one size per
    objective), the words counted are

    * 8 N^3: the (N, N, N) selector of the block-Toeplitz prediction matrices
      and the copies XLA folds it into (the peak of ``ampc solve`` on the
      cruise example grows as N^3: 0.69 GB at N_p = 100, 2.3 GB at 300, killed
      above 16 GB at 1000);
    * J (6 (N U)^2 + 4 (N Y)(N U) + 4 (N Y)^2 + 2 (N Y)(N n_x)): per objective
      Y_u, Qbar_j and its factor, H_j, K_j and its inverse, Y_w
      (eq.F3_primal_1);
    * 2 (N U)^2 + 4 N n_x^2: the reference's condensed QP and the matrix powers.

    An upper estimate: the structured (Riccati) solve forms none of the N^2
    matrices, but the command line and the reference do.
    """
    N, U = int(horizon), int(n_u)
    J, Y = len(n_y), max(int(y) for y in n_y) if len(n_y) else 0
    words = 8 * N**3
    words += J * (6 * (N * U) ** 2 + 4 * (N * Y) * (N * U) + 4 * (N * Y) ** 2)
    words += J * 2 * (N * Y) * (N * int(n_x))
    words += 2 * (N * U) ** 2 + 4 * N * int(n_x) ** 2
    return _FLOAT_BYTES * words


def check_memory(*, horizon: int, n_x: int, n_u: int, n_y: Sequence[int]) -> None:
    """ProblemError naming ``horizon`` (or ``A`` when the state size dominates)
    when :func:`condensed_bytes` exceeds :func:`available_memory`."""
    avail = available_memory()
    if avail is None:
        return
    # the estimate is exact in integers; a horizon beyond 10^12 is beyond any machine
    N = min(int(horizon), 10**12)
    need = condensed_bytes(horizon=N, n_x=n_x, n_u=n_u, n_y=n_y)
    if need <= avail:
        return
    state = 4 * N * int(n_x) ** 2 + 2 * len(n_y) * N * max(n_y) * N * int(n_x)
    sizes = (
        f"n_x = {n_x} states, n_u = {n_u} inputs, {len(n_y)} objective(s) with up to "
        f"{max(n_y)} outputs"
    )
    if _FLOAT_BYTES * state > need / 2:
        field, what = "A", f"n_x = {n_x} (with N_p = {format_count(horizon, grouped=False)})"
    else:
        field, what = "horizon", f"N_p = {format_count(horizon, grouped=False)}"
    raise ProblemError(
        f"{field}: {what} needs about {format_bytes(need)} for the condensed matrices a "
        f"solve forms ({sizes}; they grow as N_p^3 and (N_p n_u)^2), more than the "
        f"{format_bytes(avail)} this machine has available: shorten the horizon"
    )


def format_count(n: int, grouped: bool = True) -> str:
    """An integer as text (with thousands separators when ``grouped``); ``about
    10^k`` beyond 10^18 (also past Python's 4,300-digit str limit)."""
    if n >= 10**18:
        return f"about 10^{math.floor(math.log10(n))}"
    return f"{n:,}" if grouped else str(n)


def log10_norm(x: np.ndarray) -> float:
    """log10 of the Frobenius norm of ``x`` (-inf for zero), without overflow."""
    m = float(np.max(np.abs(x))) if np.size(x) else 0.0
    if m == 0.0:
        return -math.inf
    return math.log10(m) + math.log10(float(np.linalg.norm(np.asarray(x) / m)))


def max_power_log10(A: np.ndarray, horizon: int, stop: float = 400.0) -> float:
    """log10 of max_{0 <= k < N_p} ||A^k||_F, by products rescaled at every step
    (no overflow for any growth); returns early once above ``stop``."""
    n = A.shape[0]
    M = np.eye(n)
    log_scale = 0.0
    best = log10_norm(M)
    for _ in range(1, int(horizon)):
        M = A @ M
        s = float(np.linalg.norm(M))
        if s == 0.0 or not math.isfinite(s):
            break
        log_scale += math.log10(s)
        M = M / s
        best = max(best, log_scale)
        if best > stop:
            break
    return best
