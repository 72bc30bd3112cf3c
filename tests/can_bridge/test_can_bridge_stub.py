"""The shipped stubs (``can_bridge/__init__.pyi``) against the compiled module
under test: mypy's stubtest compares every name, signature and kind, and mypy
checks what ``stats()`` and ``latest_state()`` return against their
TypedDicts. Both run on the ``can_bridge`` this process imported (its folder
first on the path), so a build and its stub are checked together."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import time

import pytest

import can_bridge

pytestmark = pytest.mark.timeout(180)

ALLOWLIST = pathlib.Path(__file__).with_name("stubtest_allowlist.txt")
PACKAGE = pathlib.Path(can_bridge.__file__).parent


def _mypy(args: list[str], cwd: pathlib.Path) -> subprocess.CompletedProcess[str]:
    """Run a mypy tool in a fresh process that imports, and reads the stub
    of, the ``can_bridge`` under test: its folder first on the path, where
    mypy looks for the stub too (not a checkout's crate folder)."""
    root = str(PACKAGE.parent)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    return subprocess.run(
        [sys.executable, "-m", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=150,
    )


def test_the_package_ships_its_stub_and_marker() -> None:
    assert (PACKAGE / "__init__.pyi").is_file()
    assert (PACKAGE / "py.typed").is_file()


def test_stubtest_finds_the_stub_and_the_module_in_agreement(tmp_path: pathlib.Path) -> None:
    r = _mypy(["mypy.stubtest", "can_bridge", "--allowlist", str(ALLOWLIST)], tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr


def test_the_result_dicts_match_their_typeddicts(tmp_path: pathlib.Path) -> None:
    """A program assigning the running bridge's dicts, as literals, to the
    stub's TypedDicts: mypy refuses a missing or extra key and a value of the
    wrong type."""
    b = can_bridge.Bridge("slcan-pty:", period_ms=10)
    idle = (b.stats(), b.latest_state())
    with b:
        time.sleep(0.1)
        running = (b.stats(), b.latest_state())
    # nan/inf as names, should a counter ever report one (repr writes them bare)
    lines = ["import can_bridge", "from math import inf, nan", ""]
    for k, (stats, state) in enumerate([idle, running]):
        assert stats["ticks"] > 0 or k == 0
        lines.append(f"stats_{k}: can_bridge.Stats = {stats!r}")
        lines.append(f"state_{k}: can_bridge.VehicleState = {state!r}")
    (tmp_path / "dicts.py").write_text("\n".join(lines) + "\n")
    r = _mypy(
        ["mypy", "--strict", "--no-incremental", "--cache-dir", os.devnull, "dicts.py"],
        tmp_path,
    )
    assert r.returncode == 0, r.stdout + r.stderr
