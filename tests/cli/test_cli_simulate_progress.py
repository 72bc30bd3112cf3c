"""``ampc simulate`` says on stderr that it compiles before the first compiled call,
and what the compile and the run took after it (without a terminal no progress
bar shows; ``--quiet`` prints neither line)."""

import re

import pytest

import ampc_jax.closed_loop as closed_loop
from ampc_jax.cli import main

pytestmark = pytest.mark.timeout(240)

ARGS = ["simulate", "cruise_lane_change", "--duration", "0.5", "--no-shadow", "--no-timing"]


def test_compile_line_comes_before_the_compiled_call_and_its_time_after(
    tmp_path, capsys, monkeypatch
):
    real = closed_loop.prepare  # traces and lowers; the compile follows
    seen_before = []

    def spy(*args, **kwargs):
        seen_before.append(capsys.readouterr().err)  # what was printed before the call
        return real(*args, **kwargs)

    monkeypatch.setattr(closed_loop, "prepare", spy)
    assert main([*ARGS, "--out", str(tmp_path / "run")]) == 0
    after = capsys.readouterr().err
    assert len(seen_before) == 1
    assert seen_before[0].strip().endswith("compiling the closed loop ...")
    assert re.search(r"compiled in \d+\.\d s; 0\.5 s simulated, first run \d+\.\d\d s", after), (
        after
    )


def test_quiet_prints_no_progress_line(tmp_path, capsys, monkeypatch):
    def stop(*args, **kwargs):
        raise RuntimeError("stopped before compiling")

    monkeypatch.setattr(closed_loop, "prepare", stop)
    with pytest.raises(RuntimeError, match="stopped before compiling"):
        main([*ARGS, "--quiet", "--out", str(tmp_path / "run")])
    assert "compiling" not in capsys.readouterr().err
