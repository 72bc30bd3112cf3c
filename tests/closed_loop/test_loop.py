"""Tests of ampc_jax.closed_loop.loop: the closed loop, the shadow's e_sub,
--disable, the fallback, batches, input checks, compile once for every
parameter point, and derivatives through the loop."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ampc_jax.closed_loop.loop as S
from ampc_jax.closed_loop import (
    config_for,
    controller_for,
    run_closed_loop,
    simulate,
    simulate_batch,
    simulator_for,
    with_settings,
)
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status, usable
from ampc_jax.vehicle import CONTROL_DT, SCENARIOS
from ampc_jax.vehicle.manoeuvres import stack_scenarios

pytestmark = pytest.mark.timeout(300)

SHORT = 2.0  # s, the shared runs' duration (conftest.py: cruise_run, stability_run)


def _check_bounds(res):
    lg = res.log
    assert np.all(np.isfinite(lg.u)) and np.all(np.isfinite(lg.torques))
    lb = np.asarray(lg.data.lb[:, 0, :])
    ub = np.asarray(lg.data.ub[:, 0, :])
    cols = controller_for(res.config).input_columns
    u = lg.u[:, cols]
    assert np.all(u >= lb - 1e-9) and np.all(u <= ub + 1e-9)


def test_cruise_closed_loop_finite_and_bounded(cruise_run):
    res = cruise_run
    lg = res.log
    assert lg.t.shape == (40,)
    _check_bounds(res)
    # every step converges to the controller's tolerance (max_iter is never reached)
    assert np.all(lg.status == Status.SOLVED), lg.status
    assert int(np.sum(lg.fallback)) == 0
    # the controller tracks speed: v_ref is 18 m/s for the first second
    assert abs(float(lg.v_x[19]) - 18.0) < 0.5
    m = res.metrics()
    for key in ("e_sub_p95", "iterations_max", "yaw_rms", "rear_slip_abs_max", "realtime_factor"):
        assert np.isfinite(m[key]), key
    assert m["fallbacks"] == 0
    # with the MPC the cruise vehicle gets no driver torque (DTR tracks v_ref)
    assert np.all(lg.driver_torque == 0.0)


def test_stability_closed_loop_finite_and_bounded(stability_run):
    res = stability_run
    lg = res.log
    _check_bounds(res)
    tcr = lg.u[:, 0]
    T = lg.driver_torque
    assert np.all(tcr >= np.minimum(T, 0) - 1e-9) and np.all(tcr <= np.maximum(T, 0) + 1e-9)
    # VSC+WSC keep the rear slip near the target on mu = 0.3 (driver alone: > 0.5)
    assert np.max(np.abs(lg.slip[:, 2:])) < 0.3
    assert np.max(T) > 1000.0  # the driver's launch torque is on


def test_shadow_e_sub_matches_clarabel(cruise_run, stability_run):
    for res in (cruise_run, stability_run):
        c = controller_for(res.config)
        T, cols = c.topology, c.input_columns
        for k in (5, 20, 39):
            data = jax.tree.map(lambda x, k=k: np.asarray(x[k]), res.log.data)
            ref = solve_reference(T, data)
            assert ref.status == Status.SOLVED
            u_int = np.asarray(ref.u[0])
            np.testing.assert_allclose(res.log.u_shadow[k, cols], u_int, atol=5e-3)
            e_ref = np.abs(res.log.u_ctrl[k, cols] - u_int)
            np.testing.assert_allclose(res.log.e_sub[k, cols], e_ref, atol=5e-3)


def test_disabled_agent_gets_zero_input():
    res = simulate(
        "stability_launch_brake",
        config_for("stability_launch_brake", disabled=("VSC",), shadow=False),
        duration=1.0,
    )
    assert np.all(res.log.u[:, 2:] == 0.0)  # FDB belongs to VSC only
    assert np.all(np.isnan(res.log.u_ctrl[:, 2:]))  # not solved for
    assert np.all(np.isfinite(res.log.torques))
    assert np.any(res.log.u[:, 0] != 0.0)  # TCR acts


def test_fallback_never_emits_nan(cruise_run):
    n = 40
    fault = np.zeros(n, bool)
    fault[[10, 11, 25]] = True
    res = simulate("cruise_lane_change", duration=SHORT, fault=fault)
    assert res.compile_time == 0.0  # the fault mask is an argument: cruise_run's program
    lg = res.log
    assert int(np.sum(lg.fallback)) == 3
    assert np.all(lg.fallback[fault])
    assert np.all(np.isfinite(lg.u)) and np.all(np.isfinite(lg.torques))
    # the held command is the previous one (bounds are constant in cruise control)
    np.testing.assert_allclose(lg.u[10], lg.u[9])
    np.testing.assert_allclose(lg.u[11], lg.u[9])
    assert res.metrics()["fallbacks"] == 3
    # after the fault the controller recovers (cold restart of the warm start)
    assert np.all(usable(lg.status[~fault])) and np.all(lg.status[fault] == Status.NUMERICAL_ERROR)
    assert np.all(np.isfinite(np.asarray(lg.v_x)))
    # up to the first fault the run is cruise_run's
    np.testing.assert_array_equal(lg.torques[:10], cruise_run.log.torques[:10])


def test_float32_closed_loop():
    cfg = config_for("stability_launch_brake", shadow=False)
    res = simulate("stability_launch_brake", cfg, duration=1.0, dtype=jnp.float32)
    assert res.log.v_x.dtype == np.float32 and res.log.u.dtype == np.float32
    assert np.all(np.isfinite(res.log.torques))


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


# --------------------------------------------------------------------------- input validation
@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"duration": 0}, r"^duration: .*at least one control period \(0.05 s\)"),
        ({"duration": 0.01}, r"^duration: "),
        ({"duration": -1.0}, r"^duration: "),
        ({"duration": float("nan")}, r"^duration: expected a finite time"),
        ({"duration": 1e5}, r"^duration: expected at most 3600 s"),
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


# --------------------------------------------------------------------------- run times
def test_run_time_leaves_out_the_first_execution(monkeypatch):
    """wall_time is the median of three executions after the first (whose
    one-time costs it leaves out); a long first run is not repeated."""
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
    m = cruise_run.metrics()
    assert m["first_run_s"] > 0 and m["wall_time_s"] > 0
    assert m["compile_time_s"] == cruise_run.compile_time
    assert m["realtime_factor"] == pytest.approx(m["duration_s"] / m["wall_time_s"])
    # simulate reports the warm time, not the first execution's
    monkeypatch.setattr(S, "_warm_wall_time", lambda run, first: 0.125)
    res = simulate("cruise_lane_change", duration=SHORT, timing=False)  # compiled already
    assert res.compile_time == 0.0
    assert res.wall_time == 0.125 and res.first_run_time != 0.125
    assert res.metrics()["realtime_factor"] == pytest.approx(SHORT / 0.125)


# --------------------------------------------------------------------------- one compilation
_SWEEP = (
    ((1.0, 0.5), 1.5),
    ((0.5, 0.5), 1.2),
    ((2.0, 1.0), 1.0),
    ((1.0, 0.2), 1.7),
    ((0.3, 3.0), 1.4),
)
"""(rho_scale, relaxation) points of the acceptance test (the first: cruise's defaults)."""
_SWEEP_STEPS = 27  # 1.35 s simulated; a step count no other test compiles


@pytest.fixture(scope="module")
def sweep():
    """One jitted closed loop run at the five points of ``_SWEEP``: its trace count,
    the simulator, the points' LoopParams and logs."""
    cfg = config_for("cruise_lane_change", shadow=False)
    sim = simulator_for(cfg)
    sc = SCENARIOS["cruise_lane_change"].scenario
    configs = [
        config_for("cruise_lane_change", shadow=False, rho_scale=r, relaxation=a) for r, a in _SWEEP
    ]
    params = [c.loop_params() for c in configs]
    traces = []

    def counted(simulator, scenario, p, n_steps):
        traces.append(1)
        return run_closed_loop(simulator, scenario, p, n_steps)

    fn = jax.jit(counted, static_argnums=(0, 3))
    logs = [jax.block_until_ready(fn(sim, sc, p, _SWEEP_STEPS)) for p in params]
    return {
        "sim": sim,
        "sc": sc,
        "configs": configs,
        "params": params,
        "logs": logs,
        "traces": len(traces),
        "cache_size": fn._cache_size(),
        "fn": fn,
    }


def test_one_compiled_loop_serves_five_rho_points(sweep):
    """THE acceptance test of the redesign: one compiled closed loop at five
    different rho scales and relaxations -- one compilation, and results equal to
    separately compiled runs of the first and last point (each with its point's
    numbers as constants)."""
    sim, sc = sweep["sim"], sweep["sc"]
    # every point has the same static structure: one Simulator, one params tree
    assert all(simulator_for(c) == sim for c in sweep["configs"])
    assert sweep["traces"] == 1 and sweep["cache_size"] == 1
    for (r, a), p in zip(_SWEEP, sweep["params"], strict=True):
        np.testing.assert_array_equal(p.controller.solver.rho, r)
        assert float(p.controller.solver.relaxation) == a
    # the points are different runs (the parameters reach the solver)
    iters = [np.asarray(lg.iterations) for lg in sweep["logs"]]
    assert len({tuple(i) for i in iters}) == len(_SWEEP), iters
    assert len({int(i.sum()) for i in iters}) >= 2
    for lg in sweep["logs"]:
        assert np.all(np.asarray(lg.status) == Status.SOLVED)
    # separately compiled programs, the numbers closed over as constants: the
    # first and the last point (each a compile of its own; the three between add
    # compiles, not a check)
    for p, shared in [*zip(sweep["params"], sweep["logs"], strict=True)][:: len(_SWEEP) - 1]:
        alone = jax.jit(lambda s, p=p: run_closed_loop(sim, s, p, _SWEEP_STEPS))(sc)
        np.testing.assert_array_equal(alone.iterations, shared.iterations)
        np.testing.assert_array_equal(alone.status, shared.status)
        # bit-identical here (measured); allclose would allow the last bits of
        # folded constants, equality is what XLA gives
        for field in ("torques", "u", "v_x", "yaw_rate", "omega"):
            np.testing.assert_array_equal(
                np.asarray(getattr(alone, field)), np.asarray(getattr(shared, field)), field
            )


def test_simulate_compiles_once_for_every_rho_point(sweep):
    """simulate() caches its compiled loop per static structure: five configs that
    differ only in rho_scale/relaxation compile once, and the cached program gives
    what a fresh compilation gives."""
    duration = _SWEEP_STEPS * CONTROL_DT
    results = [simulate("cruise_lane_change", c, duration=duration) for c in sweep["configs"]]
    assert results[0].compile_time > 0.0
    assert [r.compile_time for r in results[1:]] == [0.0] * 4
    for res, lg in zip(results, sweep["logs"], strict=True):
        assert res.log.t.shape == (_SWEEP_STEPS,)
        np.testing.assert_array_equal(res.log.iterations, lg.iterations)
        np.testing.assert_allclose(res.log.torques, lg.torques, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(res.log.u, lg.u, rtol=1e-9, atol=1e-9)
    # a changed weight is still a parameter point: a cache hit, and another run
    w = simulate(
        "cruise_lane_change", with_settings(sweep["configs"][2], q_yrt=3.0e3), duration=duration
    )
    assert w.compile_time == 0.0
    assert not np.array_equal(w.log.torques, results[2].log.torques)


def test_simulate_batch_matches_single_runs(sweep):
    """The vmapped closed loop equals one run per case (per-case friction)."""
    sim, sc, p = sweep["sim"], sweep["sc"], sweep["params"][0]
    spec = SCENARIOS["cruise_lane_change"]
    mus = (1.0, 0.6)
    logs = simulate_batch(
        sweep["configs"][0], stack_scenarios([spec, spec]), _SWEEP_STEPS, mu=jnp.asarray(mus)
    )
    for b, mu in enumerate(mus):
        # the single runs: the sweep's compiled loop (mu is an argument)
        one = sweep["fn"](sim, sc._replace(mu=np.asarray(mu)), p, _SWEEP_STEPS)
        for field in ("v_x", "yaw_rate", "omega", "u", "torques", "iterations"):
            np.testing.assert_allclose(
                np.asarray(getattr(logs, field)[b]),
                np.asarray(getattr(one, field)),
                rtol=1e-9,
                atol=1e-9,
            )
    assert sweep["fn"]._cache_size() == 1  # the friction is an argument too
    np.testing.assert_allclose(logs.torques[0], sweep["logs"][0].torques, rtol=1e-9, atol=1e-9)
    assert not np.allclose(np.asarray(logs.yaw_rate[0]), np.asarray(logs.yaw_rate[1]))
    assert not np.allclose(np.asarray(logs.u[0]), np.asarray(logs.u[1]))


def test_forward_derivative_through_the_closed_loop(sweep):
    """d/d(rho scale) of the yaw-rate error of a closed loop exists (forward mode:
    the solver's while_loop has no reverse-mode derivative), is finite and equals a
    central difference where the iteration counts do not change."""
    n = _SWEEP_STEPS  # 1.35 s: the lane change's steering has begun (from about 0.9 s)
    sim, sc, p0 = sweep["sim"], sweep["sc"], sweep["params"][0]  # cruise, the defaults
    rho0 = p0.controller.solver.rho

    def run(rho):
        solver = p0.controller.solver._replace(rho=rho)
        p = p0._replace(controller=p0.controller._replace(solver=solver))
        lg = run_closed_loop(sim, sc, p, n)
        return jnp.sum((lg.yaw_rate - lg.yaw_ref) ** 2), lg.iterations

    direction = rho0  # a relative change of both factors
    jvp = jax.jit(lambda r, v: jax.jvp(run, (r,), (v,)))
    (val, it0), (tangent, _) = jvp(rho0, direction)
    assert np.isfinite(float(val)) and np.isfinite(float(tangent))
    assert float(val) > 1e-4  # the yaw rate is being tracked (steering is on)
    assert abs(float(tangent)) > 1e-5 * float(val)  # measured 1.5e-3
    h = 1e-4
    (vp, itp), _ = jvp(rho0 + h * direction, direction)  # primal outputs: the runs at rho0 +- h
    (vm, itm), _ = jvp(rho0 - h * direction, direction)
    # the derivative of a run is that of its fixed iteration counts: they must not
    # change within the difference, or the difference measures a jump
    np.testing.assert_array_equal(itp, it0)
    np.testing.assert_array_equal(itm, it0)
    fd = (float(vp) - float(vm)) / (2 * h)
    assert fd == pytest.approx(float(tangent), rel=1e-4)
    # the primal is the closed loop's own run
    lg = sweep["logs"][0]
    assert float(jnp.sum((lg.yaw_rate - lg.yaw_ref) ** 2)) == pytest.approx(float(val), rel=1e-9)


# --------------------------------------------------------------------------- full manoeuvres
@pytest.mark.parametrize(
    ("scenario", "max_iterations"),
    [("cruise_lane_change", 15), ("stability_launch_brake", 15), ("stability_dlc", 25)],
)
def test_headline_targets_of_the_full_manoeuvres(scenario, max_iterations):
    """The closed-loop targets on the whole manoeuvre at the defaults
    (README "Targets"): Local Explicit within eps at every step, at most 15 / 25
    iterations, e_sub p95 under 5 Nm against the converged shadow, no warnings."""
    m = simulate(scenario).metrics()
    assert m["iterations_max"] <= max_iterations, m["iterations_max"]
    assert m["e_sub_p95"] < 5.0, m["e_sub_p95"]
    assert m["status_counts"] == {0: m["steps"]} and m["shadow_not_solved"] == 0
    assert m["warnings"] == []


@pytest.mark.parametrize(
    ("name", "scenario"),
    [
        ("fully_distributed", "cruise_lane_change"),
        ("virtual_center", "stability_dlc"),
        pytest.param("virtual_center", "cruise_lane_change", marks=pytest.mark.slow),
        pytest.param("fully_distributed", "stability_dlc", marks=pytest.mark.slow),
    ],
)
def test_formulations_1_and_2_control_the_vehicle(name, scenario):
    """The paper's Formulations 1 and 2 in the controller's seat: bounded inputs,
    no fallback, e_sub against the shadow under the paper's 20 Nm, and r_time
    replayed against IntegratedADMM."""
    cfg = config_for(scenario, formulation=name)
    res = simulate(scenario, cfg, duration=3.0, timing=True, repeats=1)
    _check_bounds(res)
    m = res.metrics()
    assert m["formulation"] == name and m["fallbacks"] == 0
    assert m["e_sub_p95"] < 20.0
    assert np.all(np.asarray(res.log.status) == Status.SOLVED)
    assert np.isfinite(m["r_time_median"]) and m["r_time_median"] > 0
