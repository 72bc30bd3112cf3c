"""Tests of ampc_jax.vehicle.plant against closed-form limits and a fine-step reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.vehicle import VehicleParams
from ampc_jax.vehicle import plant as PL
from ampc_jax.vehicle.plant import (
    PLANT_DT,
    initial_state,
    measure,
    plant_step,
    tyre_forces,
    understeer_gradient,
)

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


def test_tyre_slopes_match_autodiff():
    """The analytic dF_x/dkappa, dF_y/dkappa used by the wheel step equal jax.jacfwd's."""
    Fz = jnp.array([4000.0, 5000.0, 5500.0, 6000.0])
    grid = [
        (k, a)
        for k in (-1.0, -0.2, -0.05, 0.0, 1e-4, 0.1, 0.148, 0.4, 3.0)
        for a in (0.0, 0.03, -0.2)
    ]
    for k, a in grid:
        kap = jnp.full(4, k) * jnp.array([1.0, 0.7, 1.3, 0.9])
        alp = jnp.full(4, a)
        _, _, dFx, dFy = PL._tyre_model(kap, alp, Fz, 0.8, P)
        jx, jy = jax.jacfwd(lambda kk, aa=alp: tyre_forces(kk, aa, Fz, 0.8, P))(kap)
        scale = 0.8 * Fz * P.B_x * P.C_x
        np.testing.assert_allclose(dFx / scale, jnp.diag(jx) / scale, atol=1e-6)
        np.testing.assert_allclose(dFy / scale, jnp.diag(jy) / scale, atol=1e-6)
    # zero slip: the small-slip stiffness; beyond the pure-slip peak: negative
    _, _, d0, _ = PL._tyre_model(jnp.zeros(4), jnp.zeros(4), Fz, 1.0, P)
    np.testing.assert_allclose(d0, P.B_x * P.C_x * Fz, rtol=1e-9)
    _, _, d1, _ = PL._tyre_model(jnp.full(4, 0.5), jnp.zeros(4), Fz, 1.0, P)
    assert np.all(np.asarray(d1) < 0)


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


def _wheel_centre_speeds(s, steer, params=P):
    """Longitudinal wheel-centre speeds v_l,i in wheel axes (m/s), from the body state."""
    x = np.array([params.a, params.a, -params.b, -params.b])
    y = 0.5 * params.T_w * np.array([1.0, -1.0, 1.0, -1.0])
    d = np.array([steer, steer, 0.0, 0.0])
    vwx = float(s.v_x) - float(s.r) * y
    vwy = float(s.v_y) + float(s.r) * x
    return vwx * np.cos(d) + vwy * np.sin(d)


def _spun(state, factors=(1.2, 0.8, 0.8, 1.2)):
    """The same state with wheel speeds scaled away from free rolling (+-20 %)."""
    return state._replace(omega=state.omega * jnp.array(factors, state.omega.dtype))


def test_free_rolling_wheel_speed():
    """Wheels started +-20 % off ``v_x / R_w`` settle to it within one control period.

    No resistance: the car keeps its speed (the wheels' momentum exchange
    cancels), and zero torque leaves zero longitudinal force, i.e. zero slip.
    """
    params = P._replace(f_rr=0.0, c_aero=0.0)
    s0 = _spun(initial_state(20.0, params))
    s1, _ = run(s0, 0.0, jnp.zeros(4), 1.0, 1, params)  # 50 ms
    np.testing.assert_allclose(s1.omega, float(s1.v_x) / params.R_w, rtol=1e-6)
    s, _ = run(s0, 0.0, jnp.zeros(4), 1.0, 40, params)
    np.testing.assert_allclose(s.omega, float(s.v_x) / params.R_w, rtol=1e-9)
    assert float(s.v_x) == pytest.approx(20.0, rel=1e-3)
    # with resistance (on the body) the car decelerates, and the wheels follow it
    # with the tiny slip their own deceleration needs (I_w a / (R_w^2 C_kappa) ~ 3e-5)
    s, _ = run(_spun(initial_state(20.0, P)), 0.0, jnp.zeros(4), 1.0, 40)
    assert float(s.v_x) < 19.8
    np.testing.assert_allclose(s.omega, float(s.v_x) / P.R_w, rtol=1e-4)


@pytest.mark.parametrize("resist", [False, True])
def test_free_rolling_cornering_each_wheel_at_its_own_speed(resist):
    """In a steady corner each free-rolling wheel turns at its own ``v_l,i / R_w``.

    ``v_l,i`` is the wheel-centre velocity ``(v_x - r y_i, v_y + r x_i)`` turned
    into the wheel's axes.  Inner and outer wheels differ by ``r T_w / R_w``
    (here 2.6 %, 100x the tolerance); the wheels start +-20 % off.
    """
    params = P if resist else P._replace(f_rr=0.0, c_aero=0.0)
    steer = 0.05
    s, _ = run(_spun(initial_state(15.0, params)), steer, jnp.zeros(4), 1.0, 60, params)
    assert float(s.r) > 0.2  # a left turn: right wheels outside
    free = _wheel_centre_speeds(s, steer, params) / params.R_w
    assert np.ptp(free) / np.mean(free) > 0.02
    assert free[3] > free[2] and free[1] > free[0]
    # the deceleration (tyre drag of the front wheels, resistance) needs a slip of
    # a few 1e-5 on each wheel; 2e-4 is still 100x below the inner/outer spread
    np.testing.assert_allclose(s.omega, free, rtol=2e-4)


def _substeps(state, steer, torques, mu, n):
    """Integrate ``n`` single plant sub-steps, recording what each one applied."""

    def body(s, _):
        m = measure(s, steer, torques, mu, P)
        s1 = plant_step(s, steer, torques, mu, P, dt=PLANT_DT, n_sub=1)
        return s1, (s.v_x, m.F_x, m.F_y, m.F_z, s1.a_x, s1.a_y)

    return jax.lax.scan(body, state, None, length=n)[1]


def substeps(state, steer, torques, mu, n):
    return [np.asarray(x) for x in _substeps_jit(state, steer, torques, mu, n)]


_substeps_jit = jax.jit(_substeps, static_argnums=(4,))


def _resistance(v_x, params=P):
    """Rolling resistance plus aerodynamic drag of the plant (N), from its parameters."""
    return params.f_rr * params.m * params.g * np.clip(v_x / 0.5, -1.0, 1.0) + (
        params.c_aero * v_x * np.abs(v_x)
    )


@pytest.mark.parametrize("mu", [1.0, 0.3])
def test_moderate_braking_follows_the_torque(mu):
    """Braking well inside the friction limit: the torque sets the deceleration.

    Per wheel ``I_w omega' = T - R_w F_x`` with ``omega' = a_x / R_w`` (constant
    small slip), so ``a_x (m + 4 I_w / R_w^2) = 4 T / R_w - F_res(v_x)``.
    """
    T = -0.3 * mu * P.m * P.g * P.R_w / 4
    s, _ = run(initial_state(20.0, P), 0.0, jnp.full(4, T), mu, 20)
    v = float(s.v_x)
    expect = (4 * T / P.R_w - _resistance(v)) / (P.m + 4 * P.I_w / P.R_w**2)
    assert float(s.a_x) == pytest.approx(expect, rel=3e-3)


@pytest.mark.parametrize("steer", [0.0, 0.03])
@pytest.mark.parametrize("mu", [1.0, 0.3])
def test_hard_braking_bounded_by_friction_at_every_substep(mu, steer):
    """Wheels locking under -5000 Nm, checked at each 1 ms sub-step (where the peak is).

    * The four tyre force vectors at every sub-step: ``sum_i |F_i| <= mu sum_i F_z,i
      = mu m g`` (load transfer conserves the total load).
    * What the body received in that sub-step: ``|m (a_x, a_y) + (F_res, 0)| <=
      mu m g`` (the tyre part of the acceleration), and the peak is reached.
    * The deceleration is at most ``mu g + f_rr g + c_aero v_x^2 / m``: friction
      plus the plant's own rolling resistance and drag at the current speed
      (at 20 m/s the resistance adds 2.1 % of g: 7 % of mu g on mu = 0.3).
    """
    mg = P.m * P.g
    vx, Fx, Fy, Fz, ax, ay = substeps(initial_state(20.0, P), steer, jnp.full(4, -5000.0), mu, 800)
    np.testing.assert_allclose(np.sum(Fz, axis=1), mg, rtol=1e-12)
    tyres = np.sum(np.hypot(Fx, Fy), axis=1)
    assert np.all(tyres <= mu * mg * (1 + 1e-9))
    assert np.max(tyres) >= 0.99 * mu * mg
    applied = np.hypot(P.m * ax + _resistance(vx), P.m * ay)
    assert np.all(applied <= mu * mg * (1 + 1e-9))
    assert np.max(applied) >= 0.99 * mu * mg
    decel = -ax
    bound = mu * P.g + P.f_rr * P.g + P.c_aero * vx**2 / P.m
    assert np.all(decel <= bound * (1 + 1e-9))
    assert np.max(decel) > mu * P.g  # resistance on top of the friction peak
    # locked (kappa = -1): the magic formula's sliding value sin(C_x atan(B_x)) = 0.864
    # of the peak, plus resistance
    f_lock = np.sin(P.C_x * np.arctan(P.B_x))
    assert -ax[-1] == pytest.approx((f_lock * mu * mg + _resistance(vx[-1])) / P.m, rel=5e-3)


# (v0, steer, wheel torques, mu): wheel-spin and lock-up transients
_TRANSIENTS = {
    "launch_mu0.3": (2.0, 0.0, [0.0, 0.0, 750.0, 750.0], 0.3),
    "spin_cornering_mu1": (10.0, 0.08, [0.0, 0.0, 2500.0, 2500.0], 1.0),
    "lock_mu0.3": (20.0, 0.0, [-1000.0] * 4, 0.3),
    "lock_mu1": (20.0, 0.0, [-3000.0] * 4, 1.0),
}


def _trajectory(v0, steer, torques, mu, n, n_sub, dtype=jnp.float64):
    tq = jnp.asarray(torques, dtype)

    def body(s, _):
        s = plant_step(s, steer, tq, mu, P, n_sub=n_sub)
        return s, (s.omega, s.v_x)

    s0 = initial_state(v0, P, dtype=dtype)
    return jax.lax.scan(body, s0, None, length=n)[1]


def trajectory(v0, steer, torques, mu, n, n_sub, dtype=jnp.float64):
    """Wheel speeds (n, 4) and v_x (n,) after each control period, as NumPy arrays."""
    out = _trajectory_jit(v0, steer, torques, mu, n, n_sub, dtype)
    return [np.asarray(x) for x in out]


_trajectory_jit = jax.jit(_trajectory, static_argnums=(4, 5, 6))


@pytest.mark.parametrize("case", sorted(_TRANSIENTS))
def test_wheel_dynamics_converge_with_the_step(case):
    """Default 1 ms sub-step vs a 20x finer one (50 us), 0.55 s of spin or lock-up.

    Tolerance at every control period: wheel speeds within 1 % of the peak wheel
    speed + 0.5 rad/s, v_x within 0.01 m/s.  Measured: 0.2-0.9 rad/s (0.25-1.7 %)
    and at most 5.4e-3 m/s; the 50 us reference is itself within 0.03 rad/s and
    2e-4 m/s of a 6 us run.  The earlier plant (linearly implicit wheel step
    with the small-slip stiffness as slope) was off by 6-128 rad/s here (launch
    on mu 0.3: 42.9 against 86.7 rad/s after 0.55 s; v_x up to 0.04 m/s),
    because for a saturated tyre that slope acts as an extra wheel inertia
    ``h R_w^2 B_x C_x mu F_z / v``.
    """
    v0, steer, torques, mu = _TRANSIENTS[case]
    om_c, vx_c = trajectory(v0, steer, torques, mu, 11, 50)
    om_f, vx_f = trajectory(v0, steer, torques, mu, 11, 1000)
    tol = 0.01 * np.max(np.abs(om_f)) + 0.5
    assert np.max(np.abs(om_c - om_f)) <= tol
    assert np.max(np.abs(vx_c - vx_f)) <= 0.01
    # the transient is a real one: a wheel spins up (slip >> peak) or locks
    slip = om_f[-1] * P.R_w / vx_f[-1] - 1.0
    assert np.max(np.abs(slip)) > 0.5
    # float32 follows the same transient
    om32, vx32 = trajectory(v0, steer, torques, mu, 11, 50, jnp.float32)
    assert np.all(np.isfinite(om32)) and np.all(np.isfinite(vx32))
    assert np.max(np.abs(om32 - om_c)) <= tol
    np.testing.assert_allclose(vx32, vx_c, rtol=1e-3)


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
