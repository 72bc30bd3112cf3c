"""The deployment commands check their optional modules first: a missing one is
one ``ampc: error:`` line naming it and the one install command, exit 2,
before anything compiles, opens or is written; the runtime extra brings
every module checked but the bridge."""

from __future__ import annotations

import importlib.metadata
import re
import sys
import tomllib
from pathlib import Path

import pytest

from ampc_jax.cli import extras, main

pytestmark = pytest.mark.timeout(120)

SCENARIO = "cruise_lane_change"
EXTRA = "python -m pip install -e '.[runtime]'"
BOTH = "python -m pip install ./can_bridge -e '.[runtime]'"
BRIDGE = "python -m pip install ./can_bridge;"


@pytest.fixture
def nothing_starts(monkeypatch):
    """Fail the test if anything compiles, opens or runs after the check."""
    import ampc_jax.runtime.artefact as artefact
    import ampc_jax.runtime.replay as replay
    import ampc_jax.runtime.runner as runner
    import ampc_jax.runtime.step as step

    def refuse(*args, **kwargs):
        raise AssertionError("started after a missing module")

    monkeypatch.setattr(step.RuntimeStep, "__post_init__", refuse)
    monkeypatch.setattr(runner, "run_controller", refuse)
    monkeypatch.setattr(artefact, "export_step", refuse)
    monkeypatch.setattr(replay, "replay_run", refuse)


def _hide(monkeypatch, *names):
    """Make ``import name`` fail as for a module that is not installed."""
    for name in names:
        monkeypatch.setitem(sys.modules, name, None)


def _line(capsys) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("ampc: error: "), err
    return lines[0]


def _cases(tmp_path):
    out = str(tmp_path / "out")
    run = ["run", "--channel", "slcan-pty:", "--scenario", SCENARIO, "--out", out]
    return {
        # (argv, hidden modules, the modules named, the install command)
        "run, no bridge": (run, ["can_bridge"], ["can_bridge"], BRIDGE),
        "run --with-plant": ([*run, "--with-plant"], ["cantools"], ["cantools"], EXTRA),
        "run --with-plant, nothing": (
            [*run, "--with-plant"],
            ["can_bridge", "can", "e2e"],
            ["can_bridge", "can (python-can)", "e2e (autosar-e2e)"],
            BOTH,
        ),
        "run --artefact": ([*run, "--artefact", "x.ampc"], ["flatbuffers"], ["flatbuffers"], EXTRA),
        "plant": (
            ["plant", "--channel", "slcan:/dev/null", "--scenario", SCENARIO, "--out", out],
            ["serial"],
            ["serial (pyserial"],
            EXTRA,
        ),
        "export": (
            ["export", "--scenario", SCENARIO, "--out", str(tmp_path / "out.ampc")],
            ["flatbuffers"],
            ["flatbuffers"],
            EXTRA,
        ),
        "replay": (["replay", str(tmp_path), "--out", out], ["can"], ["can (python-can)"], EXTRA),
        "replay --candump": (
            ["replay", "--candump", "x.log", "--scenario", SCENARIO, "--out", out],
            ["cantools", "can_bridge"],
            ["can_bridge", "cantools"],
            BOTH,
        ),
    }


@pytest.mark.parametrize("case", list(_cases(Path("x"))))
def test_a_missing_module_is_named_with_the_install_command(
    capsys, tmp_path, monkeypatch, nothing_starts, case
):
    argv, hidden, named, command = _cases(tmp_path)[case]
    _hide(monkeypatch, *hidden)
    assert main(argv) == 2
    line = _line(capsys)
    assert line.startswith(f"ampc: error: {argv[0]}: missing module"), line
    for name in named:
        assert name in line, line
    assert command in line and "from the repository root" in line, line
    assert ("Rust toolchain" in line) == ("can_bridge" in hidden), line
    assert "Traceback" not in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # nothing written


def test_what_is_installed_passes_the_check():
    # the test environment has the runtime extra and the bridge
    for modules in (extras.PLANT, extras.BUS, extras.EXPORT, extras.BRIDGE):
        assert extras.missing_message("run", modules) is None


def test_the_runtime_extra_brings_every_module_checked_but_the_bridge():
    """The command a refusal prints installs what it names: every module the
    check imports (the bridge aside, built from ./can_bridge) is provided by a
    distribution of pyproject.toml's runtime extra."""
    pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
    extra = tomllib.loads(pyproject.read_text())["project"]["optional-dependencies"]["runtime"]
    wanted = {re.split(r"[<>=!~\[ ;]", r, maxsplit=1)[0].lower() for r in extra}
    provides = importlib.metadata.packages_distributions()
    checked = set(extras.PLANT + extras.BUS + extras.EXPORT) - {"can_bridge"}
    for module in sorted(checked):
        dists = {d.lower() for d in provides.get(module, [])}
        assert dists & wanted, (module, dists, wanted)
    assert (Path(pyproject.parent) / extras.BRIDGE_DIR / "pyproject.toml").is_file()
