"""Tests of ampc_jax.closed_loop.metrics: SimResult.metrics and its warnings, and
how the reports (ampc_jax.io.reports) present them."""

from dataclasses import replace

import numpy as np
import pytest

from ampc_jax.closed_loop import config_for, simulate
from ampc_jax.closed_loop.metrics import V_X_BACKWARDS
from ampc_jax.io.reports import summary_lines, write_figures

pytestmark = pytest.mark.timeout(180)


def _text(m):
    """What ``ampc simulate`` prints for the metrics ``m``."""
    return "".join(line + "\n" for line in summary_lines(m))


def test_metrics_record_solver_options(cruise_run, stability_run):
    m = cruise_run.metrics()
    c = cruise_run.config
    assert m["rho_scale"] == list(c.rho_scale) and m["relaxation"] == c.relaxation
    assert m["integrated_rho_scale"] == c.integrated_rho_scale
    assert m["anderson"] == c.anderson and m["warm_shift"] == c.warm_shift
    assert (m["tol_primal"], m["tol_dual"], m["max_iter"]) == (1.0, 1.0, 200)
    assert m["example"] == "cruise" and m["objectives"] == ["LST", "YRT"]
    # the example's own words and numbers
    assert m["no_mpc"] == "no MPC (driver PI)" and m["slip_target"] is None
    s = stability_run.metrics()
    assert s["no_mpc"] == "driver alone" and s["slip_target"] == 0.15
    assert s["rho_scale"] == [0.3, 3.0] and s["horizon"] == 3
    # e_sub per input of the enabled agents (all four here)
    assert set(m["e_sub_max_per_input"]) == {"DTR", "RTV", "FDB_L", "FDB_R"}


def test_summary_header_of_driver_alone_and_disabled_objective(cruise_run):
    none = replace(cruise_run, config=config_for("cruise_lane_change", formulation="none"))
    out = _text(none.metrics())
    assert out.splitlines()[0] == "cruise_lane_change [none: no MPC (driver PI)]"
    for word in ("solver", "warm start", "LST", "rho_scale", "e_sub"):
        assert word not in out, word
    lst = replace(cruise_run, config=config_for("cruise_lane_change", disabled=("YRT",)))
    m = lst.metrics()
    assert m["rho_scale"] == [1.0, 0.5] and m["rho_scale_enabled"] == 1.0
    out = _text(m)
    assert out.splitlines()[0].startswith("cruise_lane_change [local_explicit; LST; N_p=2;")
    assert "rho_scale 1 (LST)," in out and "0.5" not in out.splitlines()[1]


def test_focus_numbers_na_only_before_the_window(cruise_run):
    m = cruise_run.metrics()  # 2 s run, focus window 7..13 s
    assert m["focus_steps"] == 0 and np.isnan(m["e_sub_p95_focus"])
    assert np.isnan(m["yaw_rms_focus"])
    out = _text(m)
    assert "0 of 40 steps; the run ends before it" in out and "focus p95 n/a" in out
    early = replace(cruise_run, focus=(1.5, 6.0)).metrics()  # as stability_dlc's window
    assert early["focus_steps"] == 10 and np.isfinite(early["e_sub_p95_focus"])
    assert np.isfinite(early["yaw_rms_focus"])
    out = _text(early)
    assert "10 of 40 steps\n" in out and "focus p95 n/a" not in out and "(focus n/a)" not in out


def test_figures_without_e_sub_keep_convergence(cruise_run, tmp_path):
    """--no-shadow logs no e_sub: the convergence figure is still written (its
    e_sub panels say why they are empty; log scaling an empty panel crashed)."""
    lg = cruise_run.log._replace(e_sub=np.full_like(cruise_run.log.e_sub, np.nan))
    paths = write_figures([replace(cruise_run, log=lg)], tmp_path)
    names = [p.name for p in paths]
    assert names == ["vehicle_response.png", "wheel_torques.png", "convergence.png"]
    assert all(p.stat().st_size > 0 for p in paths)


def test_stability_logs_no_speed_reference(stability_run, cruise_run):
    """The stability drivers apply an open-loop torque: no v_ref, no speed_rms."""
    assert np.all(np.isnan(stability_run.log.v_ref))
    assert np.isnan(stability_run.metrics()["speed_rms"])
    assert np.all(np.isfinite(cruise_run.log.v_ref))
    assert np.isfinite(cruise_run.metrics()["speed_rms"])
    # the stability example logs its wheel-speed reference, cruise has none
    assert np.all(np.isfinite(stability_run.log.omega_ref))
    assert np.all(np.isnan(cruise_run.log.omega_ref))


def test_warnings_flag_unreliable_runs(cruise_run):
    assert cruise_run.metrics()["warnings"] == []
    lg = cruise_run.log
    bad = replace(
        cruise_run,
        log=lg._replace(
            status=np.where(np.arange(40) < 3, 1, 0),
            shadow_status=np.where(np.arange(40) == 5, 1, 0),
            fallback=np.arange(40) == 7,
        ),
    )
    w = bad.metrics()["warnings"]
    assert w[0] == (
        f"3 of 40 control steps stopped at max_iter = {cruise_run.config.max_iter} "
        "without meeting eps_r / eps_s"
    )
    assert w[1].startswith("1 of 40 control steps fell back to the previous command")
    assert w[2].startswith("the shadow integrated MPC did not converge on 1 of 40 steps")
    assert _text(bad.metrics()).count("  warning: ") == 3
    # without the shadow its status is not a warning
    no_shadow = replace(bad, config=config_for("cruise_lane_change", shadow=False))
    assert len(no_shadow.metrics()["warnings"]) == 2
    assert no_shadow.metrics()["shadow_not_solved"] is None


def test_warning_when_the_vehicle_goes_backwards():
    """The driver alone spins out in the DLC and ends up reversing: the plant is
    forward-only, so the run says so."""
    cfg = config_for("stability_dlc", formulation="none", shadow=False)
    res = simulate("stability_dlc", cfg)
    m = res.metrics()
    assert m["v_x_min"] < 0
    assert m["warnings"][0].startswith("the vehicle went backwards (v_x ")
    assert "not physical from there on" in m["warnings"][0]
    # the warning's time is the first step below the margin
    k = int(np.argmax(res.log.v_x < V_X_BACKWARDS))
    assert f"first at t = {float(res.log.t[k]):g} s" in m["warnings"][0]
    # no MPC: no solver numbers, no solver warnings
    assert "e_sub_p95" not in m and "status_counts" not in m
    assert len(m["warnings"]) == 1
