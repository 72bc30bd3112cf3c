"""`ampc replay` refuses a tampered or truncated run: the ticks are checked against
run.json's counts and against the bridge's candump log (each logged frame decoded
with cantools and the DBC, compared with the ticks' ``framed_*``), the files
against the digests run.json recorded; each refusal is one ``ampc: error:`` line
with exit 2, never a traceback. Each case is tried as a naive edit and as a
forger's, who also reseals run.json's digests."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from ampc_jax.cli import main

# the first test to ask for run_dir waits for conftest's 10 s run (two compilations)
pytestmark = pytest.mark.timeout(300)

WHEELS = ("FL", "FR", "RL", "RR")


def _copy(run_dir: Path, tmp_path: Path) -> Path:
    d = tmp_path / "run"
    shutil.copytree(run_dir, d, ignore=shutil.ignore_patterns("plant"))
    return d


def _edit_ticks(d: Path, edit: Callable[[dict], dict]) -> None:
    table = pq.read_table(d / "ticks.parquet")
    cols = edit(table.to_pydict())
    pq.write_table(pa.table(cols, schema=table.schema), d / "ticks.parquet")


def _edit_meta(d: Path, edit: Callable[[dict], None]) -> None:
    meta = json.loads((d / "run.json").read_text())
    edit(meta)
    (d / "run.json").write_text(json.dumps(meta, indent=1))


def _reseal(d: Path) -> None:
    """What a forger does after an edit: record the files' new digests, reseal run.json."""
    from ampc_jax.runtime.ticklog import file_sha256, write_run_json

    meta = json.loads((d / "run.json").read_text())
    meta["files"] = {name: file_sha256(d / name) for name in meta["files"]}
    write_run_json(d / "run.json", meta)


def _refusal(capsys, d: Path, tmp_path: Path) -> str:
    capsys.readouterr()
    rc = main(["replay", str(d), "--out", str(tmp_path / "replay")])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("ampc: error: ")]
    assert rc == 2 and len(lines) == 1, (rc, err)
    assert lines[0].startswith(f"ampc: error: replay: {d}"), lines[0]
    assert not (tmp_path / "replay" / "replay.json").exists()
    return lines[0]


def _framed_row(cols: dict) -> int:
    """A tick in the middle of the run whose frame the log recorded."""
    idx = [i for i, n in enumerate(cols["bridge_tx_frames"]) if n > 0 and cols["sent"][i]]
    return idx[len(idx) // 2]


def test_the_untampered_run_passes_every_check(run_dir: Path) -> None:
    from ampc_jax.runtime.runcheck import check_run

    run = check_run(run_dir)
    assert run.complete and run.meta["state"] == "finished"
    n = len(run.cols["tick"])
    assert n == run.meta["ticks"] == 200
    assert run.frames_checked == int((np.asarray(run.cols["bridge_tx_frames"]) > 0).sum()) > 0
    assert run.frames_unchecked == 0


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_refuses_a_log_without_its_last_40_ticks(run_dir, tmp_path, capsys, reseal) -> None:
    d = _copy(run_dir, tmp_path)
    _edit_ticks(d, lambda c: {k: v[:-40] for k, v in c.items()})
    if reseal:
        _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert "ticks.parquet" in line and "160" in line and "200" in line, line


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_refuses_a_framed_torque_changed_by_500_nm(run_dir, tmp_path, capsys, reseal) -> None:
    d = _copy(run_dir, tmp_path)
    at = {}

    def edit(c: dict) -> dict:
        at["i"] = i = _framed_row(c)
        c["framed_RL"][i] += 500.0
        return c

    _edit_ticks(d, edit)
    if reseal:
        _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert "bridge.log" in line and f"tick {at['i']}" in line and "RL" in line, line


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_refuses_a_flipped_sent_flag(run_dir, tmp_path, capsys, reseal) -> None:
    d = _copy(run_dir, tmp_path)
    at = {}

    def edit(c: dict) -> dict:
        at["i"] = i = _framed_row(c)
        c["sent"][i] = False
        return c

    _edit_ticks(d, edit)
    if reseal:
        _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert f"tick {at['i']}" in line and "sent" in line, line


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_refuses_tick_counts_multiplied_by_ten(run_dir, tmp_path, capsys, reseal) -> None:
    d = _copy(run_dir, tmp_path)

    def edit(m: dict) -> None:
        m["ticks"] *= 10
        m["sent"] *= 10

    _edit_meta(d, edit)
    if reseal:
        _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert "run.json" in line and "2000" in line, line


@pytest.mark.parametrize("key", ["scenario", "config_hash", "dtype", "formulation", "state"])
@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_refuses_a_run_json_without_a_field(run_dir, tmp_path, capsys, key, reseal) -> None:
    d = _copy(run_dir, tmp_path)
    _edit_meta(d, lambda m: m.pop(key))
    if reseal:
        _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert "run.json" in line and repr(key) in line, line


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_refuses_a_truncated_candump_log(run_dir, tmp_path, capsys, reseal) -> None:
    d = _copy(run_dir, tmp_path)
    lines = (d / "bridge.log").read_text().splitlines(keepends=True)
    (d / "bridge.log").write_text("".join(lines[: len(lines) // 2]))
    if reseal:
        _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert "bridge.log" in line, line


def test_refuses_an_edit_only_the_digest_sees(run_dir, tmp_path, capsys) -> None:
    d = _copy(run_dir, tmp_path)

    def edit(c: dict) -> dict:
        c["iterations"][_framed_row(c)] += 1
        return c

    _edit_ticks(d, edit)
    line = _refusal(capsys, d, tmp_path)
    assert "ticks.parquet" in line and "modified" in line, line


def test_no_tick_stepped_is_refused_cleanly(run_dir, tmp_path, capsys) -> None:
    """A consistent log in which no tick stepped the controller (the state never
    became usable): nothing to replay, said in one line (was a TypeError)."""
    d = _copy(run_dir, tmp_path)
    nan = float("nan")

    def edit(c: dict) -> dict:
        n = len(c["tick"])
        c["stepped"] = c["sent"] = [False] * n
        c["seq"] = [-1] * n
        c["reason"] = ["state invalid (WheelSpeeds: timeout)"] * n
        c["skip"] = ["state"] * n
        c["iterations"] = c["status"] = [-1] * n
        c["fallback"] = [False] * n
        for k in c:
            if k.startswith(("bus_", "cmd_")) or k.endswith(("_ms", "_residual")):
                c[k] = [nan] * n
        c["clamped"] = c["fault"] = [""] * n
        return c

    _edit_ticks(d, edit)

    def counts(m: dict) -> None:
        m.update(sent=0, misses=0, skipped={"state": m["ticks"]}, margin_ms_min=None)
        m.update(compute_ms_median=None, compute_ms_p99=None, compute_ms_max=None)

    _edit_meta(d, counts)
    _reseal(d)
    line = _refusal(capsys, d, tmp_path)
    assert "no tick" in line and "stepped" in line, line


@pytest.mark.parametrize("scenario", ["cruise_lane_change", "stability_launch_brake"])
def test_replay_rho_scale_one_is_the_runs_own_setting(scenario):
    """``ampc replay --rho-scale 1`` replays the run's rho (the cruise example's default
    scales are (1, 0.5)), not 1 for every objective; 2 doubles each objective's."""
    import jax.numpy as jnp

    from ampc_jax.closed_loop import config_for
    from ampc_jax.runtime.replay import scaled_rho

    run = config_for(scenario, shadow=False)
    base = run.loop_params(jnp.float64).controller.solver.rho
    for factor in (1.0, 2.0):
        cfg = config_for(scenario, shadow=False, rho_scale=scaled_rho(run.rho_scale, factor))
        rho = cfg.loop_params(jnp.float64).controller.solver.rho
        np.testing.assert_allclose(np.asarray(rho), factor * np.asarray(base), rtol=1e-12)
    assert scaled_rho((1.0, 0.5), 2.0) == (2.0, 1.0) and scaled_rho(0.5, 3.0) == 1.5
