"""Tests of ampc_jax.simulation: closed loop, shadow e_sub, --disable, fallback, CLI."""

import json
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.cli import main
from ampc_jax.integrated import solve_reference
from ampc_jax.simulation import (
    CONTROLLER_DEFAULTS,
    SimConfig,
    Simulator,
    baseline_config,
    build_topology,
    config_for,
    integrated_solver,
    local_explicit_solver,
    simulate,
    with_settings,
)
from ampc_jax.vehicle import CONTROL_DT, CruiseSettings, StabilitySettings

pytestmark = pytest.mark.timeout(240)

SHORT = 2.0  # s simulated in the closed-loop tests (40 control steps)


@pytest.fixture(scope="module")
def cruise_run():
    return simulate("cruise_lane_change", duration=SHORT)


@pytest.fixture(scope="module")
def stability_run():
    return simulate("stability_launch_brake", duration=SHORT)


def _check_bounds(res):
    lg = res.log
    assert np.all(np.isfinite(lg.u)) and np.all(np.isfinite(lg.torques))
    lb = np.asarray(lg.data.lb[:, 0, :])
    ub = np.asarray(lg.data.ub[:, 0, :])
    T, agent_idx, _ = build_topology(res.config)
    offs = np.cumsum([0, 1, 1, 2])
    cols = np.concatenate([np.arange(offs[i], offs[i + 1]) for i in agent_idx])
    u = lg.u[:, cols]
    assert np.all(u >= lb - 1e-9) and np.all(u <= ub + 1e-9)


def test_cruise_closed_loop_finite_and_bounded(cruise_run):
    res = cruise_run
    lg = res.log
    assert lg.t.shape == (40,)
    _check_bounds(res)
    # every step converges to the controller's tolerance (max_iter is never reached)
    assert np.all(lg.status == 0), lg.status
    assert int(np.sum(lg.fallback)) == 0
    # the controller tracks speed: v_ref is 18 m/s for the first second
    assert abs(float(lg.v_x[19]) - 18.0) < 0.5
    m = res.metrics()
    for key in ("e_sub_p95", "iterations_max", "yaw_rms", "rear_slip_abs_max", "realtime_factor"):
        assert np.isfinite(m[key]), key
    assert m["fallbacks"] == 0


def test_stability_closed_loop_finite_and_bounded(stability_run):
    res = stability_run
    lg = res.log
    _check_bounds(res)
    tcr = lg.u[:, 0]
    T = lg.driver_torque
    assert np.all(tcr >= np.minimum(T, 0) - 1e-9) and np.all(tcr <= np.maximum(T, 0) + 1e-9)
    # VSC+WSC keep the rear slip near the target on mu = 0.3 (driver alone: > 0.5)
    assert np.max(np.abs(lg.slip[:, 2:])) < 0.3


def test_shadow_e_sub_matches_clarabel(cruise_run, stability_run):
    for res in (cruise_run, stability_run):
        T, agent_idx, _ = build_topology(res.config)
        offs = np.cumsum([0, 1, 1, 2])
        cols = np.concatenate([np.arange(offs[i], offs[i + 1]) for i in agent_idx])
        for k in (5, 20, 39):
            data = jax.tree.map(lambda x, k=k: np.asarray(x[k]), res.log.data)
            ref = solve_reference(T, data)
            assert ref.status == 0
            u_int = np.asarray(ref.u[0])
            np.testing.assert_allclose(res.log.u_shadow[k, cols], u_int, atol=5e-3)
            e_ref = np.abs(res.log.u_ctrl[k, cols] - u_int)
            np.testing.assert_allclose(res.log.e_sub[k, cols], e_ref, atol=5e-3)


def test_disable_builds_reduced_topology():
    T, agents, objs = build_topology(SimConfig("cruise", disabled=("YRT",)))
    assert T.agent_names == ("DTR", "FDB") and agents == (0, 2)
    assert T.objective_names == ("LST",) and T.groups == ((0, 1),) and objs == (0,)
    T, agents, objs = build_topology(SimConfig("stability", disabled=("VSC",)))
    assert T.agent_names == ("TCR", "RTV") and T.objective_names == ("WSC",)
    T, _, _ = build_topology(config_for("stability_dlc"))
    assert T.agent_names == ("TCR", "RTV", "FDB") and T.groups == ((1, 2), (0, 1))
    with pytest.raises(ValueError, match="unknown objective"):
        SimConfig("cruise", disabled=("VSC",))
    with pytest.raises(ValueError):
        SimConfig("cruise", disabled=("LST", "YRT"))


def test_disabled_agent_gets_zero_input():
    res = simulate(
        "stability_launch_brake",
        config_for("stability_launch_brake", disabled=("VSC",), shadow=False),
        duration=1.0,
    )
    assert np.all(res.log.u[:, 2:] == 0.0)  # FDB belongs to VSC only
    assert np.all(np.isfinite(res.log.torques))


def test_fallback_never_emits_nan(cruise_run):
    n = 40
    fault = np.zeros(n, bool)
    fault[[10, 11, 25]] = True
    res = simulate("cruise_lane_change", duration=SHORT, fault=fault)
    lg = res.log
    assert int(np.sum(lg.fallback)) == 3
    assert np.all(lg.fallback[fault])
    assert np.all(np.isfinite(lg.u)) and np.all(np.isfinite(lg.torques))
    # the held command is the previous one (bounds are constant in cruise control)
    np.testing.assert_allclose(lg.u[10], lg.u[9])
    np.testing.assert_allclose(lg.u[11], lg.u[9])
    assert res.metrics()["fallbacks"] == 3
    # after the fault the controller recovers (cold restart of the warm start)
    assert np.all(lg.status[~fault] <= 1) and np.all(lg.status[fault] == 2)
    assert np.all(np.isfinite(np.asarray(lg.v_x)))


def test_cli_simulate_writes_outputs(tmp_path, cruise_run, capsys):
    out = tmp_path / "run"
    code = main(
        ["simulate", "cruise_lane_change", "--duration", str(SHORT), "--out", str(out),
         "--quiet", "--repeats", "1"]
    )  # fmt: skip
    assert code == 0
    for name in ("timeseries.csv", "metrics.json", "vehicle_response.png",
                 "wheel_torques.png", "convergence.png"):  # fmt: skip
        assert (out / name).stat().st_size > 0, name
    m = json.loads((out / "metrics.json").read_text())
    assert m["steps"] == 40 and m["fallbacks"] == 0
    assert m["r_time_median"] > 0
    header = (out / "timeseries.csv").read_text().splitlines()[0].split(",")
    assert {"t", "v_x", "yaw_rate", "e_sub_DTR", "iterations", "r_time"} <= set(header)
    assert "e_sub" in capsys.readouterr().out


def test_cli_rejects_unknown_objective(capsys):
    code = main(["simulate", "cruise_lane_change", "--disable", "WSC", "--out", "x", "--quiet"])
    assert code == 2
    assert "unknown objective" in capsys.readouterr().err


def test_float32_closed_loop():
    cfg = config_for("stability_launch_brake", shadow=False)
    res = simulate("stability_launch_brake", cfg, duration=1.0, dtype=jnp.float32)
    assert res.log.v_x.dtype == np.float32
    assert np.all(np.isfinite(res.log.torques))


@pytest.mark.timeout(300)
def test_walkthrough_notebook_executes(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    from pathlib import Path

    path = Path(__file__).parents[1] / "notebooks" / "cruise_control_walkthrough.ipynb"
    nb = nbformat.read(path, as_version=4)
    # run where its figures may be written (walkthrough_figures/ in the working directory)
    nbclient.NotebookClient(nb, timeout=240, kernel_name="python3").execute(cwd=str(tmp_path))
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "e_sub_p95" in text and "yaw_rms_focus" in text
    figures = sorted(p.name for p in (tmp_path / "walkthrough_figures").glob("*.png"))
    assert figures == [
        "convergence.png",
        "vehicle_response.png",
        "wheel_torques.png",
        "yaw_error.png",
    ]


# --------------------------------------------------------------------------- solver options
@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"rho_scale": (1.0, 2.0, 3.0)}, "rho_scale"),
        ({"rho_scale": ()}, "rho_scale"),
        ({"rho_scale": -1.0}, "rho_scale"),
        ({"rho_scale": (1.0, float("nan"))}, "rho_scale"),
        ({"rho_scale": "fast"}, "rho_scale"),
        ({"relaxation": 2.0}, "relaxation"),
        ({"relaxation": 0.0}, "relaxation"),
        ({"relaxation": "1.5"}, "relaxation"),
        ({"integrated_rho_scale": 0.0}, "integrated_rho_scale"),
        ({"integrated_rho_scale": (1.0, 1.0)}, "integrated_rho_scale"),
        ({"shadow_rho_scale": float("inf")}, "shadow_rho_scale"),
        ({"shadow_relaxation": 2.5}, "shadow_relaxation"),
        ({"warm_shift": 2}, "warm_shift"),
        ({"warm_shift": True}, "warm_shift"),
        ({"anderson": 4}, "anderson"),
        ({"anderson": -1}, "anderson"),
        ({"anderson": 2.0}, "anderson"),
    ],
)
def test_solver_options_are_validated(kw, field):
    with pytest.raises(ValueError, match=rf"^{field}: "):
        SimConfig("cruise", **kw)


def test_solver_options_defaults_and_pass_through():
    for name, example in (("cruise_lane_change", "cruise"), ("stability_dlc", "stability")):
        d = CONTROLLER_DEFAULTS[example]
        c = config_for(name)
        assert c.rho_scale == tuple(d["rho_scale"]) and c.relaxation == d["relaxation"]
        assert c.integrated_rho_scale == d["integrated_rho_scale"]
        assert c.warm_shift == d["warm_shift"] and c.anderson == d["anderson"]
        assert hash(c) == hash(config_for(name))  # still a static jit argument
        T = build_topology(c)[0]
        le = Simulator(c).controller()
        assert le.rho_scale == c.rho_scale and le.relaxation == c.relaxation
        ia = integrated_solver(c, T)
        assert ia.rho_scale == c.integrated_rho_scale and ia.relaxation == c.relaxation
        assert le.anderson == ia.anderson == ia.inner.anderson == c.anderson
        assert (ia.tol_primal, ia.tol_dual) == (le.tol_primal, le.tol_dual)
        sh = Simulator(c).shadow_solver()
        assert sh.rho_scale == c.shadow_rho_scale and sh.relaxation == c.shadow_relaxation
        assert sh.anderson == 0  # the shadow stays plain ADMM
        ctrl = Simulator(config_for(name, formulation="integrated")).controller()
        assert ctrl.rho_scale == c.integrated_rho_scale and ctrl.relaxation == c.relaxation
    # --disable keeps the enabled objectives' factors
    lst = config_for("cruise_lane_change", disabled=("YRT",), rho_scale=(0.7, 0.3))
    assert lst.enabled_rho_scale == 0.7
    assert local_explicit_solver(lst, build_topology(lst)[0]).rho_scale == 0.7
    wsc = config_for("stability_dlc", disabled=("VSC",), rho_scale=(0.7, 0.3))
    assert wsc.enabled_rho_scale == 0.3
    # one float applies to every objective; the paper's solver is rho* and alpha = 1
    one = SimConfig("stability", rho_scale=2, relaxation=1)
    assert one.rho_scale == 2.0 and one.enabled_rho_scale == 2.0
    assert isinstance(one.relaxation, float)


def test_metrics_record_solver_options(cruise_run):
    m = cruise_run.metrics()
    c = cruise_run.config
    assert m["rho_scale"] == list(c.rho_scale) and m["relaxation"] == c.relaxation
    assert m["integrated_rho_scale"] == c.integrated_rho_scale


def test_cli_rejects_bad_solver_options(capsys):
    base = ["simulate", "cruise_lane_change", "--out", "x", "--quiet"]
    assert main([*base, "--rho-scale", "1,2,3"]) == 2
    assert "rho_scale" in capsys.readouterr().err
    assert main([*base, "--rho-scale", "1,x"]) == 2
    assert "--rho-scale" in capsys.readouterr().err
    assert main([*base, "--relaxation", "2"]) == 2
    assert "relaxation" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: choices 0, 1
        main([*base, "--warm-shift", "2"])
    assert "--warm-shift" in capsys.readouterr().err


def test_tuned_settings_are_the_defaults():
    """One source of truth: the scenarios run vehicle.py's default settings."""
    assert CruiseSettings().horizon == 2 and CruiseSettings().q_yrt == 1.0e4
    assert StabilitySettings().horizon == 3
    assert config_for("cruise_lane_change").settings == CruiseSettings()
    assert config_for("stability_launch_brake").settings == StabilitySettings()
    assert config_for("stability_dlc").settings == StabilitySettings()


def test_cruise_driver_alone_drives_the_car():
    """Cruise with no MPC: the driver's speed PI plays DTR (rear axle, within
    DTR's bounds), so the car follows the speed profile instead of coasting."""
    cfg = config_for("cruise_lane_change", formulation="none", shadow=False)
    res = simulate("cruise_lane_change", cfg, duration=4.0)
    lg = res.log
    dtr_max = cfg.settings.dtr_max
    assert np.all(np.isfinite(lg.torques))
    np.testing.assert_allclose(lg.u[:, 0], np.clip(lg.driver_torque, -dtr_max, dtr_max))
    np.testing.assert_allclose(lg.torques[:, 2], 0.5 * lg.u[:, 0])  # split on the rear axle
    np.testing.assert_allclose(lg.torques[:, 3], 0.5 * lg.u[:, 0])
    assert np.all(lg.torques[:, :2] == 0.0) and np.any(lg.u[:, 0] < -100.0)
    err = np.abs(np.asarray(lg.v_x) - np.asarray(lg.v_ref))
    assert float(lg.v_ref[-1]) < float(lg.v_ref[0]) - 2.0  # the profile decelerates
    assert float(np.max(err[20:])) < 1.0, float(np.max(err[20:]))


def test_simulate_batch_matches_single_runs():
    """The vmapped closed loop equals one run per case (per-case friction)."""
    from ampc_jax.manoeuvres import SCENARIOS, stack_scenarios
    from ampc_jax.simulation import simulate_batch

    name = "stability_launch_brake"
    cfg = config_for(name, shadow=False)
    spec = SCENARIOS[name]
    mus = (0.3, 0.5)
    logs = simulate_batch(cfg, stack_scenarios([spec, spec]), 20, mu=jnp.asarray(mus))
    for b, mu in enumerate(mus):
        one = simulate(name, cfg, duration=1.0, mu=mu).log
        for field in ("v_x", "yaw_rate", "omega", "u", "torques", "iterations"):
            np.testing.assert_allclose(
                np.asarray(getattr(logs, field)[b]), getattr(one, field), rtol=1e-9, atol=1e-9
            )
    assert not np.allclose(np.asarray(logs.omega[0]), np.asarray(logs.omega[1]))


# --------------------------------------------------------------------------- input validation
@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"tol_primal": -1.0}, "tol_primal"),
        ({"tol_primal": 0.0}, "tol_primal"),
        ({"tol_dual": float("nan")}, "tol_dual"),
        ({"shadow_tol_primal": float("inf")}, "shadow_tol_primal"),
        ({"max_iter": 0}, "max_iter"),
        ({"max_iter": 10.0}, "max_iter"),
        ({"max_iter": True}, "max_iter"),
        ({"shadow_max_iter": -5}, "shadow_max_iter"),
        ({"warm_start": "yes"}, "warm_start"),
        ({"settings": StabilitySettings()}, "settings"),
        ({"settings": CruiseSettings(q_yrt=-5.0)}, "q_yrt"),
        ({"settings": CruiseSettings(horizon=0)}, "horizon"),
        ({"settings": CruiseSettings(dt=0.0)}, "dt"),
    ],
)
def test_config_fields_are_validated(kw, field):
    with pytest.raises(ValueError, match=rf"^{field}: "):
        SimConfig("cruise", **kw)


def test_with_settings_is_validated_and_numbers_canonical():
    with pytest.raises(ValueError, match=r"^r_rtv: expected a weight > 0"):
        with_settings(config_for("cruise_lane_change"), r_rtv=0.0)
    c = SimConfig("cruise", tol_primal=1, max_iter=np.int64(5))
    assert isinstance(c.tol_primal, float) and type(c.max_iter) is int
    assert hash(c) == hash(SimConfig("cruise", tol_primal=1.0, max_iter=5))


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"duration": 0}, r"^duration: .*at least one control period \(0.05 s\)"),
        ({"duration": 0.01}, r"^duration: "),
        ({"duration": -1.0}, r"^duration: "),
        ({"duration": float("nan")}, r"^duration: expected a finite time"),
        ({"mu": float("nan")}, r"^mu: expected a finite road friction in \(0, 2\]"),
        ({"mu": -1.0}, r"^mu: "),
        ({"mu": 0.0}, r"^mu: "),
        ({"mu": 3.0}, r"^mu: "),
        ({"mu": [0.5, 0.6]}, r"^mu: expected one friction value"),
        ({"duration": 1.0, "fault": np.zeros(5, bool)}, r"^fault: expected a \(20,\) mask"),
    ],
)
def test_simulate_refuses_bad_duration_mu_and_fault(kw, match):
    with pytest.raises(ValueError, match=match):  # before anything is compiled
        simulate("cruise_lane_change", **kw)


def test_simulate_batch_refuses_bad_mu_and_steps():
    from ampc_jax.manoeuvres import SCENARIOS, stack_scenarios
    from ampc_jax.simulation import simulate_batch

    cfg = config_for("stability_dlc", shadow=False)
    stacked = stack_scenarios([SCENARIOS["stability_dlc"]] * 2)
    with pytest.raises(ValueError, match=r"^mu: "):
        simulate_batch(cfg, stacked, 4, mu=[0.3, -1.0])
    with pytest.raises(ValueError, match=r"^n_steps: "):
        simulate_batch(cfg, stacked, 0)


def test_one_step_run_and_loop_time_is_the_control_period():
    """The shortest run is one control period; the loop's time steps by CONTROL_DT
    even when the prediction model's settings.dt differs (it used settings.dt)."""
    cfg = config_for("cruise_lane_change", formulation="none", shadow=False)
    one = simulate("cruise_lane_change", cfg, duration=CONTROL_DT)
    assert one.log.t.shape == (1,) and one.duration == CONTROL_DT
    res = simulate("cruise_lane_change", with_settings(cfg, dt=0.1), duration=0.1)
    np.testing.assert_allclose(res.log.t, [0.0, CONTROL_DT])


def test_summary_header_of_driver_alone_and_disabled_objective(cruise_run, capsys):
    from ampc_jax.reporting import _summary

    none = replace(cruise_run, config=config_for("cruise_lane_change", formulation="none"))
    _summary(none.metrics())
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "cruise_lane_change [none: no MPC, driver speed PI]"
    for word in ("solver", "warm start", "LST", "rho_scale", "e_sub"):
        assert word not in out, word
    lst = replace(cruise_run, config=config_for("cruise_lane_change", disabled=("YRT",)))
    m = lst.metrics()
    assert m["rho_scale"] == [1.0, 0.5] and m["rho_scale_enabled"] == 1.0
    _summary(m)
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("cruise_lane_change [local_explicit; LST; N_p=2;")
    assert "rho_scale 1 (LST)," in out and "0.5" not in out.splitlines()[1]


def test_focus_numbers_na_only_before_the_window(cruise_run, capsys):
    from ampc_jax.reporting import _summary

    m = cruise_run.metrics()  # 2 s run, focus window 7..13 s
    assert m["focus_steps"] == 0 and np.isnan(m["e_sub_p95_focus"])
    assert np.isnan(m["yaw_rms_focus"])
    _summary(m)
    out = capsys.readouterr().out
    assert "0 of 40 steps; the run ends before it" in out and "focus p95 n/a" in out
    early = replace(cruise_run, focus=(1.5, 6.0)).metrics()  # as stability_dlc's window
    assert early["focus_steps"] == 10 and np.isfinite(early["e_sub_p95_focus"])
    assert np.isfinite(early["yaw_rms_focus"])
    _summary(early)
    out = capsys.readouterr().out
    assert "10 of 40 steps\n" in out and "focus p95 n/a" not in out and "(focus n/a)" not in out


def test_figures_without_e_sub_keep_convergence(cruise_run, tmp_path):
    """--no-shadow logs no e_sub: the convergence figure is still written (its
    e_sub panels say why they are empty; log scaling an empty panel crashed)."""
    from ampc_jax.reporting import _figures

    lg = cruise_run.log._replace(e_sub=np.full_like(cruise_run.log.e_sub, np.nan))
    paths = _figures([replace(cruise_run, log=lg)], tmp_path)
    names = [p.name for p in paths]
    assert names == ["vehicle_response.png", "wheel_torques.png", "convergence.png"]
    assert all(p.stat().st_size > 0 for p in paths)


def test_run_time_leaves_out_the_first_execution(monkeypatch):
    """wall_time is the median of three executions after the first (whose
    one-time costs it leaves out); a long first run is not repeated."""
    from ampc_jax import simulation as S

    calls = []
    delays = iter([0.03, 0.01, 0.02])

    def run():
        calls.append(1)
        return next(delays)

    import types

    ticks = iter([0.0, 0.03, 1.0, 1.01, 2.0, 2.02])
    # a stand-in for the module's ``time`` (the real time.perf_counter stays as it is)
    monkeypatch.setattr(S, "time", types.SimpleNamespace(perf_counter=lambda: next(ticks)))
    monkeypatch.setattr(S.jax, "block_until_ready", lambda x: x)
    assert S._warm_wall_time(run, first=0.1) == pytest.approx(0.02)
    assert len(calls) == 3
    assert S._warm_wall_time(run, first=S._WARM_BUDGET_S + 1.0) == S._WARM_BUDGET_S + 1.0
    assert len(calls) == 3  # not repeated


def test_metrics_report_first_and_warm_run_times(cruise_run, monkeypatch):
    from ampc_jax import simulation as S

    m = cruise_run.metrics()
    assert m["first_run_s"] > 0 and m["wall_time_s"] > 0
    assert m["realtime_factor"] == pytest.approx(m["duration_s"] / m["wall_time_s"])
    # simulate reports the warm time, not the first execution's
    monkeypatch.setattr(S, "_warm_wall_time", lambda run, first: 0.125)
    res = simulate("cruise_lane_change", duration=SHORT, timing=False)  # compiled already
    assert res.wall_time == 0.125 and res.first_run_time != 0.125
    assert res.metrics()["realtime_factor"] == pytest.approx(SHORT / 0.125)


def test_baseline_is_the_papers_comparison(capsys, tmp_path):
    """--compare's baseline: LST alone for cruise control (same solver settings),
    the driver alone for stability control; a run that is the baseline is refused."""
    cruise = config_for("cruise_lane_change", relaxation=1.2)
    base = baseline_config(cruise)
    assert base.enabled == ("LST",) and base.formulation == "local_explicit"
    assert base.relaxation == 1.2 and base.rho_scale == cruise.rho_scale
    stab = baseline_config(config_for("stability_dlc", disabled=("WSC",)))
    assert stab.formulation == "none"
    with pytest.raises(ValueError, match=r"^compare: this run already is .* \(LST alone\)"):
        baseline_config(base)
    with pytest.raises(ValueError, match=r"the driver alone"):
        baseline_config(stab)
    code = main(
        ["simulate", "stability_dlc", "--formulation", "none", "--compare", "--quiet",
         "--out", str(tmp_path / "x")]
    )  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: --compare: this run already is"), err


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


def test_stability_logs_no_speed_reference(stability_run, cruise_run):
    """The stability drivers apply an open-loop torque: no v_ref, no speed_rms."""
    assert np.all(np.isnan(stability_run.log.v_ref))
    assert np.isnan(stability_run.metrics()["speed_rms"])
    assert np.all(np.isfinite(cruise_run.log.v_ref))
    assert np.isfinite(cruise_run.metrics()["speed_rms"])


def test_warnings_flag_unreliable_runs(cruise_run, capsys):
    from ampc_jax.reporting import _summary

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
    _summary(bad.metrics())
    assert capsys.readouterr().out.count("  warning: ") == 3


def test_warning_when_the_vehicle_goes_backwards():
    """The driver alone spins out in the DLC and ends up reversing: the plant is
    forward-only, so the run says so."""
    cfg = config_for("stability_dlc", formulation="none", shadow=False)
    m = simulate("stability_dlc", cfg).metrics()
    assert m["v_x_min"] < 0
    assert m["warnings"][0].startswith("the vehicle went backwards (v_x ")
    assert "not physical from there on" in m["warnings"][0]


@pytest.mark.parametrize(
    ("scenario", "max_iterations"),
    [("cruise_lane_change", 15), ("stability_launch_brake", 15), ("stability_dlc", 25)],
)
def test_headline_targets_of_the_full_manoeuvres(scenario, max_iterations):
    """The issue's closed-loop targets on the whole manoeuvre at the defaults
    (README "Targets"): Local Explicit within eps at every step, at most 15 / 25
    iterations, e_sub p95 under 5 Nm against the converged shadow, no warnings."""
    m = simulate(scenario).metrics()
    assert m["iterations_max"] <= max_iterations, m["iterations_max"]
    assert m["e_sub_p95"] < 5.0, m["e_sub_p95"]
    assert m["status_counts"] == {0: m["steps"]} and m["shadow_not_solved"] == 0
    assert m["warnings"] == []
