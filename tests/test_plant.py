"""Tests of ampc_jax.plant against closed-form limits."""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.plant import (
    initial_state,
    measure,
    plant_step,
    tyre_forces,
    understeer_gradient,
)
from ampc_jax.vehicle import VehicleParams

pytestmark = pytest.mark.timeout(120)

P = VehicleParams()


def _run(state, steer, torques, mu, n, params=P):
    def body(s, _):
        s = plant_step(s, steer, torques, mu, params)
        return s, (s.v_x, s.a_x, s.r)

    return jax.lax.scan(body, state, None, length=n)


run = jax.jit(_run, static_argnums=(4, 5))


def test_tyre_pure_slip_peaks_and_ellipse():
    Fz = jnp.full(4, 5000.0)
    k = jnp.linspace(-1.0, 1.0, 2001)
    fx = jax.jit(jax.vmap(lambda kk: tyre_forces(jnp.full(4, kk), jnp.zeros(4), Fz, 0.8, P)[0]))(k)
    assert float(jnp.max(jnp.abs(fx))) == pytest.approx(0.8 * 5000.0, rel=1e-5)
    kpk = float(k[jnp.argmax(fx[:, 0])])
    assert kpk == pytest.approx(np.tan(np.pi / (2 * P.C_x)) / P.B_x, abs=1e-3)
    # small-slip stiffness B C mu F_z
    fx1, fy1 = tyre_forces(jnp.full(4, 1e-6), jnp.full(4, 1e-6), Fz, 1.0, P)
    np.testing.assert_allclose(fx1 / 1e-6, P.B_x * P.C_x * 5000.0, rtol=1e-4)
    np.testing.assert_allclose(
        fy1 / 1e-6, [P.B_yf * P.C_y * 5000.0] * 2 + [P.B_yr * P.C_y * 5000.0] * 2, rtol=1e-4
    )
    # combined slip stays inside the friction circle (equal peaks): |F| <= mu F_z
    kk, aa = jnp.meshgrid(jnp.linspace(-1, 1, 41), jnp.linspace(-0.6, 0.6, 41))
    fx, fy = jax.jit(
        jax.vmap(lambda a, b: tyre_forces(jnp.full(4, a), jnp.full(4, b), Fz, 1.0, P))
    )(kk.ravel(), aa.ravel())
    assert float(jnp.max(jnp.hypot(fx, fy))) <= 5000.0 * (1 + 1e-9)
    assert np.all(np.isfinite(np.asarray(tyre_forces(jnp.zeros(4), jnp.zeros(4), Fz, 1.0, P))))


def test_steady_state_cornering_matches_linear_bicycle():
    """r -> v delta / (L + K v^2), K from the plant's own cornering stiffnesses.

    Low lateral acceleration (about 1.2 m/s^2), no drag, free rolling wheels;
    tolerance 1.5 % (the remaining difference is the steer angle's cos/sin,
    the speed lost to the front tyres' drag and the yaw-damping transients).
    """
    params = P._replace(f_rr=0.0, c_aero=0.0)
    v, delta = 15.0, 0.015
    s, _ = run(initial_state(v, params), delta, jnp.zeros(4), 1.0, 60, params)
    K = float(understeer_gradient(1.0, params))
    assert K > 0  # the plant understeers
    expect = float(s.v_x) * delta / (params.L + K * float(s.v_x) ** 2)
    assert float(s.r) == pytest.approx(expect, rel=0.015)
    assert abs(float(s.a_y)) < 2.0


def test_free_rolling_wheel_speed():
    params = P._replace(f_rr=0.0, c_aero=0.0)
    s, _ = run(initial_state(20.0, params), 0.0, jnp.zeros(4), 1.0, 40, params)
    np.testing.assert_allclose(s.omega, float(s.v_x) / params.R_w, rtol=1e-6)
    assert float(s.v_x) == pytest.approx(20.0, rel=1e-6)
    # with resistance the wheels still roll freely (resistance acts on the body)
    s, _ = run(initial_state(20.0, P), 0.0, jnp.zeros(4), 1.0, 40)
    np.testing.assert_allclose(s.omega, float(s.v_x) / P.R_w, rtol=1e-4)


@pytest.mark.parametrize("mu", [1.0, 0.3])
def test_braking_bounded_by_mu_g(mu):
    s0 = initial_state(20.0, P)
    # moderate braking: follows the torque, well inside the friction limit
    T = -0.3 * mu * P.m * P.g * P.R_w / 4
    _, (_, ax, _) = run(s0, 0.0, jnp.full(4, T), mu, 20)
    assert float(ax[-1]) == pytest.approx(-0.3 * mu * P.g - (P.f_rr * P.g), rel=0.08)
    # very hard braking: wheels lock; deceleration close to, never above, mu g
    _, (vx, ax, _) = run(s0, 0.0, jnp.full(4, -5000.0), mu, 20)
    decel = -np.asarray(ax)
    assert np.all(decel <= mu * P.g * 1.02)  # drag adds < 2 % at 20 m/s
    assert np.max(decel) >= 0.85 * mu * P.g


def test_stop_and_standstill_finite():
    # braking to a stop does not drive the car backwards
    s, (vx, _, _) = run(initial_state(3.0, P), 0.0, jnp.full(4, -1500.0), 1.0, 60)
    assert np.all(np.isfinite(np.asarray(vx)))
    assert float(jnp.min(vx)) > -1e-3
    assert abs(float(s.v_x)) < 1e-3 and np.all(np.abs(np.asarray(s.omega)) < 1e-2)
    # at rest with zero torque, steering does nothing
    s, _ = run(initial_state(0.0, P), 0.3, jnp.zeros(4), 1.0, 20)
    for leaf in jax.tree.leaves(s):
        np.testing.assert_allclose(leaf, 0.0, atol=1e-12)
    # launch from standstill with steering and rear torque: finite, moves forward
    s, (vx, _, r) = run(initial_state(0.0, P), 0.1, jnp.array([0, 0, 600.0, 600.0]), 1.0, 40)
    assert np.all(np.isfinite(np.asarray(jnp.stack(jax.tree.leaves(s)[:6]))))
    assert float(s.v_x) > 1.0


def test_vmap_over_mu_matches_loop():
    mus = jnp.array([0.3, 0.6, 1.0])
    s0 = initial_state(15.0, P)
    tq = jnp.array([0.0, 0.0, 1200.0, 1200.0])
    f = jax.jit(lambda mu: run(s0, 0.05, tq, mu, 20)[0])
    batched = jax.vmap(f)(mus)
    for i, mu in enumerate(mus):
        single = f(mu)
        for a, b in zip(jax.tree.leaves(batched), jax.tree.leaves(single), strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-10, atol=1e-10)


def test_float32_runs_and_agrees():
    s64, _ = run(initial_state(18.0, P), 0.03, jnp.array([0, 0, 400.0, 400.0]), 0.8, 40)
    s32, _ = run(
        initial_state(18.0, P, dtype=jnp.float32),
        0.03,
        jnp.array([0, 0, 400.0, 400.0], jnp.float32),
        0.8,
        40,
    )
    for leaf in jax.tree.leaves(s32):
        assert leaf.dtype == jnp.float32
    np.testing.assert_allclose(s32.v_x, s64.v_x, rtol=1e-4)
    np.testing.assert_allclose(s32.r, s64.r, rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(s32.omega, s64.omega, rtol=1e-4)
    m = measure(s32, 0.03, jnp.zeros(4, jnp.float32), 0.8, P)
    for leaf in jax.tree.leaves(m):
        assert leaf.dtype == jnp.float32


def test_measure_fields():
    s, _ = run(initial_state(15.0, P), 0.04, jnp.array([0, 0, 300.0, 300.0]), 1.0, 40)
    m = measure(s, 0.04, jnp.zeros(4), 1.0, P)
    assert m.F_y.shape == (4,) and m.slip.shape == (4,)
    assert float(jnp.sum(m.F_z)) == pytest.approx(P.m * P.g, rel=1e-9)  # load transfer conserves
    v_rear = m.v_x - m.yaw_rate * 0.5 * P.T_w * jnp.array([1.0, -1.0])  # RL, RR centres
    np.testing.assert_allclose(m.slip[2:], (s.omega[2:] * P.R_w - v_rear) / v_rear, rtol=1e-9)
    assert np.all(np.asarray(m.slip[2:]) > 0)  # driven wheels
    # steady state: lateral forces balance m a_y approximately
    assert float(jnp.sum(m.F_y)) == pytest.approx(P.m * float(s.v_x * s.r), rel=0.03)


def test_ten_seconds_faster_than_real_time():
    s0 = initial_state(20.0, P)
    out = run(s0, 0.02, jnp.zeros(4), 1.0, 200)
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    jax.block_until_ready(run(s0, 0.02, jnp.zeros(4), 1.0, 200))
    elapsed = time.perf_counter() - t0
    assert elapsed < 0.5  # target is well under 0.1 s; loose bound for loaded CI machines
