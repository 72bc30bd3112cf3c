"""The runtime's end-to-end tests run `ampc run` as deployed: with a real-time
ticker and loop (``--rt-priority``) where this machine allows SCHED_FIFO, so
that their no-missed-deadline checks measure the runtime, not how the test
runner's other worker loads the shared cores (docs/runtime.md, "Timing")."""

import os
import subprocess

import pytest


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
