"""Vehicle data and the paper's two control models (section "Examples on Vehicle Control").

The two examples of the paper are linear(-affine) prediction models that are
re-linearised at every control step from the measured state and the driver's
steering, eq.eq_linear::

    X^(k+1) = A_d X^(k) + sum_i B_d(i) U_(i)^(k) + W_d

* Cruise control (eq.CC_system_1, eq.CC_objective, eq.CC_system):
  X = [v_x, v_y, yaw rate], agents DTR, RTV, FDB, objectives LST, YRT.
* Holistic stability control (eq.VSC_system, eq.VSC_system_1, eq.VSC_objective):
  X = [v_y, yaw rate, omega_RL, omega_RR], agents TCR, RTV, FDB, objectives VSC, WSC.

Both return a :class:`ControlModel` of plain arrays; the MPC core turns it into
a QP.  Everything here is pure JAX: jit-able, vmap-able over scenarios, and it
keeps the floating dtype of the measurement.

Conventions
-----------
* Wheels are ordered ``[FL, FR, RL, RR]``; wheel torques are in Nm, positive
  drives the wheel forward, negative brakes.
* Body axes: x forward, y to the left, yaw rate positive counter-clockwise.
* Steering: both front wheels turn by the same road-wheel angle
  (:func:`wheel_angles`, parallel steer; the plant uses the same function).

Deviations from the printed paper
---------------------------------
Each item refers to ``/work/shared/paper/NOTES.md``; ``docs/vehicle.md`` gives
the reasoning and ``tests/test_vehicle.py`` pins every choice.

1. (NOTES 1) ``C_LST = [1, 0, 0]`` and ``C_YRT = [0, 0, 1]``: the printed
   eq.CC_objective swaps them.  Always corrected (no literal reading exists:
   the printed pair would track a speed reference with the yaw rate).
2. (NOTES 2) ``I_w`` is a wheel inertia of 1.6 kg m^2, not a track width.
3. (NOTES 3) RTV yaw entry of eq.VSC_system is ``dt T_w / (I_z R_w)`` (same
   moment balance as eq.CC_system); ``T_z`` is undefined in the paper.
4. (NOTES 4) The wheel-speed reference is an angular speed,
   ``omega_ref = v_x (1 + S) / R_w`` with ``S = +S_x,des`` while the driver
   drives (``T_DTR >= 0``) and ``S = -S_x,des`` while the driver brakes
   (``T_DTR < 0``): the desired braking slip is negative.
5. (NOTES 9) eq.CC_system's A_d holds the Jacobian of the body-frame coupling
   terms (``v_x' = r v_y``, ``v_y' = -r v_x``) but is applied to the absolute
   state, which doubles those terms.  The *corrected* form adds
   ``dt [-r0 v_y0, +r0 v_x0, 0]`` to W_d so the one-step prediction is exact at
   the operating point (it is the first-order Taylor model).  The *literal*
   form (``settings.literal=True``) keeps the paper's W_d = B_STR U_STR.
6. eq.VSC_system's wheel rows omit the tyre's reaction ``-R_w F_x`` on the
   wheel (``I_w omega' = T - R_w F_x``), so the literal model predicts that any
   driving torque accelerates the wheel without bound and WSC would cancel the
   driver's torque even without slip.  The *corrected* form adds
   ``-dt R_w F_x,est / I_w`` per rear wheel to W_d, with the measured
   (estimated) longitudinal tyre forces held over the horizon, the same way the
   paper holds the lateral forces F_y in B_STR U_STR.  The literal form
   (``settings.literal=True``) keeps W_d = B_DTR T_DTR + B_STR U_STR.
7. (NOTES 11) TCR's bound [0, T_DTR] moves with the driver torque every step.
   When the driver brakes (T_DTR < 0) the printed interval is empty; TCR then
   lies in [T_DTR, 0], i.e. it may only reduce the *magnitude* of the driver's
   rear-axle torque towards zero (``bounds = [min(0, T), max(0, T)]``).
8. The printed text of eq.CC_system_1 calls T_FDB-L "the right-front" torque;
   the matrix B_d(FDB) (first column uses delta_FL and -T_w) puts it on the
   left front.  U_FDB = [T_FL, T_FR].
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array

__all__ = [
    "CONTROL_DT",
    "CRUISE_AGENTS",
    "CRUISE_C",
    "CRUISE_GROUPS",
    "CRUISE_OBJECTIVES",
    "STABILITY_AGENTS",
    "STABILITY_C",
    "STABILITY_GROUPS",
    "STABILITY_OBJECTIVES",
    "ControlModel",
    "CruiseSettings",
    "Measurement",
    "StabilitySettings",
    "VehicleParams",
    "cruise_bounds",
    "cruise_control_model",
    "cruise_wheel_torques",
    "stability_bounds",
    "stability_control_model",
    "stability_wheel_torques",
    "wheel_angles",
    "wheel_positions",
    "wheel_speed_reference",
    "yaw_rate_reference",
]

CONTROL_DT = 0.05
"""Control period in s (the paper's controllers run at 20 Hz)."""

# --------------------------------------------------------------------------- topology
CRUISE_AGENTS: tuple[str, ...] = ("DTR", "RTV", "FDB")
CRUISE_OBJECTIVES: tuple[str, ...] = ("LST", "YRT")
CRUISE_C: dict[str, list[list[float]]] = {
    "LST": [[1.0, 0.0, 0.0]],  # v_x (NOTES item 1; printed swapped)
    "YRT": [[0.0, 0.0, 1.0]],  # yaw rate
}
CRUISE_GROUPS: dict[str, tuple[str, ...]] = {
    "LST": ("DTR", "FDB"),
    "YRT": ("RTV", "FDB"),
}
"""Agent groups S_j of fig_example_1 (FDB is shared)."""

STABILITY_AGENTS: tuple[str, ...] = ("TCR", "RTV", "FDB")
STABILITY_OBJECTIVES: tuple[str, ...] = ("VSC", "WSC")
STABILITY_C: dict[str, list[list[float]]] = {
    "VSC": [[0.0, 1.0, 0.0, 0.0]],  # yaw rate
    "WSC": [[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]],  # omega_RL, omega_RR
}
STABILITY_GROUPS: dict[str, tuple[str, ...]] = {
    "VSC": ("RTV", "FDB"),
    "WSC": ("TCR", "RTV"),
}
"""Agent groups S_j of fig_example_2 (RTV is shared)."""


# --------------------------------------------------------------------------- data
class VehicleParams(NamedTuple):
    """Vehicle and tyre data (table_param plus what the plant needs).

    The first eight fields are Table I of the paper.  ``I_w`` is read as a wheel
    inertia (NOTES item 2).  The rest are choices for the stand-in plant
    (``ampc_jax.plant``), typical of a large rear-wheel-drive sedan; see
    ``docs/vehicle.md``.

    Tyres use the magic formula ``F = mu F_z sin(C atan(B s))`` per direction
    (E = 0).  With ``C = 1.4`` the longitudinal force peaks at slip
    ``tan(pi / 2.8) / B_x = 0.148`` (close to the paper's desired 15 %) and a
    locked wheel keeps ``sin(1.4 pi / 2) = 0.89`` of the peak.  Small-slip
    stiffness per unit load is ``B C``: longitudinal 19.6, lateral 16.1 front and
    21.7 rear (per rad), giving an understeer gradient
    ``(1/(mu g)) (1/(B_yf C_y) - 1/(B_yr C_y)) = 1.6e-3 s^2/m`` at mu = 1.
    """

    m: float = 2272.0  # kg, vehicle mass
    I_z: float = 4600.0  # kg m^2, yaw inertia
    a: float = 1.42  # m, CG to front axle
    b: float = 1.43  # m, CG to rear axle
    L: float = 2.85  # m, wheel base
    R_w: float = 0.351  # m, effective wheel radius
    K_us: float = 0.005  # s^2/m, *desired* understeer gradient (yaw reference)
    T_w: float = 1.66  # m, track width
    I_w: float = 1.6  # kg m^2, wheel spin inertia (NOTES item 2)
    h_cg: float = 0.55  # m, CG height (load transfer)
    g: float = 9.81  # m/s^2
    B_x: float = 14.0  # longitudinal MF stiffness factor
    C_x: float = 1.4  # longitudinal MF shape factor
    B_yf: float = 11.5  # lateral MF stiffness factor, front
    B_yr: float = 15.5  # lateral MF stiffness factor, rear
    C_y: float = 1.4  # lateral MF shape factor
    f_rr: float = 0.012  # rolling-resistance coefficient
    c_aero: float = 0.5  # N/(m/s)^2, 0.5 rho C_d A_f
    v_eps: float = 1.0  # m/s, lowest speed used in slip denominators (plant)
    omega_eps: float = 0.5  # rad/s, brake-torque regularisation at standstill (plant)


def wheel_positions(params: VehicleParams) -> tuple[Array, Array]:
    """Wheel contact points relative to the CG, shapes (4,) and (4,), [FL, FR, RL, RR]."""
    x = jnp.array([params.a, params.a, -params.b, -params.b])
    y = 0.5 * params.T_w * jnp.array([1.0, -1.0, 1.0, -1.0])
    return x, y


def wheel_angles(steer: Array) -> Array:
    """Road-wheel steering angles [FL, FR, RL, RR], shape (4,), parallel steer.

    Both front wheels take the driver's front road-wheel angle ``delta_f``; the
    rear wheels do not steer.  (Ackermann geometry would change the inner and
    outer angle by ~T_w/(2R) * delta, under 3 % for the radii used here.)
    """
    steer = jnp.asarray(steer)
    z = jnp.zeros_like(steer)
    return jnp.stack([steer, steer, z, z])


class Measurement(NamedTuple):
    """What the controller sees from the plant (all SI units, wheels [FL, FR, RL, RR]).

    Produced by ``ampc_jax.plant.measure``.  Scalars have shape () (or (batch,)
    under vmap); per-wheel fields have shape (4,).
    """

    v_x: Array  # m/s, longitudinal speed (body frame)
    v_y: Array  # m/s, lateral speed (body frame)
    yaw_rate: Array  # rad/s
    omega: Array  # (4,) rad/s, wheel spin speeds
    F_x: Array  # (4,) N, longitudinal tyre forces (wheel frame, estimate)
    F_y: Array  # (4,) N, lateral tyre forces (wheel frame, estimate) -> U_STR
    F_z: Array  # (4,) N, vertical loads
    slip: Array  # (4,) longitudinal slip ratio (omega R_w - v_w) / |v_w|
    slip_angle: Array  # (4,) rad
    a_x: Array  # m/s^2, longitudinal acceleration (body frame)
    a_y: Array  # m/s^2, lateral acceleration (body frame)


class ControlModel(NamedTuple):
    """One control step's affine prediction model, eq.eq_linear.

    ``X^(k+1) = A X^(k) + sum_i B[i] U_(i)^(k) + w`` for k = 0..N_p-1, with the
    objectives' outputs ``C_j X`` tracking ``ref[j]`` at k = 1..N_p.
    """

    A: Array  # (n_x, n_x)  A_d
    B: tuple[Array, ...]  # per agent in AGENTS order, (n_x, n_u_i)  B_d(i)
    w: Array  # (n_x,) W_d, held constant over the horizon
    x0: Array  # (n_x,) X^(0)
    ref: tuple[Array, ...]  # per objective in OBJECTIVES order, (n_y_j,)
    lb: tuple[Array, ...]  # per agent (n_u_i,)
    ub: tuple[Array, ...]  # per agent (n_u_i,)


# --------------------------------------------------------------------------- settings checks
def _check_settings(
    s: NamedTuple,
    *,
    weights: tuple[str, ...],
    input_weights: tuple[str, ...],
    bounds: tuple[str, ...],
) -> None:
    """Refuse settings that make the closed-loop MPC meaningless (ValueError naming the field).

    Python scalars only (the values :class:`~ampc_jax.simulation.SimConfig` hashes);
    settings holding traced arrays are not checked here.
    """

    def number(name: str) -> float:
        v = getattr(s, name)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(f"{name}: expected a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"{name}: expected a finite number, got {v!r}")
        return v

    h = s.horizon
    if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1:
        raise ValueError(f"horizon: expected an integer N_p >= 1 (prediction steps), got {h!r}")
    if not number("dt") > 0:
        raise ValueError(f"dt: expected a positive prediction step in s, got {s.dt!r}")
    for name in weights:
        if number(name) < 0:
            raise ValueError(
                f"{name}: expected a weight >= 0 (a negative Q_j makes the QP non-convex), "
                f"got {getattr(s, name)!r}"
            )
    for name in input_weights:
        if not number(name) > 0:
            raise ValueError(
                f"{name}: expected a weight > 0 (R_(i) = 0 leaves the objectives' Hessians "
                f"H_j singular, so eq.opt_ro's rho* is undefined), got {getattr(s, name)!r}"
            )
    for name in bounds:
        if number(name) < 0:
            raise ValueError(f"{name}: expected a torque bound >= 0 Nm, got {getattr(s, name)!r}")
    if not isinstance(s.literal, (bool, np.bool_)):
        raise ValueError(f"literal: expected True or False, got {s.literal!r}")


class CruiseSettings(NamedTuple):
    """Settings of the cruise-control example (eq.CC_system_1 .. eq.CC_system).

    The paper gives neither weights nor horizon.  Scaling rule: every term is
    O(1) at a "typically large" value, ``Q_j = 1/e_j^2`` and ``R_(i) = 1/T_i^2``
    with T_i the agent's bound (2000, 500, 1000 Nm) and e_LST = 0.5 m/s (so a
    0.5 m/s speed error held for one step costs as much as the full DTR torque).
    For YRT the rule with e = 0.05 rad/s gives 400; the default ``Q_YRT = 1e4``
    (e = 0.01 rad/s) and ``N_p = 2`` (0.1 s) were chosen from closed-loop runs
    on the plant (``docs/vehicle.md``, ``docs/results.md`` "Tuning the cruise
    example"): the model holds the measured lateral tyre forces constant over
    the horizon (the paper's STR disturbance), so it extrapolates the current
    yaw acceleration, and the longer the horizon the worse that prediction.
    With ``N_p = 10`` enabling YRT made the yaw-rate error *larger* than LST
    alone; ``N_p = 5``, ``Q_YRT = 2000`` reduced it by about a quarter;
    ``N_p = 2``, ``Q_YRT = 1e4`` halves it. These defaults are the ones the
    closed-loop simulation uses (one source of truth).

    A NamedTuple of Python scalars is hashable, so it can be a static argument;
    the numeric fields also work as traced leaves (``literal`` selects with
    ``jnp.where``) except ``horizon``, which is a size and must stay static.
    """

    dt: float = CONTROL_DT  # s, the prediction model's step (the loop runs at CONTROL_DT)
    horizon: int = 2  # N_p, prediction steps (static)
    q_lst: float = 4.0  # (m/s)^-2, Q_LST
    q_yrt: float = 1.0e4  # (rad/s)^-2, Q_YRT
    r_dtr: float = 1.0 / 2000.0**2  # Nm^-2, R_(DTR)
    r_rtv: float = 1.0 / 500.0**2  # Nm^-2, R_(RTV)
    r_fdb: float = 1.0 / 1000.0**2  # Nm^-2, R_(FDB) (each of the two inputs)
    dtr_max: float = 2000.0  # Nm, |T_DTR| bound (1000 per rear wheel)
    rtv_max: float = 1000.0  # Nm, |T_RTV| bound (docs/vehicle.md, "Actuator bounds")
    fdb_max: float = 2000.0  # Nm, FDB brakes in [-fdb_max, 0]
    literal: bool = False  # True: paper's literal W_d (NOTES item 9)

    def validate(self) -> CruiseSettings:
        """Check the fields (ValueError naming the field); returns ``self``.

        ``horizon`` an integer >= 1; ``dt`` > 0; ``q_*`` >= 0 (0 switches an
        objective's tracking off; negative is non-convex); ``r_*`` > 0 (a zero
        input weight leaves H_j singular); bounds >= 0 Nm; all finite.
        """
        _check_settings(
            self,
            weights=("q_lst", "q_yrt"),
            input_weights=("r_dtr", "r_rtv", "r_fdb"),
            bounds=("dtr_max", "rtv_max", "fdb_max"),
        )
        return self

    def Q(self) -> tuple[Array, ...]:
        """Per-objective weights Q_j in CRUISE_OBJECTIVES order, shapes (1, 1), (1, 1)."""
        return (jnp.array([[self.q_lst]]), jnp.array([[self.q_yrt]]))

    def R(self) -> tuple[Array, ...]:
        """Per-agent weights R_(i) in CRUISE_AGENTS order, shapes (1,1), (1,1), (2,2)."""
        return (
            jnp.array([[self.r_dtr]]),
            jnp.array([[self.r_rtv]]),
            self.r_fdb * jnp.eye(2),
        )


class StabilitySettings(NamedTuple):
    """Settings of the holistic stability example (eq.VSC_system .. eq.VSC_objective).

    Weights (the paper gives none): ``Q_VSC = 2000`` (as YRT before its
    retuning, see :class:`CruiseSettings`) and ``N_p = 3`` (0.15 s: fewer
    iterations and slightly better yaw tracking in closed loop than 5; the
    simulation's setting).  For WSC a wheel-speed error of 1 rad/s
    (0.35 m/s of slip speed, 3.5 % slip at 10 m/s) should cost about as much as
    300 Nm of TCR, i.e. ``Q_WSC = (300/2000)^2 ~ 0.02``; ``R_(i) = 1/T_i^2`` with
    T_TCR = 2000 Nm (the driver's torque scale), RTV 500 Nm and FDB 1000 Nm.
    The wheel model is an integrator (dt/I_w = 0.031 rad/s per Nm and step), so
    even this small Q_WSC gives a fast wheel-speed loop.
    """

    dt: float = CONTROL_DT  # s, the prediction model's step (the loop runs at CONTROL_DT)
    horizon: int = 3  # N_p (static)
    q_vsc: float = 2000.0  # (rad/s)^-2, Q_VSC
    q_wsc: float = 0.02  # (rad/s)^-2, Q_WSC (each rear wheel)
    r_tcr: float = 1.0 / 2000.0**2  # Nm^-2
    r_rtv: float = 1.0 / 500.0**2  # Nm^-2
    r_fdb: float = 1.0 / 1000.0**2  # Nm^-2 (each)
    rtv_max: float = 1000.0  # Nm (as CruiseSettings)
    fdb_max: float = 2000.0  # Nm
    slip_des: float = 0.15  # S_x,des (eq.VSC_objective)
    literal: bool = False  # True: paper's literal W_d without tyre reaction

    def validate(self) -> StabilitySettings:
        """Check the fields (ValueError naming the field); returns ``self``.

        As :meth:`CruiseSettings.validate`, and ``slip_des`` in [0, 1).
        """
        _check_settings(
            self,
            weights=("q_vsc", "q_wsc"),
            input_weights=("r_tcr", "r_rtv", "r_fdb"),
            bounds=("rtv_max", "fdb_max"),
        )
        sd = self.slip_des
        if isinstance(sd, bool) or not isinstance(sd, (int, float, np.integer, np.floating)):
            raise ValueError(f"slip_des: expected a slip ratio in [0, 1), got {sd!r}")
        if not 0.0 <= float(sd) < 1.0:
            raise ValueError(f"slip_des: expected a slip ratio in [0, 1), got {sd!r}")
        return self

    def Q(self) -> tuple[Array, ...]:
        """Per-objective weights in STABILITY_OBJECTIVES order, shapes (1, 1), (2, 2)."""
        return (jnp.array([[self.q_vsc]]), self.q_wsc * jnp.eye(2))

    def R(self) -> tuple[Array, ...]:
        """Per-agent weights in STABILITY_AGENTS order, shapes (1,1), (1,1), (2,2)."""
        return (
            jnp.array([[self.r_tcr]]),
            jnp.array([[self.r_rtv]]),
            self.r_fdb * jnp.eye(2),
        )


# --------------------------------------------------------------------------- references
def yaw_rate_reference(
    v_x: Array, steer: Array, mu: Array, params: VehicleParams, v_min: float = 0.5
) -> Array:
    """Friction-limited target yaw rate of eq.CC_objective, shape ().

    ``r_ref = sign(delta) min(|v_x delta / (L + K_us v_x^2)|, mu g / v_x)``.
    The friction limit ``mu g / v`` uses ``v = max(|v_x|, v_min)`` so it stays
    finite at standstill (where the first term, -> 0, is the minimum anyway).
    """
    v_x = jnp.asarray(v_x)
    kin = v_x * steer / (params.L + params.K_us * v_x**2)
    lim = mu * params.g / jnp.maximum(jnp.abs(v_x), v_min)
    return jnp.sign(steer) * jnp.minimum(jnp.abs(kin), lim)


def wheel_speed_reference(
    v_x: Array, driver_torque: Array, params: VehicleParams, slip_des: float = 0.15
) -> Array:
    """Rear wheel-speed reference of eq.VSC_objective (NOTES item 4), shape (2,).

    ``omega_ref = v_x (1 + S) / R_w`` with ``S = +slip_des`` when the driver
    drives (``T_DTR > 0``), ``S = -slip_des`` when the driver brakes
    (``T_DTR < 0``) and ``S = 0`` (free rolling) when the driver applies no
    torque.
    """
    s = slip_des * jnp.sign(driver_torque)
    om = v_x * (1.0 + s) / params.R_w
    return jnp.stack([om, om])


# --------------------------------------------------------------------------- bounds
def cruise_bounds(settings: CruiseSettings, dtype=None) -> tuple[tuple[Array, ...], ...]:
    """Per-agent bounds of eq.CC_system_1: ``(lb, ub)`` tuples in CRUISE_AGENTS order."""
    s = settings
    lb = (
        jnp.array([-s.dtr_max], dtype),
        jnp.array([-s.rtv_max], dtype),
        jnp.array([-s.fdb_max, -s.fdb_max], dtype),
    )
    ub = (jnp.array([s.dtr_max], dtype), jnp.array([s.rtv_max], dtype), jnp.zeros(2, dtype))
    return lb, ub


def stability_bounds(
    driver_torque: Array, settings: StabilitySettings
) -> tuple[tuple[Array, ...], ...]:
    """Per-agent bounds of the stability example (NOTES item 11), STABILITY_AGENTS order.

    TCR: ``[min(0, T_DTR), max(0, T_DTR)]`` -- the printed ``[0, T_DTR]`` while the
    driver drives; while the driver brakes TCR may only reduce the braking
    magnitude.  RTV ``[-rtv_max, rtv_max]``, FDB ``[-fdb_max, 0]`` each.
    """
    t = jnp.asarray(driver_torque)
    s = settings
    dt = t.dtype
    lb = (
        jnp.minimum(t, 0.0)[None],
        jnp.array([-s.rtv_max], dt),
        jnp.array([-s.fdb_max, -s.fdb_max], dt),
    )
    ub = (jnp.maximum(t, 0.0)[None], jnp.array([s.rtv_max], dt), jnp.zeros(2, dt))
    return lb, ub


# --------------------------------------------------------------------------- models
def _fdb_columns(delta: Array, params: VehicleParams) -> tuple[Array, Array, Array]:
    """Per-Nm effect of FL/FR brake torque on (v_x', v_y', r'), each shape (2,)."""
    p = params
    d = delta[:2]
    c, s = jnp.cos(d), jnp.sin(d)
    vx = c / (p.m * p.R_w)
    vy = s / (p.m * p.R_w)
    sign = jnp.array([-1.0, 1.0])  # FL at y = +T_w/2, FR at y = -T_w/2
    r = (2.0 * p.a * s + sign * p.T_w * c) / (2.0 * p.I_z * p.R_w)
    return vx, vy, r


def _str_rows(delta: Array, params: VehicleParams) -> tuple[Array, Array, Array]:
    """Per-N effect of the four lateral tyre forces on (v_x', v_y', r'), each (4,)."""
    p = params
    c, s = jnp.cos(delta), jnp.sin(delta)
    vx = -s / p.m
    vy = c / p.m
    sign = jnp.array([1.0, -1.0, 1.0, -1.0])  # +T_w/2 sin for left wheels
    xw = jnp.array([p.a, p.a, -p.b, -p.b])
    r = (xw * c + sign * 0.5 * p.T_w * s) / p.I_z
    return vx, vy, r


def cruise_control_model(
    meas: Measurement,
    steer: Array,
    v_ref: Array,
    mu: Array,
    params: VehicleParams,
    settings: CruiseSettings,
) -> ControlModel:
    """Cruise-control model of eq.CC_system, re-linearised at the measurement.

    Parameters
    ----------
    meas : Measurement
        Current measured state (v_x, v_y, yaw_rate) and lateral tyre forces F_y (4,).
    steer : Array, shape ()
        Driver's front road-wheel angle delta_f (rad).
    v_ref : Array, shape ()
        Target speed v_x,ref of the LST objective (m/s).
    mu : Array, shape ()
        Road friction for the yaw-rate reference's limit.
    params, settings
        Vehicle data and settings; ``settings.literal`` selects the paper's W_d
        (NOTES item 9), else the operating-point-exact affine form.

    Returns
    -------
    ControlModel
        n_x = 3 (X = [v_x, v_y, yaw rate]); B = (B_DTR (3,1), B_RTV (3,1),
        B_FDB (3,2)); ref = ([v_ref], [r_ref]) for (LST, YRT).
    """
    p, s = params, settings
    dt = s.dt
    vx, vy, r = meas.v_x, meas.v_y, meas.yaw_rate
    dtype = jnp.result_type(vx, float)
    one = jnp.ones((), dtype)
    delta = wheel_angles(steer).astype(dtype)

    A = jnp.array(
        [[one, r * dt, vy * dt], [-r * dt, one, -vx * dt], [0 * one, 0 * one, one]], dtype
    )
    B_dtr = jnp.array([[dt / (p.m * p.R_w)], [0.0], [0.0]], dtype)
    B_rtv = jnp.array([[0.0], [0.0], [dt * p.T_w / (p.I_z * p.R_w)]], dtype)
    fx, fy, fr = _fdb_columns(delta, p)
    B_fdb = dt * jnp.stack([fx, fy, fr]).astype(dtype)
    sx, sy, sr = _str_rows(delta, p)
    B_str = dt * jnp.stack([sx, sy, sr]).astype(dtype)
    w_paper = B_str @ meas.F_y.astype(dtype)
    # NOTES item 9: A applied to the absolute state gives dt*(2 r v_y, -2 r v_x) for
    # the coupling terms; subtract one copy so the model is exact at X^(0).
    w_fix = dt * jnp.stack([-r * vy, r * vx, 0 * r]).astype(dtype)
    w = w_paper + jnp.where(s.literal, 0.0, 1.0) * w_fix

    x0 = jnp.stack([vx, vy, r]).astype(dtype)
    r_ref = yaw_rate_reference(vx, steer, mu, p).astype(dtype)
    ref = (jnp.reshape(jnp.asarray(v_ref, dtype), (1,)), r_ref[None])
    lb, ub = cruise_bounds(s, dtype)
    return ControlModel(A, (B_dtr, B_rtv, B_fdb), w, x0, ref, lb, ub)


def stability_control_model(
    meas: Measurement,
    steer: Array,
    driver_torque: Array,
    mu: Array,
    params: VehicleParams,
    settings: StabilitySettings,
) -> ControlModel:
    """Holistic stability model of eq.VSC_system and eq.VSC_system_1.

    Parameters
    ----------
    meas : Measurement
        Current v_x (parameter of A_d), v_y, yaw_rate, rear wheel speeds
        omega[2:], lateral tyre forces F_y (4,) and, for the corrected form, the
        rear longitudinal tyre forces F_x[2:].
    steer : Array, shape ()
        Driver's front road-wheel angle (rad).
    driver_torque : Array, shape ()
        Driver's rear-axle torque T_DTR (Nm, split equally on RL/RR); a
        disturbance in W_d and the moving TCR bound (NOTES item 11).
    mu : Array, shape ()
        Road friction for the yaw-rate reference.
    params, settings
        ``settings.literal`` keeps the paper's W_d (no tyre reaction on the
        wheels); otherwise ``-dt R_w F_x / I_w`` is added per rear wheel.

    Returns
    -------
    ControlModel
        n_x = 4 (X = [v_y, yaw rate, omega_RL, omega_RR]); B = (B_TCR (4,1),
        B_RTV (4,1), B_FDB (4,2)); ref = ([r_ref], [omega_ref, omega_ref]).
    """
    p, s = params, settings
    dt = s.dt
    vx, vy, r = meas.v_x, meas.v_y, meas.yaw_rate
    dtype = jnp.result_type(vx, float)
    delta = wheel_angles(steer).astype(dtype)
    T = jnp.asarray(driver_torque, dtype)

    A = jnp.eye(4, dtype=dtype).at[0, 1].set(-vx * dt)
    k = dt / (2.0 * p.I_w)
    B_tcr = jnp.array([[0.0], [0.0], [-k], [-k]], dtype)
    B_rtv = jnp.array(
        [[0.0], [dt * p.T_w / (p.I_z * p.R_w)], [-dt / p.I_w], [dt / p.I_w]], dtype
    )  # NOTES item 3
    _, fy, fr = _fdb_columns(delta, p)
    zeros2 = jnp.zeros(2, dtype)
    B_fdb = dt * jnp.stack([fy, fr, zeros2, zeros2]).astype(dtype)
    B_dtr = jnp.array([0.0, 0.0, k, k], dtype)
    _, sy, sr = _str_rows(delta, p)
    zeros4 = jnp.zeros(4, dtype)
    B_str = dt * jnp.stack([sy, sr, zeros4, zeros4]).astype(dtype)
    w_paper = B_dtr * T + B_str @ meas.F_y.astype(dtype)
    fx_rear = meas.F_x[2:].astype(dtype)
    w_fix = jnp.concatenate([jnp.zeros(2, dtype), -dt * p.R_w * fx_rear / p.I_w])
    w = w_paper + jnp.where(s.literal, 0.0, 1.0) * w_fix

    x0 = jnp.stack([vy, r, meas.omega[2], meas.omega[3]]).astype(dtype)
    r_ref = yaw_rate_reference(vx, steer, mu, p).astype(dtype)
    om_ref = wheel_speed_reference(vx, T, p, s.slip_des).astype(dtype)
    lb, ub = stability_bounds(T, s)
    return ControlModel(A, (B_tcr, B_rtv, B_fdb), w, x0, (r_ref[None], om_ref), lb, ub)


# --------------------------------------------------------------------------- torque mapping
def cruise_wheel_torques(u: tuple[Array, ...]) -> Array:
    """Wheel torques [FL, FR, RL, RR] (Nm) from the cruise agents' inputs.

    Parameters
    ----------
    u : tuple of arrays
        ``(U_DTR (1,), U_RTV (1,), U_FDB (2,))`` in CRUISE_AGENTS order.
        DTR is split equally on the rear axle; RTV adds +T on RR and -T on RL;
        FDB (<= 0, braking) acts on FL and FR.
    """
    dtr, rtv, fdb = (jnp.asarray(x) for x in u)
    rear = 0.5 * dtr[0]
    return jnp.stack([fdb[0], fdb[1], rear - rtv[0], rear + rtv[0]])


def stability_wheel_torques(u: tuple[Array, ...], driver_torque: Array) -> Array:
    """Wheel torques [FL, FR, RL, RR] (Nm) from the stability agents and the driver.

    Parameters
    ----------
    u : tuple of arrays
        ``(U_TCR (1,), U_RTV (1,), U_FDB (2,))`` in STABILITY_AGENTS order.
    driver_torque : Array, shape ()
        T_DTR; the rear axle gets ``(T_DTR - T_TCR)/2`` per wheel, then -/+ T_RTV
        on RL/RR; FDB acts on FL, FR.
    """
    tcr, rtv, fdb = (jnp.asarray(x) for x in u)
    rear = 0.5 * (driver_torque - tcr[0])
    return jnp.stack([fdb[0], fdb[1], rear - rtv[0], rear + rtv[0]])
