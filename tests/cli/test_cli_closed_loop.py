"""Tests of ``ampc simulate`` (ampc_jax.cli.simulate): closed-loop runs from the
command line, their outputs, --compare, --disable and bad solver options."""

import json

import pytest

from ampc_jax.cli import main

pytestmark = pytest.mark.timeout(480)  # a closed loop, its shadow and replay compile

SHORT = 2.0  # s simulated (40 control steps)


def test_cli_simulate_writes_outputs(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(
        ["simulate", "cruise_lane_change", "--duration", str(SHORT), "--out", str(out),
         "--quiet", "--repeats", "1"]
    )  # fmt: skip
    assert code == 0
    for name in ("timeseries.csv", "metrics.json", "vehicle_response.png",
                 "wheel_torques.png", "convergence.png"):  # fmt: skip
        assert (out / name).stat().st_size > 0, name
    assert not (out / "baseline").exists()  # only with --compare
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == 40 and m["fallbacks"] == 0
    assert m["r_time_median"] > 0
    header = (out / "timeseries.csv").read_text().splitlines()[0].split(",")
    assert {"t", "v_x", "yaw_rate", "e_sub_DTR", "iterations", "r_time"} <= set(header)
    assert "e_sub" in capsys.readouterr().out


def test_cli_rejects_unknown_objective(capsys):
    code = main(["simulate", "cruise_lane_change", "--disable", "WSC", "--out", "x", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: --disable: 'WSC' is not an objective of the cruise"), err


def test_cli_rejects_bad_solver_options(capsys):
    base = ["simulate", "cruise_lane_change", "--out", "x", "--quiet"]
    assert main([*base, "--rho-scale", "1,2,3"]) == 2
    err = capsys.readouterr().err
    assert "ampc: error: --rho-scale: expected a float or 2 values" in err, err
    assert main([*base, "--rho-scale", "1,x"]) == 2
    assert "--rho-scale" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # argparse checks the range: exit 2
        main([*base, "--relaxation", "2"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "ampc: error: --relaxation: expected a value in (0, 2)" in err, err
    with pytest.raises(SystemExit):  # argparse: choices 0, 1
        main([*base, "--warm-shift", "2"])
    assert "--warm-shift" in capsys.readouterr().err


def test_cli_compare_of_a_baseline_is_refused(tmp_path, capsys):
    code = main(
        ["simulate", "stability_dlc", "--formulation", "none", "--compare", "--quiet",
         "--out", str(tmp_path / "x")]
    )  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: --compare: this run already is"), err
    assert not (tmp_path / "x").exists()  # refused before anything runs or is written


@pytest.mark.slow  # the --compare layout is tests/cli/test_cli_friction.py's in the default run
def test_cli_compare_writes_the_baseline_and_overlays_it(tmp_path, capsys):
    """The paper's stability comparison (fig_VSC_straight_vehicle): VSC+WSC
    against the driver alone, who spins the rear wheels on mu = 0.3."""
    out = tmp_path / "cmp"
    code = main(
        ["simulate", "stability_launch_brake", "--duration", "2", "--compare", "--no-timing",
         "--quiet", "--out", str(out)]
    )  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    b = json.loads((out / "baseline" / "metrics.json").read_text())
    assert m["objectives"] == ["VSC", "WSC"] and b["formulation"] == "none"
    assert b["steps"] == m["steps"] == 40
    assert b["rear_slip_abs_max"] > 1.0 > 0.3 > m["rear_slip_abs_max"]
    assert (out / "baseline" / "timeseries.csv").stat().st_size > 0
    for name in ("vehicle_response.png", "yaw_error.png", "convergence.png"):
        assert (out / name).stat().st_size > 0, name
    line = next(x for x in text.splitlines() if x.startswith("VSC+WSC against the driver alone"))
    assert f"rear |slip| max {b['rear_slip_abs_max']:.4g} -> {m['rear_slip_abs_max']:.4g}" in line


def test_simulate_with_formulation_1(tmp_path, capsys):
    out = tmp_path / "f1"
    args = ["simulate", "cruise_lane_change", "--formulation", "fully_distributed"]
    code = main([*args, "--duration", "2", "--no-timing", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["formulation"] == "fully_distributed"
    assert metrics["e_sub_p95"] < 20.0
