"""How `ampc run` ends: a plant that dies ends the run with exit 1 and the reason;
a run killed with SIGKILL keeps its tick log up to the kill on disk (the journal
is written as the ticks run) and replays from the journal alone, whenever the
kill came; Ctrl-C writes the finished logs."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from rt_procs import SCENARIO, RunProcess

from ampc_jax.cli import main
from ampc_jax.testing.budget import budget

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


def _journal_rows(path: Path) -> int:
    try:
        return sum(line.startswith(b'{"tick":') for line in path.read_bytes().split(b"\n"))
    except OSError:
        return 0


@pytest.mark.timeout(300)
def test_sigkill_keeps_every_tick_up_to_the_kill_and_the_run_replays(
    tmp_path: Path, rt_args, capsys
) -> None:
    """Killed half a second into actuation (10 ticks, before run.json's first
    rewrite, so it holds the run's settings and no counts): the journal alone
    replays, and the replay says the run was killed."""
    from ampc_jax.runtime.replay import load_run

    out = tmp_path / "run"
    run = RunProcess(*_args(out, rt_args))
    try:
        end = time.monotonic() + budget(240)
        while (seen := _journal_rows(out / "ticks.jsonl")) < 10:
            assert run.proc.poll() is None and time.monotonic() < end, seen
            time.sleep(0.01)
        os.kill(run.proc.pid, signal.SIGKILL)  # no clean-up of any kind
        run.proc.wait(timeout=budget(10))
    finally:
        run.kill_all()  # the plant, orphaned
    assert not (out / "ticks.parquet").exists()
    meta, cols = load_run(out)
    assert meta["state"] == "running"
    ticks = np.asarray(cols["tick"])
    assert ticks.size >= seen and np.array_equal(ticks, np.arange(ticks.size)), ticks
    sent = np.asarray(cols["sent"], bool)
    assert np.array_equal(np.asarray(cols["seq"])[sent], np.arange(1, sent.sum() + 1))
    # `ampc replay` accepts the journal and reproduces every stepped command
    capsys.readouterr()
    rc = main(["replay", str(out), "--out", str(tmp_path / "replay")])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert f"did not finish: it was killed (its process {run.proc.pid} is gone)" in captured.err
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


# -- killed at other moments: the journal as the runtime's writer leaves it ----------


def _reaped() -> int:
    """The id of a process that has exited (and been reaped)."""
    child = subprocess.Popen(["true"])
    child.wait()
    return child.pid


def _killed(run_dir: Path, d: Path, ticks: int, *, rewrite: int | None = None,
            cut: bool = False, run_json: bool = True) -> None:  # fmt: skip
    """``d`` as a run killed after ``ticks`` ticks leaves it, from the rows of the
    shared run (its bridge.log with them): the journal written by TickJournal as
    the runner writes it (a tick's framed update one tick later), run.json as at
    start-up or (``rewrite``) as rewritten after that many ticks, the last line cut
    in half (``cut``), run.json gone (``run_json`` False)."""
    import pyarrow.parquet as pq

    from ampc_jax.runtime.runner import _counts
    from ampc_jax.runtime.ticklog import TickJournal

    d.mkdir()
    shutil.copy(run_dir / "bridge.log", d / "bridge.log")
    meta = json.loads((run_dir / "run.json").read_text())
    keys = ("scenario", "formulation", "dtype", "config_hash", "source", "channel", "start_reset")
    settings = {k: meta[k] for k in keys}
    settings.update(pid=_reaped(), host=socket.gethostname())
    rows = pq.read_table(run_dir / "ticks.parquet").to_pylist()
    framed = [k for k in rows[0] if k.startswith("framed_")] + ["bridge_mode", "bridge_tx_frames"]
    journal = TickJournal(d, settings)
    for i in range(ticks + cut):
        if i and rows[i - 1]["bridge_tx_frames"] != -1:
            journal.framed(rows[i - 1])
        row = dict(rows[i])
        row.update({k: (-1 if k == "bridge_tx_frames" else "" if k == "bridge_mode" else
                        float("nan")) for k in framed})  # fmt: skip
        if i == ticks:  # the kill cut this line short
            journal.close()
            line = json.dumps(row) + "\n"
            with open(d / "ticks.jsonl", "a") as f:
                f.write(line[: len(line) // 2])
            break
        journal.append(row)
        if rewrite is not None and i + 1 == rewrite:
            done = rows[: i + 1]
            compute = [r["compute_ms"] for r in done if r["stepped"]]
            journal.status({**_counts(done, compute), "bridge": meta["bridge"]})
    else:
        journal.close()
    if not run_json:
        (d / "run.json").unlink()


KILLS = {
    "0.5 s in": {"ticks": 10},
    "mid-line": {"ticks": 25, "cut": True},
    "after run.json's first rewrite": {"ticks": 30, "rewrite": 20},
    "before run.json was written": {"ticks": 15, "run_json": False},
}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("moment", sorted(KILLS))
def test_a_run_killed_at_any_moment_replays_from_its_journal(
    run_dir: Path, tmp_path: Path, capsys, moment: str
) -> None:
    d = tmp_path / "run"
    _killed(run_dir, d, **KILLS[moment])
    capsys.readouterr()
    rc = main(["replay", str(d), "--out", str(tmp_path / "replay")])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "did not finish: it was killed" in captured.err, captured.err
    res = json.loads((tmp_path / "replay" / "replay.json").read_text())
    ticks = KILLS[moment]["ticks"]
    assert res["log"]["ticks"] == ticks and res["log"]["alive"] is False, res["log"]
    d_ = res["determinism"]
    assert d_["differ"] == 0 and d_["identical"] > 0, d_


@pytest.mark.timeout(120)
def test_a_run_killed_before_its_first_tick_is_refused_in_one_line(
    run_dir: Path, tmp_path: Path, capsys
) -> None:
    d = tmp_path / "run"
    _killed(run_dir, d, 0)
    capsys.readouterr()
    rc = main(["replay", str(d), "--out", str(tmp_path / "replay")])
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("ampc: error: ")]
    assert rc == 2 and len(lines) == 1, err
    assert "was killed before its first tick" in lines[0] and "nothing to replay" in lines[0]
