"""Tests of ampc_jax.vehicle.manoeuvres: path geometry, the driver on the plant, scenarios."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.testing.budget import budget
from ampc_jax.vehicle import CONTROL_DT, VehicleParams
from ampc_jax.vehicle.cruise import cruise_wheel_torques
from ampc_jax.vehicle.manoeuvres import (
    DLC_SECTIONS,
    SCENARIOS,
    DriverParams,
    double_lane_change,
    driver_step,
    initial_driver_state,
    initial_plant_state,
    join_paths,
    make_scenario,
    path_slope,
    path_y,
    single_lane_change,
    stack_scenarios,
    straight,
)
from ampc_jax.vehicle.plant import measure, plant_step
from ampc_jax.vehicle.stability import stability_wheel_torques

pytestmark = pytest.mark.timeout(120)

P = VehicleParams()
D = DriverParams()


def test_dlc_geometry():
    x0 = 10.0
    p = double_lane_change(x0, 3.5)
    s = np.cumsum(DLC_SECTIONS)
    assert tuple(DLC_SECTIONS) == (15.0, 30.0, 25.0, 25.0, 15.0, 30.0)
    # entry lane, side lane and exit lane at the right stations
    for X in np.linspace(x0 - 10, x0 + s[0], 7):
        assert float(path_y(p, X)) == pytest.approx(0.0, abs=1e-12)
    for X in np.linspace(x0 + s[1], x0 + s[2], 7):
        assert float(path_y(p, X)) == pytest.approx(3.5, abs=1e-12)
    for X in np.linspace(x0 + s[3], x0 + s[5] + 20, 7):
        assert float(path_y(p, X)) == pytest.approx(0.0, abs=1e-12)
    # transitions: halfway at the middle, monotone, smooth (slope 0 at ends)
    assert float(path_y(p, x0 + 15 + 15)) == pytest.approx(1.75)
    assert float(path_y(p, x0 + 70 + 12.5)) == pytest.approx(1.75)
    xs = jnp.linspace(x0 + 15, x0 + 45, 50)
    assert np.all(np.diff(np.asarray(path_y(p, xs))) >= 0)
    assert float(path_slope(p, x0 + 15)) == pytest.approx(0.0, abs=1e-12)
    assert float(path_slope(p, x0 + 30)) == pytest.approx(1.875 * 3.5 / 30)  # quintic peak slope


def test_slc_straight_join():
    slc = single_lane_change(20.0, 30.0, -3.5)
    assert float(path_y(slc, 0.0)) == 0.0 and float(path_y(slc, 60.0)) == -3.5
    assert float(path_y(straight(), 123.0)) == 0.0
    j = join_paths(slc, double_lane_change(100.0, 3.5))
    assert float(path_y(j, 80.0)) == pytest.approx(-3.5)
    assert float(path_y(j, 160.0)) == pytest.approx(0.0)  # -3.5 + 3.5 in the side lane
    assert j.x0.shape == straight().x0.shape  # same shapes -> stackable
    with pytest.raises(ValueError):
        join_paths(j, j)


def _simulate(scenario, n, speed_kp=0.0, speed_ki=0.0, example="stability"):
    sc = scenario._replace(speed_kp=jnp.asarray(speed_kp), speed_ki=jnp.asarray(speed_ki))

    def body(carry, k):
        ps, ds = carry
        ds, steer, T, v_ref = driver_step(ds, ps, k * CONTROL_DT, sc, D)
        if example == "cruise":  # no MPC here: the driver's torque plays DTR
            tq = cruise_wheel_torques((T[None], jnp.zeros(1), jnp.zeros(2)))
        else:
            tq = stability_wheel_torques((jnp.zeros(1), jnp.zeros(1), jnp.zeros(2)), T)
        m = measure(ps, steer, tq, sc.mu, P)
        ps = plant_step(ps, steer, tq, sc.mu, P)
        return (ps, ds), (ps.X, ps.Y, ps.v_x, steer, T, v_ref, m.slip)

    init = (initial_plant_state(sc, P), initial_driver_state())
    return jax.lax.scan(body, init, jnp.arange(n))


simulate = jax.jit(_simulate, static_argnums=(1, 4))


def test_driver_follows_lane_change():
    spec = SCENARIOS["cruise_lane_change"]
    _, (X, Y, vx, steer, T, v_ref, _) = simulate(
        spec.scenario, spec.n_steps, 1500.0, 200.0, "cruise"
    )
    err = np.abs(np.asarray(Y - path_y(spec.scenario.path, X)))
    assert err.max() < 1.2  # m, pure pursuit through an SLC and an ISO DLC at 12-20 m/s
    assert err[-20:].max() < 0.3  # settled after the manoeuvre
    assert np.all(np.abs(np.diff(np.asarray(steer))) <= D.steer_rate_max * D.dt + 1e-12)
    assert np.abs(np.asarray(vx - v_ref)).max() < 2.0
    assert float(X[-1]) > 200.0


def test_launch_brake_driver_alone_spins_rear_wheels():
    spec = SCENARIOS["stability_launch_brake"]
    assert float(spec.scenario.mu) == 0.3
    _, (X, Y, vx, steer, T, _, slip) = simulate(spec.scenario, spec.n_steps)
    slip = np.asarray(slip)
    t = np.arange(spec.n_steps) * CONTROL_DT
    launch = (t > 1.0) & (t < 3.5)
    brake = (t > 4.5) & (t < 7.0)
    assert slip[launch, 2:].min() > 0.5  # far above the desired 15 %
    assert slip[brake, 2:].max() < -0.5  # rear wheels lock while braking
    assert np.all(np.isfinite(np.asarray(vx))) and float(jnp.min(vx)) > 0.5


def test_stability_dlc_driver_alone_spins_out():
    """2800 Nm on the rear axle in the second lane change: a rear wheel spins
    up, the rear axle loses its side force and the driver alone loses the car
    (with the plant's wheel dynamics step-converged; the earlier wheel step
    was too slow to spin the wheel and the driver recovered)."""
    spec = SCENARIOS["stability_dlc"]
    _, (X, Y, vx, steer, T, _, slip) = simulate(spec.scenario, spec.n_steps)
    assert np.asarray(slip)[:, 2:].max() > 0.5
    err = np.abs(np.asarray(Y - path_y(spec.scenario.path, X)))
    assert err.max() > 5.0  # off the course
    assert np.all(np.isfinite(np.asarray(vx)))


def test_scenarios_registry_and_stacking():
    assert set(SCENARIOS) == {"cruise_lane_change", "stability_launch_brake", "stability_dlc"}
    for name, spec in SCENARIOS.items():
        assert spec.name == name
        assert spec.example in ("cruise", "stability")
        assert 0.0 <= spec.focus[0] < spec.focus[1] <= spec.duration
        assert spec.n_steps == round(spec.duration / CONTROL_DT)
    batch = stack_scenarios(list(SCENARIOS.values()))
    assert batch.mu.shape == (3,) and batch.path.x0.shape[0] == 3
    # driver_step vmaps over scenarios
    ps = jax.vmap(lambda s: initial_plant_state(s, P))(batch)
    ds = jax.vmap(lambda _: initial_driver_state())(batch.mu)
    out = jax.vmap(lambda d, p, s: driver_step(d, p, 1.0, s, D))(ds, ps, batch)
    assert out[1].shape == (3,)


def test_make_scenario_float32_driver():
    sc = make_scenario(0.5, 10.0, straight(), ([0.0, 5.0], [10.0, 15.0]), speed_kp=500.0)
    ps = initial_plant_state(sc, P, dtype=jnp.float32)
    ds = initial_driver_state(jnp.float32)
    ds, steer, T, v_ref = driver_step(ds, ps, 2.5, sc, D)
    assert steer.dtype == T.dtype == v_ref.dtype == jnp.float32
    assert float(v_ref) == pytest.approx(12.5)
    assert float(T) == pytest.approx(500.0 * 2.5)


def test_scenarios_are_float64_numpy_whatever_x64_at_import():
    for spec in SCENARIOS.values():
        for leaf in jax.tree.leaves(spec.scenario):
            assert isinstance(leaf, np.ndarray) and leaf.dtype == np.float64
    assert float(SCENARIOS["stability_launch_brake"].scenario.mu) == 0.3
    # imported with x64 off, enabled afterwards (what the CLI does): still exact
    import subprocess
    import sys

    code = (
        "import ampc_jax.vehicle.manoeuvres as m, jax, numpy as np\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "sc = m.SCENARIOS['stability_launch_brake'].scenario\n"
        "assert sc.mu.dtype == np.float64 and float(sc.mu) == 0.3, sc.mu\n"
        "import jax.numpy as jnp\n"
        "assert jnp.asarray(sc.mu).dtype == jnp.float64\n"
        "b = m.stack_scenarios(list(m.SCENARIOS.values()))\n"
        "assert b.mu.dtype == np.float64 and float(b.mu[1]) == 0.3\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=budget(60)
    )
    assert out.returncode == 0, out.stderr
