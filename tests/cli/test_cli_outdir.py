"""One rule for every ``--out``: a non-empty directory (an existing file, for
``ampc export``) is refused without ``--force``, before anything compiles or
opens; a failed command removes what it created and left empty (no empty
directory, no 0-byte ``bridge.log``); a sweep's own directory is resumed."""

from __future__ import annotations

import argparse
import json
import os

import pytest

from ampc_jax.cli import build_parser, main, outdir

pytestmark = pytest.mark.timeout(120)

SCENARIO = "cruise_lane_change"


@pytest.fixture
def nothing_compiles(monkeypatch):
    """Fail the test if a controller step, a closed loop or a sweep starts."""
    import ampc_jax.cli.simulate as simulate
    import ampc_jax.runtime.runner as runner
    import ampc_jax.runtime.step as step
    import ampc_jax.sweep.run as sweep_run

    def refuse(*args, **kwargs):
        raise AssertionError("started after a refusal")

    monkeypatch.setattr(step.RuntimeStep, "compiled", refuse)
    monkeypatch.setattr(runner, "run_controller", refuse)
    monkeypatch.setattr(simulate, "_run", refuse)
    monkeypatch.setattr(sweep_run, "_step_rows", refuse)


def _line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("ampc: error: ")]
    assert len(lines) == 1, err
    return lines[0]


def _commands(out: str) -> dict[str, list[str]]:
    return {
        "simulate": ["simulate", SCENARIO, "--out", out],
        "demo": ["demo", "--out", out],
        "run": ["run", "--channel", "slcan-pty:", "--scenario", SCENARIO, "--out", out],
        "plant": ["plant", "--channel", "slcan:/dev/null", "--scenario", SCENARIO, "--out", out],
        "replay": ["replay", out + "_log", "--out", out],
        "tune": ["tune", "--out", out],
        "sweep": ["sweep", "--family", "cruise_step", "--cases", "4", "--out", out],
    }


@pytest.mark.parametrize("command", list(_commands("x")))
def test_a_non_empty_out_is_refused_without_force(capsys, tmp_path, nothing_compiles, command):
    out = tmp_path / "earlier"
    out.mkdir()
    (out / "metrics.json").write_text('{"an": "earlier run"}')
    argv = _commands(str(out))[command]
    assert main(argv) == 2
    line = _line(capsys)
    assert line.startswith(f"ampc: error: --out {out}: the directory is not empty"), line
    assert "metrics.json" in line and "--force" in line, line
    assert [p.name for p in out.iterdir()] == ["metrics.json"]  # nothing lost
    assert (out / "metrics.json").read_text() == '{"an": "earlier run"}'


def test_every_command_with_an_out_has_force_with_its_default():
    parser = build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    have = set()
    for name, p in sub.choices.items():
        flags = {o: a for a in p._actions for o in a.option_strings}
        if "--out" in flags:
            assert "--force" in flags, name
            assert flags["--force"].help.endswith("(default: refuse it)"), name
            have.add(name)
    assert have >= {"simulate", "demo", "run", "plant", "export", "replay", "tune", "sweep"}


def test_export_refuses_an_existing_file(capsys, tmp_path, nothing_compiles):
    art = tmp_path / "cruise.ampc"
    art.write_bytes(b"an earlier artefact")
    assert main(["export", "--scenario", SCENARIO, "--out", str(art)]) == 2
    line = _line(capsys)
    assert line.startswith(f"ampc: error: --out {art}: the file exists") and "--force" in line
    assert art.read_bytes() == b"an earlier artefact"


def test_force_writes_into_it_and_a_failure_leaves_what_was_there(capsys, tmp_path):
    out = tmp_path / "earlier"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "empty.txt").write_text("")
    # --force passes the refusal; the replay then fails on its log directory
    assert main(["replay", str(tmp_path / "nowhere"), "--out", str(out), "--force"]) == 2
    assert "run.json" in _line(capsys)
    # a directory that was there is left as it was, its empty file included
    assert sorted(p.name for p in out.iterdir()) == ["empty.txt", "notes.txt"]


def test_a_failed_command_removes_the_directories_it_created(capsys, tmp_path):
    """``ampc run`` on a device that does not open left OUT with a 0-byte bridge.log."""
    out = tmp_path / "a" / "b" / "run"
    device = tmp_path / "no" / "ttyACM0"
    argv = ["run", "--channel", f"slcan:{device}", "--scenario", SCENARIO, "--quiet"]
    assert main([*argv, "--out", str(out)]) == 2
    assert _line(capsys).startswith("ampc: error: --channel: ")
    assert not (tmp_path / "a").exists()  # OUT and the parents it created
    # a replay that fails: its --out is gone too
    assert main(["replay", str(tmp_path / "nowhere"), "--out", str(tmp_path / "r")]) == 2
    assert "run.json" in _line(capsys)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_run_with_force_still_clears_an_earlier_runs_logs(capsys, tmp_path):
    """Over an earlier run's OUT (--force), a run that fails before its first
    tick leaves none of that run's logs passing for its own."""
    out = tmp_path / "run"
    out.mkdir()
    for name in ("run.json", "ticks.parquet", "ticks.jsonl"):
        (out / name).write_text("an earlier run's")
    (out / "notes.txt").write_text("mine")
    device = tmp_path / "no" / "ttyACM0"
    argv = ["run", "--channel", f"slcan:{device}", "--scenario", SCENARIO, "--quiet"]
    assert main([*argv, "--out", str(out)]) == 2  # refused: nothing removed
    assert "not empty" in _line(capsys)
    assert (out / "run.json").exists()
    (out / "empty_but_mine.txt").write_text("")
    os.utime(out / "empty_but_mine.txt", (1e9, 1e9))  # from before the command
    assert main([*argv, "--out", str(out), "--force"]) == 2
    assert _line(capsys).startswith("ampc: error: --channel: ")
    # the earlier run's logs are gone, and no 0-byte bridge.log of this one is left
    assert sorted(p.name for p in out.iterdir()) == ["empty_but_mine.txt", "notes.txt"]


def test_a_sweep_resumes_its_own_out_and_force_never_mixes_two(capsys, tmp_path, nothing_compiles):
    out = tmp_path / "s"
    out.mkdir()
    (out / "sweep.json").write_text(json.dumps({"spec": {"family": "generated"}}))
    argv = ["sweep", "--family", "cruise_step", "--cases", "4", "--quiet", "--out", str(out)]
    for extra in ([], ["--force"]):  # a sweep's out: the sweep's own check, --force or not
        assert main([*argv, *extra]) == 2
        line = _line(capsys)
        assert line.startswith("ampc: error: --out: ") and "holds a different sweep" in line


def test_claim_dir_notes_only_what_it_created(tmp_path):
    outdir.begin()
    assert outdir.claim_dir(str(tmp_path / "x" / "y")) is None
    (tmp_path / "x" / "y" / "bridge.log").write_text("")
    (tmp_path / "keep").mkdir()
    (tmp_path / "keep" / "a").write_text("")
    os.utime(tmp_path / "keep" / "a", (1e9, 1e9))  # there before the command
    assert outdir.claim_dir(str(tmp_path / "keep"), force=True) is None
    (tmp_path / "keep" / "b").write_text("")  # the command's, empty
    (tmp_path / "keep" / "c").write_text("c")  # the command's
    outdir.finish(1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep"]
    assert sorted(p.name for p in (tmp_path / "keep").iterdir()) == ["a", "c"]
    # success keeps everything, empty or not
    outdir.begin()
    assert outdir.claim_dir(str(tmp_path / "z")) is None
    outdir.finish(0)
    assert (tmp_path / "z").is_dir()
    f = tmp_path / "file"
    f.write_text("x")
    assert "not a directory" in outdir.claim_dir(str(f))
