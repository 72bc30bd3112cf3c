"""Tests of ampc_jax.closed_loop.controller: Controller.init/step called directly
(jitted), as a runtime or a replay calls it, outside the simulated loop.

* a Python loop of driver, plant and ``Controller.step`` (plus the shadow's
  ``IntegratedShadow.observe``) reproduces the compiled closed loop's log;
* the fallback guard on a NaN measurement;
* the horizon check;
* one compiled step for every parameter point (no retracing).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.closed_loop import (
    Controller,
    ControllerState,
    DriverInputs,
    config_for,
    controller_for,
    simulator_for,
    with_settings,
)
from ampc_jax.results import USABLE_STATUS, Status
from ampc_jax.vehicle import CONTROL_DT, SCENARIOS, CruiseSettings
from ampc_jax.vehicle.manoeuvres import driver_step, initial_driver_state, initial_plant_state
from ampc_jax.vehicle.plant import measure, plant_step

pytestmark = pytest.mark.timeout(240)

F64 = jnp.float64


# the driver and the plant, as the loop calls them (scenario and friction arguments,
# so both replays share one compilation each)
_driver = jax.jit(driver_step, static_argnums=(4,))
_measure = jax.jit(
    lambda ps, steer, mu, vp: measure(ps, steer, jnp.zeros(4, F64), mu, vp), static_argnums=(3,)
)
_plant = jax.jit(plant_step, static_argnums=(4,))


class Replay:
    """The closed loop of a logged run, rebuilt step by step in Python around a
    jitted ``Controller.step`` (``traces`` counts its successful traces), and the
    shadow's ``IntegratedShadow.observe`` when ``shadow``."""

    def __init__(self, res, shadow=True):
        self.res = res
        cfg = res.config
        self.config = cfg
        self.ctrl = controller_for(cfg)
        self.shadow = simulator_for(cfg).shadow
        self.params = cfg.loop_params(F64)
        self.observed = shadow
        sc = jax.tree.map(lambda x: jnp.asarray(x, F64), SCENARIOS[res.scenario].scenario)
        vp, dp, mu = cfg.vehicle, cfg.driver, sc.mu
        self.traces = []

        def counted_step(state, params, meas, driver):
            out = self.ctrl.step(state, params, meas, driver)
            self.traces.append(1)  # after the step: a refused trace does not count
            return out

        self.step = jax.jit(counted_step)
        observe = jax.jit(self.shadow.observe) if shadow else None
        ps, ds = initial_plant_state(sc, vp, F64), initial_driver_state(F64)
        cs, ss = self.ctrl.init(F64), self.shadow.init(F64)
        self.states, self.meas, self.drivers, self.out, self.shadow_out = [], [], [], [], []
        for k in range(len(res.log.t)):
            ds, steer, T, v_ref = _driver(ds, ps, k * CONTROL_DT, sc, dp)
            m = _measure(ps, steer, mu, vp)
            drv = DriverInputs(steer, T, v_ref, mu)
            self.states.append(cs)
            self.meas.append(m)
            self.drivers.append(drv)
            tq, cs, info = self.step(cs, self.params.controller, m, drv)
            if observe is not None:
                ss, sh = observe(ss, self.params.shadow, info.data)
                self.shadow_out.append(sh)
            self.out.append((tq, info))
            ps = _plant(ps, steer, tq, mu, vp)


@pytest.fixture(scope="module")
def cruise_replay(cruise_run):
    return Replay(cruise_run)


@pytest.fixture(scope="module", params=["cruise", "stability"])
def replay(request):
    if request.param == "cruise":
        return request.getfixturevalue("cruise_replay")
    # (the shadow's replay is the cruise one's: same observer, another topology)
    return Replay(request.getfixturevalue("stability_run"), shadow=False)


def test_step_reproduces_the_closed_loop(replay):
    """Controller.step, jitted on its own and fed the plant's measurement and the
    driver's inputs, gives the compiled loop's torques, inputs and iterations."""
    lg, cols = replay.res.log, replay.ctrl.input_columns
    assert replay.ctrl == simulator_for(replay.config).controller
    assert len(replay.out) == 40
    assert len(replay.traces) == 1  # one trace of the step for the whole run
    for k, (tq, info) in enumerate(replay.out):
        np.testing.assert_allclose(tq, lg.torques[k], rtol=1e-9, atol=1e-9, err_msg=f"{k}")
        np.testing.assert_allclose(info.u, lg.u[k], rtol=1e-9, atol=1e-9, err_msg=f"{k}")
        np.testing.assert_allclose(info.u_ctrl, lg.u_ctrl[k], rtol=1e-9, atol=1e-9)
        assert int(info.iterations) == int(lg.iterations[k]), k
        assert int(info.status) == int(lg.status[k]) and bool(info.fallback) == lg.fallback[k]
        assert float(info.driver_torque) == pytest.approx(lg.driver_torque[k], abs=1e-9)
        # the problem data and warm start the step logged are the loop's
        np.testing.assert_allclose(info.data.x0, lg.data.x0[k], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(info.warm.Z, lg.warm.Z[k], rtol=1e-9, atol=1e-9)
    # the shadow observer on each step's own problem: the loop's u_shadow
    for k, sh in enumerate(replay.shadow_out):
        np.testing.assert_allclose(sh.u0, lg.u_shadow[k, cols], rtol=1e-9, atol=1e-9)
        assert int(sh.iterations) == int(lg.shadow_iterations[k]), k
        assert int(sh.status) == int(lg.shadow_status[k]) == Status.SOLVED, k
    assert len(replay.shadow_out) == (40 if replay.observed else 0)
    assert replay.observed or replay.ctrl.example.name == "stability"
    # the runs are not trivial: the solver iterates and the agents act
    assert lg.iterations.min() >= 2 and np.max(np.abs(lg.u)) > 50.0
    # init: a cold solver state and no previous command
    s0 = replay.ctrl.init(F64)
    for a, b in zip(
        jax.tree.leaves(s0.warm), jax.tree.leaves(replay.ctrl.solver.cold_state(F64)), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(s0.u_prev, np.zeros(replay.ctrl.topology.n_u))


@pytest.mark.parametrize("bad", ["all", "F_y"])
def test_nan_measurement_falls_back(replay, bad):
    """A NaN measurement: the guard holds the previous command (clipped to the
    bounds), the torques are finite and within bounds, the warm start is reset
    to cold; the next good step recovers, as from a cold start."""
    ctrl, p, k = replay.ctrl, replay.params.controller, 20
    state, meas, drv = replay.states[k], replay.meas[k], replay.drivers[k]
    assert np.any(np.asarray(state.u_prev) != 0.0)  # a command to hold
    if bad == "all":
        nan_meas = jax.tree.map(lambda x: jnp.full_like(x, jnp.nan), meas)
    else:
        nan_meas = meas._replace(F_y=meas.F_y.at[1].set(jnp.nan))
    tq, nxt, info = replay.step(state, p, nan_meas, drv)
    assert bool(info.fallback)
    assert int(info.status) not in USABLE_STATUS or not np.all(np.isfinite(info.u_ctrl))
    assert np.all(np.isfinite(tq)) and np.all(np.isfinite(info.u))
    lb, ub = np.asarray(info.data.lb[0]), np.asarray(info.data.ub[0])
    assert np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))
    held = np.clip(np.asarray(state.u_prev), lb, ub)
    cols = ctrl.input_columns
    np.testing.assert_array_equal(info.u[cols], held)
    np.testing.assert_array_equal(nxt.u_prev, held)
    assert np.all(info.u[cols] >= lb) and np.all(info.u[cols] <= ub)
    np.testing.assert_allclose(
        tq, ctrl.example.wheel_torques(info.u, info.driver_torque), rtol=1e-12
    )
    cold = ctrl.solver.cold_state(F64)
    for a, b in zip(jax.tree.leaves(nxt.warm), jax.tree.leaves(cold), strict=True):
        np.testing.assert_array_equal(a, b)
    # recovery: the next good measurement converges, exactly as a cold start would
    tq2, _, info2 = replay.step(nxt, p, meas, drv)
    assert int(info2.status) == Status.SOLVED and not bool(info2.fallback)
    tq3, _, info3 = replay.step(ControllerState(cold, held), p, meas, drv)
    np.testing.assert_array_equal(tq2, tq3)
    assert int(info2.iterations) == int(info3.iterations)
    # and the warm start it replaced did help: the logged warm step needs fewer iterations
    assert int(replay.out[k][1].iterations) < int(info2.iterations)


def test_wrong_horizon_is_refused(replay):
    ctrl, p = replay.ctrl, replay.params.controller
    kind = ctrl.example.settings_type
    wrong = p._replace(settings=kind(horizon=ctrl.horizon + 1).as_arrays(F64))
    args = (replay.states[0], wrong, replay.meas[0], replay.drivers[0])
    msg = rf"^settings\.horizon: the controller was built for N_p = {ctrl.horizon}, got "
    with pytest.raises(ValueError, match=msg):
        replay.step(*args)
    with pytest.raises(ValueError, match=msg):
        ctrl.step(*args)


def test_controller_validates_its_fields():
    from ampc_jax.vehicle import CRUISE

    with pytest.raises(ValueError, match=r"^formulation: "):
        Controller(CRUISE, ("LST",), 2, formulation="none")
    with pytest.raises(ValueError, match=r"^enabled: "):
        Controller(CRUISE, ("VSC",), 2)
    with pytest.raises(ValueError, match=r"^enabled: "):
        Controller(CRUISE, (), 2)
    c = Controller(CRUISE, ["YRT", "LST"], 2)
    assert c.enabled == ("YRT", "LST") and c.topology.objective_names == ("LST", "YRT")
    assert hash(c) == hash(Controller(CRUISE, ("YRT", "LST"), 2))
    # horizon check also for a cruise settings object of the wrong horizon
    assert CruiseSettings(horizon=3).horizon != c.horizon


def test_one_compiled_step_serves_every_parameter_point(cruise_replay):
    """rho scales, relaxation, tolerances and weights are arguments of the jitted
    step: one trace, one compilation; each point gives its own result, the one a
    step compiled for that point alone gives."""
    replay = cruise_replay
    ctrl, k = replay.ctrl, 10
    name = replay.res.scenario
    ex = ctrl.example
    weight = ex.settings_type.WEIGHTS[1]  # q_yrt, q_wsc
    configs = [
        config_for(name, rho_scale=(0.5, 0.5), relaxation=1.2),
        config_for(name, rho_scale=(2.0, 1.0), relaxation=1.0),
        config_for(name, rho_scale=(1.0, 0.2), relaxation=1.7, tol_primal=1e-4, tol_dual=1e-4),
        with_settings(config_for(name), **{weight: 0.2 * getattr(ex.settings_type(), weight)}),
    ]
    assert all(controller_for(c) == ctrl for c in configs)
    # the replay's jitted step: traced once for the 40 steps of its run (and the
    # other tests' calls), it serves every point without tracing again
    f = replay.step
    args = (replay.states[k], replay.meas[k], replay.drivers[k])
    f(args[0], replay.params.controller, *args[1:])
    cached = f._cache_size()  # (the other tests' calls may add entries, not traces)
    outs = []
    for c in configs:
        p = c.loop_params(F64).controller
        tq, _, info = f(args[0], p, *args[1:])
        outs.append((np.asarray(tq), int(info.iterations), p))
    assert len(replay.traces) == 1 and f._cache_size() == cached
    # the points are different problems for the solver
    assert len({it for _, it, _ in outs}) >= 2, [it for _, it, _ in outs]
    for i in range(len(outs)):
        for j in range(i):
            assert not np.array_equal(outs[i][0], outs[j][0]), (i, j)
    # one point against a step compiled with that point's numbers as constants
    tq_c, it_c, p_c = outs[2]
    tq_k, _, info_k = jax.jit(lambda: ctrl.step(args[0], p_c, *args[1:]))()
    np.testing.assert_allclose(tq_k, tq_c, rtol=1e-9, atol=1e-9)
    assert int(info_k.iterations) == it_c


def test_the_closed_loop_runs_the_papers_iteration_unless_asked():
    """The reproduction's controller, shadow and timing run the paper's iteration
    (no finish, eq.opt_ro at every step) whatever Local Explicit's own defaults;
    --finish active_set changes the controller's finish alone; a bad finish is
    named."""
    from ampc_jax.closed_loop.shadow import IntegratedShadow
    from ampc_jax.formulations import PAPER_ITERATION

    for name in ("cruise_lane_change", "stability_dlc"):
        cfg = config_for(name, shadow=False)
        s = controller_for(cfg).solver
        assert (cfg.finish, s.finish, s.rho_method) == ("none", "none", "power")
        fin = controller_for(config_for(name, shadow=False, finish="active_set")).solver
        assert (fin.finish, fin.rho_method) == ("active_set", "power")
        sh = IntegratedShadow(controller_for(cfg).topology).solver
        assert {k: getattr(sh, k) for k in PAPER_ITERATION} == PAPER_ITERATION
    with pytest.raises(ValueError, match=r"^finish: "):
        config_for("cruise_lane_change", finish="exact")
