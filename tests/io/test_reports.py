"""ampc_jax.io.reports: the per-step CSV, metrics.json (NaN as null) and the text
summaries, on one short closed-loop run."""

import csv
import json
import math
from dataclasses import replace

import numpy as np
import pytest

from ampc_jax.closed_loop import config_for, simulate
from ampc_jax.io.reports import (
    comparison_line,
    summary_lines,
    write_metrics,
    write_run,
    write_timeseries,
)
from ampc_jax.vehicle import WHEELS

pytestmark = pytest.mark.timeout(180)

SCENARIO = "cruise_lane_change"
STEPS = 20  # 1 s: ends before the focus window (7..13 s), so the focus numbers are NaN


@pytest.fixture(scope="module")
def run():
    """LST+YRT with the shadow integrated MPC (e_sub), 1 s."""
    return simulate(SCENARIO, duration=1.0)


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))


def test_write_timeseries_columns_and_rows(run, tmp_path):
    path = write_timeseries(run, tmp_path / "sub" / "timeseries.csv")  # creates the folder
    assert path == tmp_path / "sub" / "timeseries.csv"
    header, *rows = _rows(path)
    assert len(rows) == STEPS and all(len(r) == len(header) for r in rows)
    names = run.config.input_names  # DTR, RTV, FDB_L, FDB_R
    expected = (
        ["t", "X", "Y", "path_y", "psi", "v_x", "v_ref", "v_y", "yaw_rate", "yaw_ref", "steer",
         "driver_torque", "omega_ref"]
        + [f"{p}_{w}" for w in WHEELS for p in ("omega", "slip")]
        + [f"u_{n}" for n in names]
        + [f"u_shadow_{n}" for n in names]
        + [f"e_sub_{n}" for n in names]
        + [f"torque_{w}" for w in WHEELS]
        + ["iterations", "status", "shadow_iterations", "shadow_status", "fallback"]
    )  # fmt: skip
    assert header == expected
    col = {n: [r[k] for r in rows] for k, n in enumerate(header)}
    np.testing.assert_allclose([float(x) for x in col["t"]], run.log.t, rtol=1e-8)
    np.testing.assert_allclose([float(x) for x in col["v_x"]], run.log.v_x, rtol=1e-8)
    assert [int(x) for x in col["iterations"]] == [int(i) for i in run.log.iterations]
    assert set(col["fallback"]) == {"0"}
    # NaN is an empty cell (cruise control logs no wheel-speed reference)
    assert set(col["omega_ref"]) == {""}
    assert all(x != "" for x in col["e_sub_DTR"])  # the shadow ran


def test_write_timeseries_with_timing_columns(run, tmp_path):
    k = np.arange(STEPS, dtype=float)
    timing = {
        "t_distributed": 1e-4 * (k + 1),
        "t_integrated": 2e-4 * (k + 1),
        "r_time": np.full(STEPS, 0.5),
        "integrated_iterations": np.arange(STEPS),
        "distributed_iterations": np.arange(STEPS),
    }
    header, *rows = _rows(write_timeseries(replace(run, timing=timing), tmp_path / "ts.csv"))
    assert header[-4:] == ["t_distributed_s", "t_integrated_s", "r_time", "integrated_iterations"]
    assert [r[header.index("r_time")] for r in rows] == ["0.5"] * STEPS
    assert rows[3][header.index("integrated_iterations")] == "3"


def test_write_metrics_writes_nan_as_null(run, tmp_path):
    m = run.metrics()
    nans = sorted(k for k, v in m.items() if isinstance(v, float) and math.isnan(v))
    assert "yaw_rms_focus" in nans and "e_sub_p95_focus" in nans  # the run ends before it
    path = write_metrics(m, tmp_path / "a" / "metrics.json")
    d = json.loads(path.read_text(), parse_constant=pytest.fail)  # strict JSON: no NaN
    assert all(d[k] is None for k in nans)
    assert d["steps"] == STEPS and d["objectives"] == ["LST", "YRT"]
    assert d["e_sub_p95"] == pytest.approx(m["e_sub_p95"]) and d["e_sub_p95"] is not None
    # numpy scalars, nested containers, tuples and non-finite numbers anywhere
    odd = {
        "a": np.float64("nan"),
        "b": [1.0, np.inf, np.float32(2.5)],
        "c": np.int64(3),
        "d": {"e": float("-inf"), 4: (np.int32(1), None)},
    }
    d = json.loads(
        write_metrics(odd, tmp_path / "odd.json").read_text(), parse_constant=pytest.fail
    )
    assert d == {"a": None, "b": [1.0, None, 2.5], "c": 3, "d": {"e": None, "4": [1, None]}}


def test_write_run_writes_both_files(run, tmp_path):
    ts, mj = write_run(run, tmp_path / "out")
    assert (ts, mj) == (tmp_path / "out" / "timeseries.csv", tmp_path / "out" / "metrics.json")
    assert ts.stat().st_size > 0 and json.loads(mj.read_text())["scenario"] == SCENARIO


def test_summary_lines_of_the_run(run):
    m = run.metrics()
    lines = summary_lines(m)
    assert m["dtype"] == "float64" and m["settings_changed"] == {}
    assert lines[0] == (
        f"{SCENARIO} [local_explicit; LST+YRT; N_p={m['horizon']}; warm start; float64]"
    )
    assert lines[1].startswith(
        "  solver          eps_r 1, eps_s 1, relaxation 1.5, rho_scale 1, 0.5"
    )
    assert "0 of 20 steps; the run ends before it: focus numbers n/a" in lines[2]
    e_sub = next(x for x in lines if x.startswith("  e_sub (Nm)"))
    assert f"p95 {m['e_sub_p95']:.3g}" in e_sub and "focus p95 n/a" in e_sub
    assert any(x.startswith("  iterations      p50 ") for x in lines)
    assert not any("r_time" in x for x in lines)  # no replay
    assert any(x.startswith("  yaw-rate rms ") and "(focus n/a)" in x for x in lines)
    assert not any("warning" in x for x in lines)
    # warnings of an unreliable run, one line each
    bad = dict(m, warnings=["3 of 20 control steps stopped at max_iter", "another"])
    assert [x for x in summary_lines(bad) if x.startswith("  warning: ")] == [
        "  warning: 3 of 20 control steps stopped at max_iter",
        "  warning: another",
    ]
    # an r_time replay adds its line
    timed = dict(m, r_time_median=0.9, r_time_p95=1.2, t_distributed_median_us=50.0,
                 t_integrated_median_us=55.0)  # fmt: skip
    (r_line,) = [x for x in summary_lines(timed) if x.startswith("  r_time")]
    assert "median 0.9  p95 1.2  (local_explicit 50 us vs integrated 55 us)" in r_line


def test_summary_header_of_driver_alone_and_disabled_objective(run):
    none = replace(run, config=config_for(SCENARIO, formulation="none")).metrics()
    lines = summary_lines(none)
    assert lines[0] == f"{SCENARIO} [none: {none['no_mpc']}]"
    assert none["no_mpc"] == "no MPC (driver PI)"
    text = "\n".join(lines)
    for word in ("solver", "warm start", "LST", "rho_scale", "e_sub"):
        assert word not in text, word
    lst = replace(run, config=config_for(SCENARIO, disabled=("YRT",))).metrics()
    assert lst["rho_scale"] == [1.0, 0.5] and lst["rho_scale_enabled"] == 1.0
    lines = summary_lines(lst)
    assert lines[0].startswith(f"{SCENARIO} [local_explicit; LST; N_p=")
    assert "rho_scale 1 (LST)," in lines[1] and "0.5" not in lines[1]


def test_comparison_line():
    m = {"formulation": "local_explicit", "objectives": ["LST", "YRT"], "yaw_rms_focus": 0.02,
         "slip_target": None}  # fmt: skip
    base = dict(m, objectives=["LST"], yaw_rms_focus=0.05)
    assert comparison_line(m, base) == (
        "LST+YRT against LST: yaw-rate rms (focus) 0.05 -> 0.02 rad/s (2.50x lower)"
    )
    # no ratio when the run is worse; n/a when a number is missing (NaN or None)
    assert comparison_line(dict(m, yaw_rms_focus=0.06), base).endswith("0.05 -> 0.06 rad/s")
    assert comparison_line(dict(m, yaw_rms_focus=float("nan")), base).endswith("yaw_rms_focus n/a")
    assert comparison_line(m, dict(base, yaw_rms_focus=None)).endswith("yaw_rms_focus n/a")
    # stability control against the driver alone: the rear-slip numbers too
    stab = dict(m, objectives=["VSC", "WSC"], slip_target=0.1, rear_slip_abs_max=0.2,
                rear_slip_excess_rms=0.01)  # fmt: skip
    driver = dict(stab, formulation="none", rear_slip_abs_max=1.5, rear_slip_excess_rms=0.4)
    line = comparison_line(stab, driver)
    assert line.startswith("VSC+WSC against the driver alone: yaw-rate rms (focus) ")
    assert "; rear |slip| max 1.5 -> 0.2 (7.50x lower)" in line
    assert "; rear slip excess rms 0.4 -> 0.01 (40.00x lower)" in line


def test_reports_on_the_run_itself(run):
    """summary_lines and comparison_line take the metrics of real runs as they are."""
    m = run.metrics()
    base = replace(run, config=config_for(SCENARIO, disabled=("YRT",))).metrics()
    line = comparison_line(m, base)
    assert line == "LST+YRT against LST: yaw-rate rms (focus) yaw_rms_focus n/a"  # 1 s: no focus
    assert all(isinstance(x, str) and "\n" not in x for x in summary_lines(m))
