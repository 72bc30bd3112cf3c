"""A tuned-parameters file records the solver settings it was tuned under, and a
command applying it under other settings warns once; `--set` keeps the file's
bounds."""

import json

import pytest

from ampc_jax.cli import main
from ampc_jax.io import read_params, write_params
from ampc_jax.io.params_file import tuned_for_differences


def _warnings(err):
    return [line for line in err.splitlines() if line.startswith("ampc: warning: ")]


@pytest.mark.timeout(60)
def test_differences_name_each_setting():
    tuned = write_params(
        "/dev/null",
        tuned_for={"anderson": 0, "relaxation": 1.5, "rho_scale": [1.0, 0.5], "dtype": "float64"},
    )
    same = {"anderson": 0, "relaxation": 1.5, "rho_scale": (1.0, 0.5), "dtype": "float64"}
    assert tuned_for_differences(tuned, same) == []
    diff = tuned_for_differences(tuned, {**same, "anderson": 3, "rho_scale": 1.0})
    assert diff == ["anderson: tuned 0, running 3", "rho_scale: tuned [1.0, 0.5], running 1.0"]
    assert tuned_for_differences(write_params("/dev/null"), same) == []  # nothing recorded


@pytest.mark.timeout(60)
def test_a_bad_tuned_for_is_refused_naming_the_field(tmp_path):
    for doc, field in (
        ({"anderson": -1}, "tuned_for.anderson"),
        ({"relaxation": "fast"}, "tuned_for.relaxation"),
        ({"colour": 1}, "tuned_for.colour"),
        ([1], "tuned_for"),
    ):
        path = tmp_path / "p.json"
        path.write_text(json.dumps({"format": "ampc-params/1", "tuned_for": doc}))
        with pytest.raises(ValueError, match=field):
            read_params(path)


@pytest.mark.timeout(120)
def test_solve_warns_once_when_the_file_was_tuned_with_anderson(tmp_path, capsys):
    path = tmp_path / "params.json"
    write_params(path, tuned_for={"anderson": 3, "formulation": "local_explicit"})
    argv = ["solve", "cruise_control", "--json", "--params", str(path)]
    assert main(argv) == 0
    lines = _warnings(capsys.readouterr().err)
    assert lines == [
        f"ampc: warning: --params {path} was tuned for other solver settings than this "
        f"command runs (anderson: tuned 3, running 0): its numbers may not pay off here"
    ]
    assert main([*argv, "--anderson", "3"]) == 0
    assert _warnings(capsys.readouterr().err) == []


@pytest.mark.timeout(300)
def test_simulate_warns_for_a_file_tuned_without_anderson(tmp_path, capsys):
    path = tmp_path / "params.json"
    write_params(
        path,
        example="cruise",
        rho_scale=[1.0, 0.5],
        relaxation=1.5,
        tuned_for={"anderson": 0, "dtype": "float64", "tol": 1.0},
    )
    code = main(
        ["simulate", "cruise_lane_change", "--duration", "0.2", "--params", str(path), "--out",
         str(tmp_path / "run"), "--quiet", "--no-timing", "--no-shadow"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 0, err
    lines = _warnings(err)
    assert len(lines) == 1 and "anderson: tuned 0, running 3" in lines[0], err


@pytest.mark.timeout(60)
def test_simulate_set_keeps_the_params_file_bounds(tmp_path, capsys):
    code = main(
        ["simulate", "cruise_lane_change", "--set", "q_yrt=1e308", "--out", str(tmp_path / "r"),
         "--quiet"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert err.startswith("ampc: error: --set q_yrt=1e308: expected a value within a factor"), err
