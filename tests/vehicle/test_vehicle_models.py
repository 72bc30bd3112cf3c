"""Tests of ampc_jax.vehicle's control models as a whole: constants, references,
JAX properties, the settings (validation, pytree), and both models against the
nonlinear plant's response to each agent's input.

Each printed-paper deviation (paper-notes items 1-4, 9, 11) is pinned in this
folder: items 1, 2 here, the others in test_cruise.py and test_stability.py.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.vehicle import (
    CRUISE,
    STABILITY,
    CruiseSettings,
    StabilitySettings,
    VehicleParams,
)
from ampc_jax.vehicle.cruise import cruise_control_model, cruise_wheel_torques
from ampc_jax.vehicle.models import yaw_rate_reference
from ampc_jax.vehicle.params import wheel_positions
from ampc_jax.vehicle.plant import initial_state, measure, plant_step
from ampc_jax.vehicle.stability import stability_control_model

pytestmark = pytest.mark.timeout(120)

P = VehicleParams()
DT = 0.05


# --------------------------------------------------------------------------- constants
def test_topology_constants():
    assert CRUISE.agents == ("DTR", "RTV", "FDB")
    assert CRUISE.objectives == ("LST", "YRT")
    # paper-notes item 1: LST observes v_x, YRT the yaw rate (printed swapped).
    assert CRUISE.states == ("v_x", "v_y", "yaw_rate")
    assert CRUISE.outputs["LST"] == ((1.0, 0.0, 0.0),)
    assert CRUISE.outputs["YRT"] == ((0.0, 0.0, 1.0),)
    assert set(CRUISE.groups["LST"]) == {"DTR", "FDB"}
    assert set(CRUISE.groups["YRT"]) == {"RTV", "FDB"}
    assert STABILITY.agents == ("TCR", "RTV", "FDB")
    assert STABILITY.objectives == ("VSC", "WSC")
    assert STABILITY.states == ("v_y", "yaw_rate", "omega_RL", "omega_RR")
    assert STABILITY.outputs["VSC"] == ((0.0, 1.0, 0.0, 0.0),)
    assert STABILITY.outputs["WSC"] == ((0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))
    assert set(STABILITY.groups["VSC"]) == {"RTV", "FDB"}
    assert set(STABILITY.groups["WSC"]) == {"TCR", "RTV"}


def test_table_parameters():
    # Table I; paper-notes item 2: I_w is a wheel inertia (kg m^2), T_w the track.
    assert (P.m, P.I_z, P.a, P.b, P.L, P.R_w, P.K_us, P.T_w) == (
        2272.0,
        4600.0,
        1.42,
        1.43,
        2.85,
        0.351,
        0.005,
        1.66,
    )
    assert P.I_w == 1.6
    assert P.a + P.b == pytest.approx(P.L)


def test_unit_rtv_gives_yaw_acceleration(make_meas):
    """A unit RTV torque: yaw acceleration T_w/(I_z R_w) (paper-notes item 3), both examples."""
    cm = cruise_control_model(make_meas(), 0.0, 15.0, 1.0, P, CruiseSettings())
    sm = stability_control_model(make_meas(), 0.0, 500.0, 1.0, P, StabilitySettings())
    expect = P.T_w / (P.I_z * P.R_w)
    assert cm.B[1][2, 0] / DT == pytest.approx(expect, rel=1e-14)
    assert sm.B[1][1, 0] / DT == pytest.approx(expect, rel=1e-14)
    # the same torque through the wheel-torque map gives the same moment balance
    tq = cruise_wheel_torques((jnp.zeros(1), jnp.ones(1), jnp.zeros(2)))
    x, y = wheel_positions(P)
    mz = float(jnp.sum(-y * tq / P.R_w))
    assert mz / P.I_z == pytest.approx(expect, rel=1e-14)


# --------------------------------------------------------------------------- references
def test_yaw_rate_reference_linear_and_friction_limited():
    v, d = 10.0, 0.02
    lin = v * d / (P.L + P.K_us * v**2)
    assert float(yaw_rate_reference(v, d, 1.0, P)) == pytest.approx(lin)
    assert float(yaw_rate_reference(v, -d, 1.0, P)) == pytest.approx(-lin)
    # large steer on low friction: limited to mu g / v
    assert float(yaw_rate_reference(20.0, 0.2, 0.3, P)) == pytest.approx(0.3 * P.g / 20.0)
    assert float(yaw_rate_reference(20.0, -0.2, 0.3, P)) == pytest.approx(-0.3 * P.g / 20.0)
    # finite at standstill and zero steer
    for v in (0.0, 1e-9, -0.0):
        assert np.isfinite(float(yaw_rate_reference(v, 0.3, 1.0, P)))
    assert float(yaw_rate_reference(15.0, 0.0, 1.0, P)) == 0.0
    g = jax.grad(lambda v: yaw_rate_reference(v, 0.1, 1.0, P))(0.0)
    assert np.isfinite(float(g))


# --------------------------------------------------------------------------- jax properties
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_models_jit_vmap_dtype(dtype, make_meas):
    m = make_meas(dtype=dtype)
    ms = jax.tree.map(lambda x: jnp.stack([x, 1.1 * x]), m)
    f = jax.jit(
        jax.vmap(
            lambda mm: cruise_control_model(
                mm, jnp.asarray(0.03, dtype), jnp.asarray(15.0, dtype), 1.0, P, CruiseSettings()
            )
        )
    )
    cm = f(ms)
    assert cm.A.shape == (2, 3, 3)
    for leaf in jax.tree.leaves(cm):
        assert leaf.dtype == dtype
        assert np.all(np.isfinite(leaf))
    g = jax.jit(
        jax.vmap(
            lambda mm, t: stability_control_model(
                mm, jnp.asarray(0.03, dtype), t, 1.0, P, StabilitySettings()
            )
        )
    )
    sm = g(ms, jnp.array([500.0, -200.0], dtype))
    for leaf in jax.tree.leaves(sm):
        assert leaf.dtype == dtype
    # float32 agrees with float64
    cm64 = cruise_control_model(make_meas(), 0.03, 15.0, 1.0, P, CruiseSettings())
    np.testing.assert_allclose(cm.B[2][0], cm64.B[2], rtol=1e-5)


# --------------------------------------------------------------------------- model vs plant
def test_corrected_models_predict_plant_better_than_literal():
    """One-step predictions from a cornering / launching operating point of the plant.

    Cross-checks the signs of A_d, B_d and W_d against the independent plant; the
    corrected affine forms (paper-notes item 9 and the wheel reaction) are far closer.
    """

    def run(s, steer, tq, mu, n):
        return jax.lax.scan(lambda s, _: (plant_step(s, steer, tq, mu, P), None), s, None, n)[0]

    # cruise: steady cornering, zero inputs
    s = run(initial_state(15.0, P), 0.05, jnp.zeros(4), 1.0, 40)
    m = measure(s, 0.05, jnp.zeros(4), 1.0, P)
    s1 = run(s, 0.05, jnp.zeros(4), 1.0, 1)
    dx = np.array([s1.v_x, s1.v_y, s1.r]) - np.array([s.v_x, s.v_y, s.r])
    errs = {}
    for lit in (False, True):
        cm = cruise_control_model(m, 0.05, 15.0, 1.0, P, CruiseSettings(literal=lit))
        errs[lit] = np.abs(np.asarray(cm.A @ cm.x0 + cm.w - cm.x0) - dx)
    assert errs[False][1] < 1e-3 < 0.1 < errs[True][1]  # v_y: the doubled -r v_x term
    assert errs[False][2] < 0.1 * abs(float(s.r))
    # stability: driven rear wheels with a moderate torque (no spin)
    tq0 = jnp.array([0.0, 0.0, 600.0, 600.0])
    s = run(initial_state(10.0, P), 0.0, tq0, 0.3, 40)
    m = measure(s, 0.0, tq0, 0.3, P)
    s1 = run(s, 0.0, tq0, 0.3, 1)
    d_om = np.asarray(s1.omega[2:] - s.omega[2:])
    e = {}
    for lit in (False, True):
        sm = stability_control_model(m, 0.0, 1200.0, 0.3, P, StabilitySettings(literal=lit))
        e[lit] = np.abs(np.asarray(sm.A @ sm.x0 + sm.w - sm.x0)[2:] - d_om)
    assert np.all(e[False] < 0.5) and np.all(e[True] > 10.0)


# --------------------------------------------------------------------------- B vs plant
_AGENT_STEPS = (("DTR/TCR", 100.0), ("RTV", 50.0), ("FDB_L", -100.0), ("FDB_R", -100.0))
"""Small input steps per input column (Nm), in the order of ``hstack(model.B)``."""


def _plant_steps(ps, steer, tq, mu, n):
    def body(s, _):
        return plant_step(s, steer, tq, mu, P), None

    return jax.lax.scan(body, ps, None, length=n)[0]


_plant_run = jax.jit(_plant_steps, static_argnums=(4,))


def _input_responses(ps, steer, mu, wheel_torques, states, n_periods=1):
    """Plant response to a step on each agent input, shape (n_states, 4 input columns).

    ``wheel_torques(u)`` maps the example's (4,) agent inputs ``[U_1, U_2, U_3
    (2)]`` to the four wheel torques exactly as the closed loop does (it is the
    example's ``VehicleExample.wheel_torques``, which
    ``closed_loop.Controller.step`` calls).  The response is the difference of
    two plant runs from the same state, with and without the step, so the
    operating point's own drift cancels.
    """
    base = states(_plant_run(ps, steer, wheel_torques(jnp.zeros(4)), mu, n_periods))
    cols = []
    for j, (_, du) in enumerate(_AGENT_STEPS):
        u = np.zeros(4)
        u[j] = du
        cols.append(
            states(_plant_run(ps, steer, wheel_torques(jnp.asarray(u)), mu, n_periods)) - base
        )
    return np.stack(cols, axis=1)


def _check_sign_and_ratio(plant, model, rows_cols, lo, hi, what):
    for i, j in rows_cols:
        ratio = plant[i, j] / model[i, j]
        assert lo <= ratio <= hi, f"{what}: state {i}, input {_AGENT_STEPS[j][0]}: {ratio:.3f}"


@pytest.mark.parametrize("v0, steer, mu", [(15.0, 0.0, 1.0), (15.0, 0.04, 1.0), (20.0, 0.03, 0.6)])
def test_cruise_B_matches_plant_input_response(v0, steer, mu):
    """Cruise model's B_d against the nonlinear plant, from a steady (coasting) state.

    One control period after a small step on one agent input (DTR +100 Nm, RTV
    +50 Nm, FDB -100 Nm on one front wheel), the controlled states respond as
    ``B_d dU`` predicts: v_x for DTR and FDB (LST), the yaw rate for RTV and FDB
    (YRT).  Signs must agree, and plant/model lies in [0.5, 1.05]: the model
    ignores the torque spent on the wheel's own acceleration (a few %) and the
    tyres' yaw damping that builds up within the period (measured 0.89-0.95 on
    v_x, 0.63-0.94 on the yaw rate), so it may over-predict but never by 2x nor
    under-predict.  v_y is not checked over one period: its B_d entries are the
    brake force's lateral component (``sin delta``), smaller than the plant's
    kinematic ``-v_x dr`` coupling within the same period; over two periods the
    model carries that coupling through A_d, and there the signs of
    ``(A_d + I) B_d dU`` and the plant's v_y agree.
    """
    ps = _plant_run(initial_state(v0, P), steer, jnp.zeros(4), mu, 60)
    cm = cruise_control_model(
        measure(ps, steer, jnp.zeros(4), mu, P), steer, v0, mu, P, CruiseSettings()
    )
    dU = np.array([du for _, du in _AGENT_STEPS])
    B = np.hstack([np.asarray(b) for b in cm.B]) * dU  # (3, 4) one-step model response

    def states(s):
        return np.array([s.v_x, s.v_y, s.r])

    # with the MPC the cruise vehicle gets no driver torque (its DTR agent is the drive)
    def wheel_torques(u):
        return CRUISE.wheel_torques(u, CRUISE.driver_torque_seen(jnp.asarray(0.0), mpc=True))

    plant = _input_responses(ps, steer, mu, wheel_torques, states)
    # v_x: DTR, FDB_L, FDB_R; yaw rate: RTV, FDB_L, FDB_R
    _check_sign_and_ratio(plant, B, [(0, 0), (0, 2), (0, 3)], 0.5, 1.05, "cruise v_x")
    _check_sign_and_ratio(plant, B, [(2, 1), (2, 2), (2, 3)], 0.5, 1.05, "cruise yaw rate")
    # v_y over two periods: signs of (A + I) B dU (RTV and FDB; DTR does not steer)
    plant2 = _input_responses(ps, steer, mu, wheel_torques, states, n_periods=2)
    model2 = (np.asarray(cm.A) + np.eye(3)) @ B
    for j in (1, 2, 3):
        assert np.sign(plant2[1, j]) == np.sign(model2[1, j]) != 0


@pytest.mark.parametrize(
    "v0, steer, mu, T_drv", [(10.0, 0.0, 0.3, 600.0), (12.0, 0.04, 1.0, 800.0)]
)
def test_stability_B_matches_plant_input_response(v0, steer, mu, T_drv):
    """Stability model's B_d against the plant, driver torque held, tyres unsaturated.

    Yaw-rate row (VSC; RTV and FDB): sign and plant/model in [0.5, 1.05], as for
    the cruise model (measured 0.63-0.81).  Wheel rows (WSC; TCR and RTV on
    omega_RL, omega_RR): sign only.  They are the paper's integrator
    ``I_w omega' = T`` (eq.VSC_system; the corrected W_d only adds the held
    measured F_x), while in the plant a tyre in its linear range holds the
    wheel with its slip stiffness: a torque step moves the wheel speed only to
    the new equilibrium slip, ``dkappa = dT / (R_w dF_x/dkappa)``, so the model
    over-predicts the response 8-30x (measured plant/model 0.03-0.12).
    """

    def wheel_torques(u):
        return STABILITY.wheel_torques(u, T_drv)

    tq0 = wheel_torques(jnp.zeros(4))
    ps = _plant_run(initial_state(v0, P), steer, tq0, mu, 40)
    m = measure(ps, steer, tq0, mu, P)
    assert np.all(np.abs(np.asarray(m.slip)) < 0.05)  # linear range
    sm = stability_control_model(m, steer, T_drv, mu, P, StabilitySettings())
    dU = np.array([du for _, du in _AGENT_STEPS])
    B = np.hstack([np.asarray(b) for b in sm.B]) * dU  # (4, 4)

    def states(s):
        return np.array([s.v_y, s.r, s.omega[2], s.omega[3]])

    plant = _input_responses(ps, steer, mu, wheel_torques, states)
    _check_sign_and_ratio(plant, B, [(1, 1), (1, 2), (1, 3)], 0.5, 1.05, "stability yaw rate")
    wheel = [(i, j) for i in (2, 3) for j in (0, 1)]
    _check_sign_and_ratio(plant, B, wheel, 1e-3, np.inf, "stability wheel (sign)")
    assert max(plant[i, j] / B[i, j] for i, j in wheel) < 0.3  # the documented over-prediction


def test_stability_wheel_rows_exact_when_the_tyre_is_saturated():
    """Spinning rear wheels (slip ~8 on mu = 0.3): the integrator wheel rows are exact.

    With the tyre past its peak, ``dF_x/dkappa <= 0`` and the road's reaction no
    longer depends on the wheel speed, so a torque step dT changes the wheel
    speed by ``dt dT / I_w`` as B_TCR and B_RTV predict (plant/model 0.95-1.02).
    This also checks the plant's wheel step: a slope-bounded step of the kind
    used before added inertia and gave 0.82 here.
    """
    T_drv, mu, steer = 1500.0, 0.3, 0.0

    def wheel_torques(u):
        return STABILITY.wheel_torques(u, T_drv)

    tq0 = wheel_torques(jnp.zeros(4))
    ps = _plant_run(initial_state(10.0, P), steer, tq0, mu, 40)
    m = measure(ps, steer, tq0, mu, P)
    assert np.all(np.asarray(m.slip[2:]) > 2.0)
    sm = stability_control_model(m, steer, T_drv, mu, P, StabilitySettings())
    dU = np.array([du for _, du in _AGENT_STEPS])
    B = np.hstack([np.asarray(b) for b in sm.B]) * dU

    def states(s):
        return np.array([s.v_y, s.r, s.omega[2], s.omega[3]])

    plant = _input_responses(ps, steer, mu, wheel_torques, states)
    wheel = [(i, j) for i in (2, 3) for j in (0, 1)]
    _check_sign_and_ratio(plant, B, wheel, 0.95, 1.02, "saturated wheel")


# --------------------------------------------------------------------------- settings checks
def test_default_settings_validate_and_edges_are_allowed():
    assert CruiseSettings().validate() == CruiseSettings()
    assert StabilitySettings().validate() == StabilitySettings()
    # Q_j = 0 switches an objective's tracking off, a zero bound fixes an agent at 0
    CruiseSettings(q_yrt=0.0, fdb_max=0.0, horizon=1, q_lst=10).validate()
    StabilitySettings(q_wsc=0, slip_des=0.0, literal=True).validate()
    # the examples build their validated defaults
    assert CRUISE.settings() == CruiseSettings()
    assert STABILITY.settings(q_vsc=100.0) == StabilitySettings(q_vsc=100.0)
    with pytest.raises(ValueError, match=r"^q_vsc: expected"):
        STABILITY.settings(q_vsc=-1.0)


@pytest.mark.parametrize(
    ("kind", "kw", "field"),
    [
        (CruiseSettings, {"horizon": 0}, "horizon"),
        (CruiseSettings, {"horizon": 2.0}, "horizon"),
        (CruiseSettings, {"horizon": True}, "horizon"),
        (CruiseSettings, {"dt": 0.0}, "dt"),
        (CruiseSettings, {"dt": float("nan")}, "dt"),
        (CruiseSettings, {"q_yrt": -5.0}, "q_yrt"),
        (CruiseSettings, {"q_lst": float("inf")}, "q_lst"),
        (CruiseSettings, {"q_lst": "4"}, "q_lst"),
        (CruiseSettings, {"r_dtr": 0.0}, "r_dtr"),
        (CruiseSettings, {"r_fdb": -1e-6}, "r_fdb"),
        (CruiseSettings, {"dtr_max": -1.0}, "dtr_max"),
        (CruiseSettings, {"literal": "no"}, "literal"),
        (StabilitySettings, {"horizon": -1}, "horizon"),
        (StabilitySettings, {"q_wsc": -0.02}, "q_wsc"),
        (StabilitySettings, {"q_vsc": float("nan")}, "q_vsc"),
        (StabilitySettings, {"r_tcr": 0.0}, "r_tcr"),
        (StabilitySettings, {"rtv_max": float("inf")}, "rtv_max"),
        (StabilitySettings, {"slip_des": 1.0}, "slip_des"),
        (StabilitySettings, {"slip_des": -0.1}, "slip_des"),
    ],
)
def test_settings_validate_names_the_field(kind, kw, field):
    with pytest.raises(ValueError, match=rf"^{field}: expected"):
        kind(**kw).validate()


# --------------------------------------------------------------------------- settings as pytrees
_CRUISE_LEAVES = (
    "q_lst",
    "q_yrt",
    "r_dtr",
    "r_rtv",
    "r_fdb",
    "dtr_max",
    "rtv_max",
    "fdb_max",
)
_STABILITY_LEAVES = (
    "q_vsc",
    "q_wsc",
    "r_tcr",
    "r_rtv",
    "r_fdb",
    "rtv_max",
    "fdb_max",
    "slip_des",
)


@pytest.mark.parametrize(
    ("kind", "leaves"),
    [(CruiseSettings, _CRUISE_LEAVES), (StabilitySettings, _STABILITY_LEAVES)],
)
def test_settings_leaves_are_the_weights_and_bounds(kind, leaves):
    """Weights and bounds are the pytree's leaves; horizon, dt and literal are static."""
    s = kind()
    assert s.STATIC == ("horizon", "dt", "literal")
    assert set(s.field_names()) == set(leaves) | set(s.STATIC)
    flat, treedef = jax.tree_util.tree_flatten_with_path(s)
    assert tuple(p[0].name for p, _ in flat) == leaves
    assert [v for _, v in flat] == [getattr(s, n) for n in leaves]
    # the static fields live in the treedef: a new horizon/dt/literal is a new
    # structure, new weights are not
    same = jax.tree.structure(s)
    assert jax.tree.structure(s.replace(**{leaves[0]: 123.0, leaves[-2]: 7.0})) == same
    for change in ({"horizon": s.horizon + 1}, {"dt": 0.1}, {"literal": True}):
        assert jax.tree.structure(s.replace(**change)) != same, change
    # unflatten rebuilds the settings (static fields kept)
    s2 = s.replace(horizon=4, literal=True)
    back = jax.tree.unflatten(jax.tree.structure(s2), [2.0 * v for v in jax.tree.leaves(s2)])
    assert (back.horizon, back.literal, back.dt) == (4, True, s.dt)
    assert getattr(back, leaves[0]) == 2.0 * getattr(s, leaves[0])
    # as_arrays: every leaf a dtype array, the static fields untouched
    arr = s2.as_arrays(jnp.float32)
    assert all(x.dtype == jnp.float32 and x.shape == () for x in jax.tree.leaves(arr))
    assert (arr.horizon, arr.literal) == (4, True)


def test_settings_as_jit_argument_weights_traced_horizon_static(make_meas):
    """A compiled function of the settings: new weights and bounds reuse it, a new
    horizon (or literal) retraces, and each value reaches the model."""
    traces = []

    def model_w_ub(s):
        traces.append(s.horizon)
        cm = cruise_control_model(make_meas(), 0.05, 15.0, 1.0, P, s)
        return cm.w, jnp.concatenate(cm.ub), s.Q()[1][0, 0]

    f = jax.jit(model_w_ub)
    base = CruiseSettings()
    w0, ub0, q0 = f(base.as_arrays(jnp.float64))
    w1, ub1, q1 = f(base.replace(q_yrt=2.5e3, dtr_max=1500.0).as_arrays(jnp.float64))
    assert len(traces) == 1  # weights and bounds are arguments
    assert float(q0) == 1.0e4 and float(q1) == 2.5e3
    np.testing.assert_allclose(ub0, [2000, 1000, 0, 0])
    np.testing.assert_allclose(ub1, [1500, 1000, 0, 0])
    np.testing.assert_array_equal(w0, w1)
    w_lit, _, _ = f(base.replace(literal=True).as_arrays(jnp.float64))
    assert len(traces) == 2  # literal is static: its own trace
    w_ref = cruise_control_model(make_meas(), 0.05, 15.0, 1.0, P, CruiseSettings(literal=True)).w
    np.testing.assert_allclose(w_lit, w_ref, rtol=1e-12, atol=1e-15)
    assert not np.allclose(w_lit, w0)
    f(base.replace(horizon=5).as_arrays(jnp.float64))
    assert traces == [2, 2, 5]  # horizon is static: its own trace


def test_settings_replace_checks_names_not_values():
    """``replace`` rejects unknown fields but validates nothing itself (values are
    checked by ``validate``, which SimConfig calls: tests/closed_loop/test_config.py)."""
    s = CruiseSettings().replace(q_yrt=-5.0, horizon=0)
    assert (s.q_yrt, s.horizon) == (-5.0, 0)
    assert s.q_lst == CruiseSettings().q_lst
    with pytest.raises(ValueError, match=r"^horizon: "):
        s.validate()
    with pytest.raises(TypeError, match=r"CruiseSettings: unknown field\(s\) \['q_vsc'\]"):
        CruiseSettings().replace(q_vsc=1.0)
    with pytest.raises(TypeError, match=r"'slip'"):
        StabilitySettings().replace(slip=0.1)
    # frozen: a copy, never an edit
    with pytest.raises(AttributeError):
        s.q_yrt = 1.0  # type: ignore[misc]
