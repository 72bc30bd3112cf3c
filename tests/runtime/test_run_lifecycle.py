"""How `ampc run` ends: a plant that dies ends the run with exit 1 and the reason;
a run killed with SIGKILL keeps its tick log up to the kill on disk (the journal
is written as the ticks run) and replays; Ctrl-C writes the finished logs."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from rt_procs import SCENARIO, RunProcess

from ampc_jax.cli import main

pytestmark = [pytest.mark.both_cores]


def _args(out: Path, rt_args: list[str], seconds: float = 30.0) -> list[str]:
    args = [*rt_args, "--channel", "slcan-pty:", "--scenario", SCENARIO, "--with-plant"]
    return [*args, "--duration", f"{seconds:g}", "--out", str(out)]


@pytest.mark.timeout(300)
def test_a_killed_plant_ends_the_run_with_exit_1_and_the_reason(tmp_path: Path, rt_args) -> None:
    out = tmp_path / "run"
    run = RunProcess(*_args(out, rt_args))
    try:
        run.wait_for_ticks(20, timeout=240)
        plants = [pid for pid, cmd in run.started.items() if " plant " in cmd]
        assert len(plants) == 1, run.started
        os.kill(plants[0], signal.SIGKILL)
        rc, stdout, stderr = run.finish(timeout=60)
    finally:
        run.kill_all()
    assert rc == 1, (stdout[-2000:], stderr[-2000:])
    errors = [line for line in stderr.splitlines() if line.startswith("ampc: error: ")]
    assert len(errors) == 1, stderr
    assert "plant" in errors[0] and "signal 9" in errors[0], errors[0]
    meta = json.loads((out / "run.json").read_text())
    assert meta["state"] == "error" and "plant" in meta["error"], meta
    assert 20 <= meta["ticks"] < 600, meta


@pytest.mark.timeout(300)
def test_sigkill_keeps_every_tick_up_to_the_kill_and_the_run_replays(
    tmp_path: Path, rt_args, capsys
) -> None:
    from ampc_jax.runtime.replay import load_run

    out = tmp_path / "run"
    run = RunProcess(*_args(out, rt_args))
    try:
        seen = run.wait_for_ticks(40, timeout=240)
        os.kill(run.proc.pid, signal.SIGKILL)  # no clean-up of any kind
        run.proc.wait(timeout=10)
    finally:
        run.kill_all()  # the plant, orphaned
    assert not (out / "ticks.parquet").exists()
    meta, cols = load_run(out)
    assert meta["state"] == "running"
    # every tick up to the last progress line (printed after its tick was logged)
    ticks = np.asarray(cols["tick"])
    assert ticks.size >= seen and np.array_equal(ticks, np.arange(ticks.size)), ticks
    sent = np.asarray(cols["sent"], bool)
    assert np.array_equal(np.asarray(cols["seq"])[sent], np.arange(1, sent.sum() + 1))
    # `ampc replay` accepts the journal and reproduces every stepped command
    capsys.readouterr()
    rc = main(["replay", str(out), "--out", str(tmp_path / "replay")])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "did not finish" in captured.err  # said, not hidden
    res = json.loads((tmp_path / "replay" / "replay.json").read_text())
    d = res["determinism"]
    stepped = int(np.asarray(cols["stepped"], bool).sum())
    assert d["differ"] == 0 and d["identical"] == stepped > 0, d
    assert res["log"]["complete"] is False and res["log"]["ticks"] == ticks.size


@pytest.mark.slow  # one more run of its own over the pty
@pytest.mark.timeout(300)
def test_ctrl_c_ends_the_run_with_its_logs_written(tmp_path: Path, rt_args) -> None:
    from ampc_jax.runtime.replay import load_run

    out = tmp_path / "run"
    run = RunProcess(*_args(out, rt_args))
    try:
        seen = run.wait_for_ticks(30, timeout=240)
        os.kill(run.proc.pid, signal.SIGINT)
        rc, stdout, stderr = run.finish(timeout=60)
    finally:
        run.kill_all()
    assert rc == 130, stderr
    meta, cols = load_run(out)
    assert meta["state"] == "stopped" and meta["stopped_by"] == "SIGINT", meta
    assert (out / "ticks.parquet").is_file() and not (out / "ticks.jsonl").exists()
    assert meta["ticks"] == len(cols["tick"]) >= seen
