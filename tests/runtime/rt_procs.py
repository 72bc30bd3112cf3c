"""Helpers of the runtime's end-to-end tests: `ampc` in a subprocess, a run in the
background read line by line, and the processes it started (from /proc)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from ampc_jax.testing.budget import budget

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = "cruise_lane_change"
RUN_SECONDS = 10.0


def ampc(*args: str, timeout: float, check: bool = True) -> subprocess.CompletedProcess:
    """``python -m ampc_jax.cli ARGS`` in a subprocess (exit 0 asserted with ``check``)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run(
        [sys.executable, "-m", "ampc_jax.cli", *args],
        capture_output=True,
        text=True,
        timeout=budget(timeout),
        env=env,
        cwd=ROOT,
    )
    if check:
        assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p


def cmdline(pid: int) -> str:
    """The command line of process ``pid`` ("" once it is gone)."""
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def children(pid: int) -> list[int]:
    """The ids of the processes whose parent is ``pid`` (from /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid ...: comm may hold spaces, so split after its ')'
        fields = stat[stat.rindex(")") + 2 :].split()
        if int(fields[1]) == pid:
            out.append(int(d.name))
    return out


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


class RunProcess:
    """`ampc run ARGS` started in the background, its progress lines read as they come."""

    def __init__(self, *args: str) -> None:
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ampc_jax.cli", "run", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            text=True,
            cwd=ROOT,
        )
        self.lines: list[str] = []
        self.started: dict[int, str] = {}  # its children seen so far (the plant): command lines

    def wait_for_ticks(self, n: int, timeout: float) -> int:
        """Read progress lines until one reports at least ``n`` ticks; returns its count."""
        end = time.monotonic() + budget(timeout)
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            self.started.update({c: cmdline(c) for c in children(self.proc.pid)})
            words = line.split()
            if line.startswith("t ") and "ticks" in words:
                ticks = int(words[words.index("ticks") + 1])
                if ticks >= n:
                    return ticks
            assert time.monotonic() < end, "".join(self.lines[-20:])
        raise AssertionError(f"the run ended before {n} ticks: {''.join(self.lines[-20:])}")

    def finish(self, timeout: float) -> tuple[int, str, str]:
        """Wait for the end: (exit code, all of stdout, stderr)."""
        out, err = self.proc.communicate(timeout=budget(timeout))
        return self.proc.returncode, "".join(self.lines) + out, err

    def kill_all(self) -> None:
        """SIGKILL the run and every child it was seen with, where still there (clean-up):
        a child only while its command line is still the one seen (no recycled id)."""
        own = {c: cmdline(c) for c in children(self.proc.pid)}
        for pid, cmd in {**self.started, **own}.items():
            if cmd and cmdline(pid) == cmd:
                _kill(pid)
        if self.proc.poll() is None:
            self.proc.kill()
        try:
            self.proc.communicate(timeout=10)
        except (subprocess.TimeoutExpired, ValueError):
            pass
