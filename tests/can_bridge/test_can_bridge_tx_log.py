"""The bridge's candump log stays bounded under a flood, and every I/O error
of it names the file (docs/bus-safety.md, "Out: what the wire sees", and
can_bridge/README.md).

Bounds: received frames are logged at most ``log_rx_per_s`` a second for
the bridge's own identifiers and as many for all others (a token bucket with
a second's burst: a flood of unknown frames keeps a sample and never hides
the vehicle's), and nothing once the file holds ``log_max_bytes``; what is
left out is counted in ``log_suppressed``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import can_bridge
from ampc_jax.testing.budget import budget
from ampc_jax.testing.can_fault_peers import open_raw_host, read_all

pytestmark = pytest.mark.timeout(60)


def _flood(fd: int, seconds: float, line: bytes = b"t7FF0\r") -> int:
    """Write unknown-ID frames as fast as the pty takes them; returns how many."""
    n = 0
    chunk = line * 512
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            n += os.write(fd, chunk) // len(line)
        except BlockingIOError:
            read_all(fd, 0.001)  # the bridge's frames and replies
    return n


def test_tx_log_a_flood_of_unknown_frames_keeps_the_log_bounded(tmp_path: Path) -> None:
    """Two seconds of unknown-ID frames as fast as the pty takes them: the
    log keeps a sample of them (at most a second's burst plus the rate),
    every one left out is counted, and the bridge's own frames are all there
    (before: 660,672 frames, +33 MB in 2 s, log_dropped=0)."""
    log = tmp_path / "b.log"
    rate = 1000
    b = can_bridge.Bridge("slcan-pty:", period_ms=50, log_path=log, log_rx_per_s=rate)
    b.start()
    fd = open_raw_host(b.pty_path)
    try:
        read_all(fd, 0.2)
        t0 = time.monotonic()
        sent = _flood(fd, 2.0)
        took = time.monotonic() - t0
        time.sleep(0.3)
        s = b.stats()
    finally:
        b.stop()
        os.close(fd)
    lines = log.read_text().splitlines()
    unknown = [x for x in lines if " 7FF#" in x]
    tx = [x for x in lines if x.endswith(" T")]
    assert sent > 5 * rate, sent  # a flood indeed
    assert 0 < len(unknown) <= rate * (took + 1.5) + 10, (len(unknown), took)
    assert s["log_suppressed"] >= s["rx_unknown_id"] - len(unknown) - 10
    assert s["log_suppressed"] > 0 and s["log_dropped"] == 0, s
    assert len(tx) >= s["tx_frames"] - 1
    assert log.stat().st_size < 200_000


def test_tx_log_the_file_is_capped_and_the_cap_named(tmp_path: Path) -> None:
    log = tmp_path / "capped.log"
    b = can_bridge.Bridge("slcan-pty:", period_ms=10, log_path=log, log_max_bytes=4096)
    b.start()
    fd = open_raw_host(b.pty_path)
    try:
        _flood(fd, 0.5)
        time.sleep(0.3)
        s = b.stats()
    finally:
        b.stop()
        os.close(fd)
    assert log.stat().st_size <= 4096
    assert s["log_suppressed"] > 0
    assert str(log) in s["last_log_error"] and "log_max_bytes" in s["last_log_error"]


def test_tx_log_a_write_error_names_the_file() -> None:
    """/dev/full: every line lost is counted, the bridge runs on, and
    stats()["last_log_error"] names the file and the error."""
    b = can_bridge.Bridge("slcan-pty:", period_ms=10, log_path="/dev/full", log_overwrite=True)
    b.start()
    fd = open_raw_host(b.pty_path)
    try:
        read_all(fd, 0.6)
        s = b.stats()
    finally:
        b.stop()
        os.close(fd)
    assert s["log_errors"] > 0 and s["tx_frames"] > 20
    assert "/dev/full" in s["last_log_error"], s["last_log_error"]
    assert "No space left on device" in s["last_log_error"]


def test_tx_log_a_file_over_the_size_limit_names_the_file(tmp_path: Path) -> None:
    """A process whose file size limit (RLIMIT_FSIZE) stops the log: the
    error is EFBIG, "File too large", with the log's path (a run that
    stopped on "[Errno 27] File too large" named no file)."""
    log = tmp_path / "big.log"
    code = textwrap.dedent(
        f"""
        import os, resource, sys, time
        sys.path[:0] = {sys.path!r}
        import can_bridge
        from ampc_jax.testing.can_fault_peers import open_raw_host, read_all
        resource.setrlimit(resource.RLIMIT_FSIZE, (3000, 3000))
        b = can_bridge.Bridge("slcan-pty:", period_ms=5, log_path={str(log)!r})
        b.start()
        fd = open_raw_host(b.pty_path)
        read_all(fd, 1.0)
        s = b.stats()
        b.stop()
        print(s["log_errors"], s["tx_frames"])
        print(s["last_log_error"])
        """
    )
    p = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=budget(30),
        check=False,
    )
    assert p.returncode == 0, p.stderr
    counts, msg = p.stdout.strip().split("\n", 1)
    errors, frames = map(int, counts.split())
    assert errors > 0 and frames > 50, p.stdout
    assert str(log) in msg and "File too large" in msg, msg
    assert log.stat().st_size <= 3000
