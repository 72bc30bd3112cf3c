"""Input validation of ``ampc simulate`` / ``ampc demo`` (ampc_jax.reporting); no simulation runs."""

import subprocess
import sys

import pytest

from ampc_jax.cli import build_parser, main
from ampc_jax.reporting import _parse_settings
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
        ("--duration", "two", "expected a number"),
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
    ],
)
def test_argparse_rejects_bad_numbers(capsys, tmp_path, flag, value, expected):
    with pytest.raises(SystemExit) as exc:
        main([*BASE, flag, value, "--out", str(tmp_path / "x")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: " in err and expected in err, err
    assert not (tmp_path / "x").exists()


def test_argparse_accepts_the_edges():
    args = build_parser().parse_args(
        [*BASE, "--duration", "0.05", "--mu", "2", "--max-iter", "1", "--tol-primal", "1e-12",
         "--tol-dual", "3", "--repeats", "1", "--relaxation", "1.9"]
    )  # fmt: skip
    assert (args.duration, args.mu, args.max_iter, args.repeats) == (0.05, 2.0, 1, 1)
    assert (args.tol_primal, args.tol_dual, args.relaxation) == (1e-12, 3.0, 1.9)


@pytest.mark.parametrize(
    ("item", "expected"),
    [
        ("horizon=0", "--set horizon=0: expected an integer N_p >= 1"),
        ("horizon=1.5", "'1.5' is not a valid int"),
        ("dt=0", "--set dt=0: expected a positive prediction step"),
        ("dt=nan", "--set dt=nan: expected a finite number"),
        ("q_yrt=-5", "--set q_yrt=-5: expected a weight >= 0"),
        ("q_lst=inf", "--set q_lst=inf: expected a finite number"),
        ("r_fdb=0", "--set r_fdb=0: expected a weight > 0"),
        ("fdb_max=-1", "--set fdb_max=-1: expected a torque bound >= 0"),
        ("literal=maybe", "--set literal=maybe: expected true or false"),
        ("q_vsc=1", "FIELD one of"),
    ],
)
def test_cli_rejects_bad_settings(capsys, tmp_path, item, expected):
    code = main([*BASE, "--duration", "1", "--set", item, "--out", str(tmp_path / "x")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: ") and expected in err, err
    assert not (tmp_path / "x").exists()  # refused before anything ran or was written


def test_parse_settings_values():
    c = CruiseSettings()
    assert _parse_settings(["q_yrt=0", "horizon=1", "literal=yes"], c) == {
        "q_yrt": 0.0,
        "horizon": 1,
        "literal": True,
    }
    assert _parse_settings(["literal=off", "fdb_max=0"], c) == {"literal": False, "fdb_max": 0.0}
    with pytest.raises(ValueError, match=r"^--set slip_des=1: expected a slip ratio in \[0, 1\)"):
        _parse_settings(["slip_des=1"], StabilitySettings())


def test_unwritable_output_directory_is_a_usage_error(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = blocker / "sub"
    assert main([*BASE, "--duration", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: cannot create the output directory" in err, err
    assert main(["demo", "--quiet", "--out", str(out)]) == 2
    assert "cannot create the output directory" in capsys.readouterr().err


@pytest.mark.timeout(180)
def test_bad_duration_exits_2_without_traceback(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "ampc_jax.cli", *BASE, "--duration", "0", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=170,
    )
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "argument --duration: expected a finite time of at least one control period" in r.stderr


def test_progress_bars_only_on_a_terminal(monkeypatch):
    """Bars show on a terminal, not in redirected output (no carriage-return
    debris in logs), and never with --quiet."""
    import io

    from ampc_jax import reporting as R

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", Terminal())
    assert not R._bar(3, quiet=False).disable
    assert R._bar(3, quiet=True).disable
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert R._bar(3, quiet=False).disable
