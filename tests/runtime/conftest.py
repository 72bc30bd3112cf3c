"""The runtime's end-to-end tests run `ampc run` as deployed: with a real-time
ticker and loop (``--rt-priority``) where this machine allows SCHED_FIFO (docs/runtime.md,
"Timing"). They assert what the bus carried and what the logs hold, never how
late a tick was: deadline misses, periods and compute times belong in
``bench/bench_runtime.py``.

``run_dir``: one 10 s closed loop over a pty (`ampc run --with-plant`), shared by
the files that check its frames, its vehicle, its replay and its logs' integrity.
The helpers live in rt_procs.py (made importable here whatever pytest's import mode)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

_here = str(Path(__file__).resolve().parent)
if _here not in sys.path:
    sys.path.insert(0, _here)

from rt_procs import RUN_SECONDS, SCENARIO, ampc  # noqa: E402


def _fifo_allowed() -> bool:
    if not hasattr(os, "SCHED_FIFO"):
        return False
    try:
        return (
            subprocess.run(["chrt", "-f", "1", "true"], capture_output=True, timeout=10).returncode
            == 0
        )
    except (OSError, subprocess.SubprocessError):
        return False


@pytest.fixture(scope="session")
def rt_args() -> list[str]:
    """``["--rt-priority", "30"]`` where SCHED_FIFO is allowed, else ``[]``."""
    return ["--rt-priority", "30"] if _fifo_allowed() else []


@pytest.fixture(scope="session")
def run_result(tmp_path_factory, rt_args) -> tuple[Path, subprocess.CompletedProcess]:
    """One finished `ampc run --with-plant` of RUN_SECONDS: (its directory, the process)."""
    out = tmp_path_factory.mktemp("run")
    p = ampc(
        "run",
        *rt_args,
        "--channel",
        "slcan-pty:",
        "--scenario",
        SCENARIO,
        "--duration",
        f"{RUN_SECONDS:g}",
        "--with-plant",
        "--quiet",
        "--out",
        str(out),
        timeout=300,
    )
    return out, p


@pytest.fixture(scope="session")
def run_dir(run_result) -> Path:
    return run_result[0]
