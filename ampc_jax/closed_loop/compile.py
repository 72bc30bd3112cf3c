"""Compiling a command's programs: cheaper options for closed loops, several at once.

Two rules, measured by ``bench/bench_compile.py`` (``docs/results.md``,
"Compile times"):

* **A closed loop compiles without LLVM's optimisation passes and with
  XLA:CPU's classic emitters** (:data:`LOOP_COMPILER_OPTIONS`). Reason: its
  compile is what a user waits for and its run is not: on the cruise lane
  change (16 s, shadow on) the compile took 5.2 instead of 15.8 CPU seconds
  and the run 88 instead of 77 ms; on the stability launch/brake 3.0 instead
  of 12.5 s, the run 42 ms either way; iterations, e_sub and tracking were
  identical. The single-step programs that are timed (the r_time replay, the
  runtime's step) keep XLA's defaults: there the run is what is measured
  (one Local Explicit step ran 1.65x slower with these options).
* **Independent programs compile at the same time** (:class:`Compiler`, one
  thread per core): XLA releases the GIL while it compiles, so a command
  with several programs (``ampc demo``: the run, its baseline and the two
  replayed solvers) waits for the longest chain rather than for their sum.
  Tracing and lowering stay on the calling thread (they hold the GIL).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import jax

__all__ = ["LOOP_COMPILER_OPTIONS", "Compiler", "cores", "loop_compiler_options"]

LOOP_COMPILER_OPTIONS: dict[str, Any] = {
    "xla_backend_optimization_level": 0,
    "xla_cpu_use_fusion_emitters": False,
}
"""XLA options of a compiled closed loop on the CPU (see the module docstring)."""


def loop_compiler_options() -> dict[str, Any]:
    """:data:`LOOP_COMPILER_OPTIONS` where the default backend is the CPU, else none
    (the options are XLA:CPU's)."""
    return dict(LOOP_COMPILER_OPTIONS) if jax.default_backend() == "cpu" else {}


def cores() -> int:
    """The cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _compile(lowered: Any, options: dict[str, Any] | None) -> tuple[Any, float]:
    t0 = time.perf_counter()
    compiled = lowered.compile(compiler_options=options) if options else lowered.compile()
    return compiled, time.perf_counter() - t0


class Compiler:
    """A pool that compiles lowered programs concurrently, one thread per core
    (``workers``; default :func:`cores`); use it as a context manager.

    :meth:`submit` returns a ``Future`` of ``(compiled, seconds)``, the
    seconds being that compile's wall time (with other compiles beside it).
    Programs are started in the order submitted: submit first what is needed
    first.
    """

    def __init__(self, workers: int | None = None) -> None:
        self._pool = ThreadPoolExecutor(max_workers=workers or cores())

    def submit(self, lowered: Any, options: dict[str, Any] | None = None) -> Future:
        return self._pool.submit(_compile, lowered, options)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> Compiler:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
