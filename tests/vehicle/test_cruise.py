"""Tests of ampc_jax.vehicle.cruise: the cruise-control model (eq.CC_system) against
hand-derived moment balances.

Printed-paper deviations pinned here: paper-notes items 1 (C rows, in
test_vehicle_models.py), 3 (RTV yaw entry) and 9 (the corrected affine term).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.vehicle import CRUISE, CruiseSettings, VehicleParams
from ampc_jax.vehicle.cruise import cruise_bounds, cruise_control_model, cruise_wheel_torques
from ampc_jax.vehicle.params import wheel_positions

pytestmark = pytest.mark.timeout(120)

P = VehicleParams()
DT = 0.05


def test_cruise_shapes_and_entries(make_meas):
    m = make_meas()
    steer = 0.05
    cm = cruise_control_model(m, steer, 16.0, 1.0, P, CruiseSettings())
    assert cm.A.shape == (3, 3)
    assert [b.shape for b in cm.B] == [(3, 1), (3, 1), (3, 2)]
    assert cm.w.shape == (3,) and cm.x0.shape == (3,)
    assert [r.shape for r in cm.ref] == [(1,), (1,)]
    # eq.CC_system A_d
    np.testing.assert_allclose(
        cm.A, [[1, 0.2 * DT, 0.3 * DT], [-0.2 * DT, 1, -15 * DT], [0, 0, 1]], rtol=1e-14
    )
    # DTR: force T/R_w on the mass -> dt/(m R_w)
    np.testing.assert_allclose(cm.B[0][:, 0], [DT / (P.m * P.R_w), 0, 0], rtol=1e-14)
    # RTV: +T on RR, -T on LL -> yaw moment T_w T / R_w (paper-notes item 3 form)
    np.testing.assert_allclose(cm.B[1][:, 0], [0, 0, DT * P.T_w / (P.I_z * P.R_w)], rtol=1e-14)
    # FDB: brake torque T on FL at (a, +T_w/2), wheel turned by delta
    c, s = np.cos(steer), np.sin(steer)
    fl = [c / (P.m * P.R_w), s / (P.m * P.R_w), (P.a * s - 0.5 * P.T_w * c) / (P.I_z * P.R_w)]
    fr = [c / (P.m * P.R_w), s / (P.m * P.R_w), (P.a * s + 0.5 * P.T_w * c) / (P.I_z * P.R_w)]
    np.testing.assert_allclose(cm.B[2], DT * np.array([fl, fr]).T, rtol=1e-13)
    np.testing.assert_allclose(cm.x0, [15.0, 0.3, 0.2])
    lb, ub = cm.lb, cm.ub
    np.testing.assert_allclose(np.concatenate(lb), [-2000, -1000, -2000, -2000])
    np.testing.assert_allclose(np.concatenate(ub), [2000, 1000, 0, 0])
    # the example object builds the same model (its driver torque is not used)
    ex = CRUISE.model(m, steer, 123.0, 16.0, 1.0, P, CruiseSettings())
    for a, b in zip(jax.tree.leaves(ex), jax.tree.leaves(cm), strict=True):
        np.testing.assert_array_equal(a, b)


def test_cruise_bounds_follow_the_settings():
    lb, ub = cruise_bounds(CruiseSettings(dtr_max=1500.0, rtv_max=300.0, fdb_max=700.0))
    np.testing.assert_allclose(np.concatenate(lb), [-1500, -300, -700, -700])
    np.testing.assert_allclose(np.concatenate(ub), [1500, 300, 0, 0])


def test_str_disturbance_moment_balance(make_meas):
    """W_d = B_STR F_y: lateral forces' moment and accelerations (eq.CC_system)."""
    steer = 0.08
    Fy = jnp.array([3000.0, 2500.0, 2800.0, 2600.0])
    m = make_meas(v_y=0.0, r=0.0, F_y=Fy)  # no coupling terms
    cm = cruise_control_model(m, steer, 15.0, 1.0, P, CruiseSettings())
    d = np.array([steer, steer, 0, 0])
    x, y = np.asarray(wheel_positions(P)[0]), np.asarray(wheel_positions(P)[1])
    fxb, fyb = -np.asarray(Fy) * np.sin(d), np.asarray(Fy) * np.cos(d)
    expect = DT * np.array([fxb.sum() / P.m, fyb.sum() / P.m, (x * fyb - y * fxb).sum() / P.I_z])
    np.testing.assert_allclose(cm.w, expect, rtol=1e-12)


def test_cruise_corrected_vs_literal_affine_term(make_meas):
    """paper-notes item 9: corrected W_d makes the one-step prediction exact at X^(0)."""
    m = make_meas(v_x=15.0, v_y=0.4, r=0.3, F_y=[0.0] * 4)
    lit = cruise_control_model(m, 0.0, 15.0, 1.0, P, CruiseSettings(literal=True))
    cor = cruise_control_model(m, 0.0, 15.0, 1.0, P, CruiseSettings())
    np.testing.assert_allclose(lit.A, cor.A)
    x0 = cor.x0
    # Euler step of v_x' = r v_y, v_y' = -r v_x, r' = 0 (no forces)
    euler = x0 + DT * jnp.array([0.3 * 0.4, -0.3 * 15.0, 0.0])
    np.testing.assert_allclose(cor.A @ x0 + cor.w, euler, rtol=1e-13)
    # the literal form doubles the coupling terms
    np.testing.assert_allclose(lit.A @ x0 + lit.w - x0, 2 * (euler - x0), rtol=1e-13)
    # the Jacobian (A) is the same in both: the difference is only in w
    np.testing.assert_allclose(cor.w - lit.w, DT * np.array([-0.3 * 0.4, 0.3 * 15.0, 0.0]))


def test_literal_flag_traced(make_meas):
    """The model accepts a traced ``literal`` flag (jnp.where selects).

    (As a field of settings passed to a compiled function, ``literal`` is static:
    test_vehicle_models.py, the settings' pytree tests.)"""
    m = make_meas()
    f = jax.jit(
        lambda lit: cruise_control_model(m, 0.05, 15.0, 1.0, P, CruiseSettings(literal=lit)).w
    )
    w_true = cruise_control_model(m, 0.05, 15.0, 1.0, P, CruiseSettings(literal=True)).w
    w_false = cruise_control_model(m, 0.05, 15.0, 1.0, P, CruiseSettings(literal=False)).w
    # both values of the traced flag select their own form (one compiled function)
    np.testing.assert_allclose(f(True), w_true, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(f(False), w_false, rtol=1e-12, atol=1e-15)
    # and the forms differ by the coupling correction (paper-notes item 9), so a flag
    # ignored under tracing could not pass both lines above
    np.testing.assert_allclose(
        w_false - w_true, DT * np.array([-0.2 * 0.3, 0.2 * 15.0, 0.0]), rtol=1e-12, atol=1e-15
    )


def test_cruise_wheel_torque_map():
    tq = cruise_wheel_torques(
        (jnp.array([1000.0]), jnp.array([200.0]), jnp.array([-300.0, -100.0]))
    )
    np.testing.assert_allclose(tq, [-300.0, -100.0, 300.0, 700.0])
    # the example's map (what the closed loop calls) on the (4,) input vector
    np.testing.assert_allclose(
        CRUISE.wheel_torques(jnp.array([1000.0, 200.0, -300.0, -100.0]), 555.0), tq
    )


def test_cruise_example_behaviour_without_and_with_the_mpc():
    """With the MPC its DTR agent tracks v_ref (the vehicle gets no driver torque);
    without it the driver's speed PI plays DTR within DTR's bounds."""
    T = jnp.asarray(2500.0)
    assert float(CRUISE.driver_torque_seen(T, mpc=True)) == 0.0
    assert float(CRUISE.driver_torque_seen(T, mpc=False)) == 2500.0
    s = CruiseSettings(dtr_max=1800.0)
    np.testing.assert_allclose(CRUISE.no_mpc_inputs(T, s), [1800.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(CRUISE.no_mpc_inputs(-T, s), [-1800.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(CRUISE.no_mpc_inputs(jnp.asarray(300.0), s), [300.0, 0, 0, 0])
    from ampc_jax.vehicle import SCENARIOS

    sc = CRUISE.no_mpc_scenario(SCENARIOS["cruise_lane_change"].scenario)
    assert (float(sc.speed_kp), float(sc.speed_ki)) == (1500.0, 200.0)
    assert CRUISE.slip_target(s) is None
    assert CRUISE.baseline()["disabled"] == ("YRT",)
