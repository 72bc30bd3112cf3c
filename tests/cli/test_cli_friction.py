"""What using ``ampc`` feels like: help texts, one error format, warnings as lines,
ignored flags said so, consistent output folders, refusals that say what to do."""

import argparse
import json
import re
import subprocess
import sys
from dataclasses import fields

import pytest

from ampc_jax.admm import SolverParams
from ampc_jax.cli import build_parser, main
from ampc_jax.closed_loop import SimConfig
from ampc_jax.testing.budget import budget

pytestmark = pytest.mark.timeout(300)


def _subcommands():
    parser = build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def _options():
    """(command, action) for every option of every sub-command, less -h/--help."""
    for name, sub in _subcommands().items():
        for action in sub._actions:
            if not action.option_strings:  # a positional
                continue
            if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
                continue
            yield name, action


# ----------------------------------------------------------------------- 1. help texts
def test_every_option_states_its_default():
    options = list(_options())
    assert {name for name, _ in options} == {
        "solve",
        "simulate",
        "demo",
        "run",
        "plant",
        "export",
        "replay",
        "sweep",
        "sweep-merge",
        "tune",
    }
    assert len(options) > 30
    for name, action in options:
        text = action.help or ""
        if action.required:  # a required option has no default: it says so
            assert text.endswith("(required)"), (name, action.option_strings, text)
            continue
        assert "default" in text, (name, action.option_strings, text)
        # the notes' form: the help ends with "(default: ...)"
        assert "(default: " in text and text.endswith(")"), (name, action.option_strings, text)


def test_paper_labels_in_help_texts_carry_words():
    rho = next(a for n, a in _options() if n == "solve" and "--rho" in a.option_strings)
    assert "optimal rho" in rho.help
    label = re.compile(r"(paper )?eq\.\s?\w+")
    for name, action in _options():
        text = action.help or ""
        if label.search(text):
            words = re.sub(r"\([^)]*\)", "", label.sub("", text)).split()
            assert len(words) >= 3, (name, action.option_strings, text)


def test_version(capsys):
    from importlib.metadata import version

    import ampc_jax

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out == f"ampc-jax {ampc_jax.__version__}\n"
    assert ampc_jax.__version__ == version("ampc-jax")


# ---------------------------------------------------------------- 2. one error format
# the library's field names the messages must not leak (the flags replace them)
FIELD_NAMES = sorted(
    {f.name for f in fields(SimConfig) if "_" in f.name}
    | {f for f in SolverParams._fields if "_" in f}
)


def _flag_count(flag, text):
    return len(re.findall(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", text))


@pytest.mark.parametrize(
    ("flag", "argv"),
    [
        ("--rho", ["solve", "cruise_control", "--rho", "abc"]),
        ("--tol", ["solve", "cruise_control", "--tol", "-1"]),
        ("--max-iter", ["solve", "cruise_control", "--max-iter", "0"]),
        ("--relaxation", ["solve", "cruise_control", "--relaxation", "2.5"]),
        ("--mu", ["simulate", "cruise_lane_change", "--mu", "5"]),
        ("--rho-scale", ["simulate", "cruise_lane_change", "--rho-scale", "1,2,3"]),
        ("--relaxation", ["simulate", "cruise_lane_change", "--relaxation", "2.5"]),
        ("--disable", ["simulate", "cruise_lane_change", "--disable", "VSC"]),
        ("--disable", ["simulate", "cruise_lane_change", "--disable", "LST", "--disable", "YRT"]),
        ("--tol-primal", ["simulate", "stability_dlc", "--tol-primal", "0"]),
        (
            "--integrated-rho-scale",
            ["simulate", "cruise_lane_change", "--integrated-rho-scale", "-1"],
        ),
        ("--compare", ["simulate", "stability_dlc", "--formulation", "none", "--compare"]),
        ("--rho-scale", ["simulate", "cruise_lane_change", "--rho-scale", "abc"]),
    ],
)
def test_one_error_format(capsys, tmp_path, flag, argv):
    out = tmp_path / "out"
    extra = ["--quiet", "--out", str(out)] if argv[0] == "simulate" else []
    try:
        code = main([*argv, *extra])
    except SystemExit as exc:  # argparse's own checks
        code = exc.code
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert code == 2, err
    assert last.startswith(f"ampc: error: {flag}: "), err
    assert _flag_count(flag, last) == 1, last
    leaked = [f for f in FIELD_NAMES if re.search(rf"\b{f}\b", last)]
    assert not leaked, last
    assert "Traceback" not in err and not out.exists()


# ------------------------------------------------------------------- problem files
def _problem(tmp_path, name, objective0=None, drop_bounds=()):
    d = {
        "horizon": 4,
        "A": [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.9]],
        "x0": [0.0, 0.0, 0.0],
        "agents": [
            {"name": "a", "B": [[0.0], [1.0], [0.0]], "R": [0.1], "lb": [-1], "ub": [1]},
            {"name": "b", "B": [[0.0], [0.5], [1.0]], "R": [0.2], "lb": [-1], "ub": [1]},
            {"name": "c", "B": [[0.0], [0.0], [1.0]], "R": [0.3], "lb": [-2], "ub": [2]},
        ],
        "objectives": [
            {"name": "pos", "C": [[1.0, 0.0, 0.0]], "Q": [1.0], "ref": [1.0], **(objective0 or {})},
            {"name": "z", "C": [[0.0, 0.0, 1.0]], "Q": [2.0], "ref": [0.5]},
        ],
    }
    for i in drop_bounds:
        del d["agents"][i]["lb"], d["agents"][i]["ub"]
    path = tmp_path / name
    path.write_text(json.dumps(d))
    return str(path)


# --------------------------------------------------------- 3. warnings as one line
def test_group_missing_an_influencing_agent_warns_in_one_line(tmp_path):
    """Objective pos lists only agent a, but b drives its output too: one
    ``ampc: warning:`` line, no Python warning with its source line."""
    path = _problem(tmp_path, "group.json", objective0={"agents": ["a"]})
    r = subprocess.run(
        [sys.executable, "-m", "ampc_jax.cli", "solve", path, "--formulation", "integrated",
         "--json"],
        capture_output=True,
        text=True,
        timeout=budget(120),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    json.loads(r.stdout)
    lines = r.stderr.splitlines()
    warnings = [x for x in lines if x.startswith("ampc: warning: ")]
    assert len(warnings) == 1, r.stderr
    assert "objectives[0] (pos)" in warnings[0] and "['b']" in warnings[0]
    assert "UserWarning" not in r.stderr and "ProblemWarning" not in r.stderr
    assert "warnings.warn" not in r.stderr and ".py:" not in r.stderr, r.stderr


# ----------------------------------------------------------- 4. ignored flags said so
def test_solver_with_local_explicit_is_said_to_be_ignored(capsys, tmp_path):
    path = _problem(tmp_path, "p.json")
    assert (
        main(["solve", path, "--formulation", "local_explicit", "--solver", "osqp", "--json"]) == 0
    )
    captured = capsys.readouterr()
    assert "ampc: --solver ignored by --formulation local_explicit" in captured.err.splitlines()
    result = json.loads(captured.out)
    assert result["formulation"] == "local_explicit" and set(result["rho"]) == {"pos", "z"}


# --------------------------------------------------- 6. refusals say what to do
def test_problem_without_bounds_refused_by_local_explicit_says_what_to_give(capsys, tmp_path):
    path = _problem(tmp_path, "free.json", drop_bounds=(2,))
    assert main(["solve", path, "--json"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    (line,) = captured.err.splitlines()
    assert line.startswith(f"ampc: error: {path}: agents[2] (c): ")
    assert "give the agent finite 'lb' and 'ub'" in line
    assert "integrated formulation" in line  # the other way out


# ------------------------------------------------------- 5. output folder layout
def _layout(out):
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.suffix in (".csv", ".json"))


LAYOUT = ["baseline/metrics.json", "baseline/timeseries.csv", "metrics.json", "timeseries.csv"]


def test_simulate_compare_output_layout(capsys, tmp_path):
    out = tmp_path / "D"
    code = main(
        ["simulate", "stability_launch_brake", "--compare", "--duration", "1", "--no-timing",
         "--quiet", "--out", str(out)]
    )  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert _layout(out) == LAYOUT
    m = json.loads((out / "metrics.json").read_text())
    b = json.loads((out / "baseline" / "metrics.json").read_text())
    assert m["objectives"] == ["VSC", "WSC"] and b["formulation"] == "none"
    assert m["steps"] == b["steps"] == 20
    assert f"baseline in {out / 'baseline'}" in text
    assert {p.name for p in out.glob("*.png")} == {
        "vehicle_response.png",
        "wheel_torques.png",
        "convergence.png",
        "yaw_error.png",
    }


@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:invalid value encountered")
def test_demo_writes_the_same_layout(capsys, tmp_path, monkeypatch):
    """``ampc demo`` = ``simulate cruise_lane_change --compare`` with the r_time
    replay: the same folders (no lst_only/, no combined metrics.json). Runs cut
    to 1 s here (the full demo takes about 15 s more)."""
    from ampc_jax import closed_loop

    full = closed_loop.prepare  # the closed loops' lowering: their duration

    def short(spec, config=None, *, duration=None, **kw):
        return full(spec, config, duration=1.0 if duration is None else duration, **kw)

    monkeypatch.setattr(closed_loop, "prepare", short)
    out = tmp_path / "demo"
    assert main(["demo", "--quiet", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert _layout(out) == LAYOUT
    m = json.loads((out / "metrics.json").read_text())
    b = json.loads((out / "baseline" / "metrics.json").read_text())
    assert m["scenario"] == b["scenario"] == "cruise_lane_change"
    assert m["objectives"] == ["LST", "YRT"] and b["objectives"] == ["LST"]
    assert m["steps"] == 20 and m["r_time_median"] > 0  # the replay ran
    header = (out / "timeseries.csv").read_text().splitlines()[0].split(",")
    assert "r_time" in header
    assert "LST+YRT against LST:" in text and f"outputs in {out}" in text
    assert "load-sensitive, meaningful on an idle machine" in text.splitlines()[0]
    assert m["r_time_load"]["cores"] >= 1
    # --no-timing: no replay (the closed loops are compiled already: no compile here)
    assert main(["demo", "--quiet", "--no-timing", "--out", str(tmp_path / "fast")]) == 0
    text = capsys.readouterr().out
    assert "r_time replay skipped (--no-timing)" in text.splitlines()[0]
    fast = json.loads((tmp_path / "fast" / "metrics.json").read_text())
    assert "r_time_median" not in fast and fast["steps"] == 20
