"""Input validation of ``ampc simulate`` / ``ampc demo`` (ampc_jax.cli.simulate,
ampc_jax.cli.args); no simulation runs."""

import subprocess
import sys

import pytest

from ampc_jax.cli import build_parser, main
from ampc_jax.cli.simulate import _parse_floats, _parse_settings
from ampc_jax.testing.budget import budget
from ampc_jax.vehicle import CruiseSettings, StabilitySettings

pytestmark = pytest.mark.timeout(120)

BASE = ["simulate", "cruise_lane_change", "--quiet", "--no-timing"]


@pytest.mark.parametrize(
    ("flag", "value", "expected"),
    [
        ("--duration", "0", "at least one control period (0.05 s)"),
        ("--duration", "0.01", "at least one control period"),
        ("--duration", "-1", "at least one control period"),
        ("--duration", "nan", "finite time"),
        ("--duration", "inf", "finite time"),
        ("--duration", "two", "expected a number, got 'two'"),
        ("--duration", "1e12", "at most 3600 s (72000 control steps) in one run"),
        ("--mu", "nan", "finite road friction in (0, 2]"),
        ("--mu", "-1", "(0, 2]"),
        ("--mu", "0", "(0, 2]"),
        ("--mu", "3", "(0, 2]"),
        ("--max-iter", "0", "integer >= 1"),
        ("--max-iter", "1.5", "expected an integer"),
        ("--tol-primal", "-1", "positive finite"),
        ("--tol-primal", "0", "positive finite"),
        ("--tol-dual", "nan", "positive finite"),
        ("--repeats", "0", "integer >= 1"),
        ("--integrated-rho-scale", "0", "positive finite"),
        ("--warm-shift", "2", "invalid choice: 2"),
        ("--anderson", "4", "invalid choice: 4"),
    ],
)
def test_argparse_rejects_bad_numbers(capsys, tmp_path, flag, value, expected):
    with pytest.raises(SystemExit) as exc:
        main([*BASE, flag, value, "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    last = err.splitlines()[-1]
    assert err.startswith("usage: ampc simulate")  # argparse errors print the usage first
    assert last.startswith(f"ampc: error: {flag}: ") and expected in last, err
    assert "argument " not in err and err.count(f"{flag}: ") == 1, err
    assert not (tmp_path / "x").exists()


def test_argparse_accepts_the_edges():
    args = build_parser().parse_args(
        [*BASE, "--duration", "0.05", "--mu", "2", "--max-iter", "1", "--tol-primal", "1e-12",
         "--tol-dual", "3", "--repeats", "1", "--relaxation", "1.9"]
    )  # fmt: skip
    assert (args.duration, args.mu, args.max_iter, args.repeats) == (0.05, 2.0, 1, 1)
    assert (args.tol_primal, args.tol_dual, args.relaxation) == (1e-12, 3.0, 1.9)
    assert args.out == "out" and args.formulation == "local_explicit"
    assert build_parser().parse_args(["demo"]).out == "demo"


@pytest.mark.parametrize(
    ("item", "expected"),
    [
        ("horizon=0", "--set horizon=0: expected an integer N_p >= 1"),
        ("horizon=1.5", "--set horizon=1.5: '1.5' is not a valid int"),
        ("dt=0", "--set dt=0: expected a positive prediction step"),
        ("dt=nan", "--set dt=nan: expected a finite number"),
        ("q_yrt=-5", "--set q_yrt=-5: expected a weight >= 0"),
        ("q_lst=inf", "--set q_lst=inf: expected a finite number"),
        ("r_fdb=0", "--set r_fdb=0: expected a weight > 0"),
        ("fdb_max=-1", "--set fdb_max=-1: expected a torque bound >= 0"),
        ("literal=maybe", "--set literal=maybe: expected true or false"),
        ("q_vsc=1", "--set q_vsc=1: expected FIELD=VALUE with FIELD one of"),
        ("horizon", "--set horizon: expected FIELD=VALUE"),
    ],
)
def test_cli_rejects_bad_settings(capsys, tmp_path, item, expected):
    code = main([*BASE, "--duration", "1", "--set", item, "--out", str(tmp_path / "x")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ampc: error: {expected}"), err
    assert not (tmp_path / "x").exists()  # refused before anything ran or was written


def test_parse_settings_values():
    c = CruiseSettings()
    assert _parse_settings(["q_yrt=0", "horizon=1", "literal=yes"], c) == {
        "q_yrt": 0.0,
        "horizon": 1,
        "literal": True,
    }
    assert _parse_settings(["literal=off", "fdb_max=0"], c) == {"literal": False, "fdb_max": 0.0}
    assert _parse_settings([], c) == {}
    with pytest.raises(ValueError, match=r"^--set slip_des=1: expected a slip ratio in \[0, 1\)"):
        _parse_settings(["slip_des=1"], StabilitySettings())
    # a field of the other example is named as unknown, with this example's fields
    with pytest.raises(ValueError, match=r"^--set slip_des=0.1: expected FIELD=VALUE .*'q_lst'"):
        _parse_settings(["slip_des=0.1"], c)


def test_parse_floats():
    assert _parse_floats("--rho-scale", None) is None
    assert _parse_floats("--rho-scale", "0.5") == 0.5
    assert _parse_floats("--rho-scale", "1,0.5") == (1.0, 0.5)
    with pytest.raises(ValueError, match=r"^--rho-scale\b.*: expected a number or comma"):
        _parse_floats("--rho-scale", "abc")


def test_unwritable_output_directory_is_a_usage_error(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = blocker / "sub"
    assert main([*BASE, "--duration", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ampc: error: --out {out}: cannot create the output directory"), err
    assert main(["demo", "--quiet", "--out", str(out)]) == 2
    assert "cannot create the output directory" in capsys.readouterr().err


def test_unknown_scenario_is_named(capsys, tmp_path):
    assert main(["simulate", "cruise_lane", "--quiet", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: unknown scenario 'cruise_lane'; expected one of")
    assert "cruise_lane_change" in err and not (tmp_path / "x").exists()


@pytest.mark.timeout(180)
def test_bad_duration_exits_2_without_traceback(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "ampc_jax.cli", *BASE, "--duration", "0", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=budget(170),
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.splitlines()[-1].startswith(
        "ampc: error: --duration: expected a finite time of at least one control period"
    )


def test_progress_bars_only_on_a_terminal(monkeypatch):
    """Bars show on a terminal, not in redirected output (no carriage-return
    debris in logs), and never with --quiet."""
    import io

    from tqdm import tqdm

    from ampc_jax.cli import simulate as S
    from ampc_jax.cli.args import progress_disabled

    assert progress_disabled(True) is True and progress_disabled(False) is None

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", Terminal())
    assert not tqdm(total=3, disable=progress_disabled(False)).disable
    assert tqdm(total=3, disable=progress_disabled(True)).disable
    assert not S._bar(3, quiet=False).disable  # the bar the commands draw
    assert S._bar(3, quiet=True).disable
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert tqdm(total=3, disable=progress_disabled(False)).disable
    assert S._bar(3, quiet=False).disable
