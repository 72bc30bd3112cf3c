"""Nonlinear double-track plant standing in for CarSim (section "Experimental Studies").

A seven-degree-of-freedom double-track vehicle (plus position and heading):

* body: ``m (v_x' - r v_y) = sum F_x,body - F_res``,
  ``m (v_y' + r v_x) = sum F_y,body``, ``I_z r' = sum (x_i F_y,i - y_i F_x,i)``;
* wheels: ``I_w omega_i' = T_i - R_w F_x,i``;
* tyres: magic formula per direction, ``F = mu F_z sin(C atan(B s))`` (E = 0),
  combined by the *normalised slip* method: with ``s_x = kappa/kappa_p``,
  ``s_y = alpha/alpha_p`` (``kappa_p``, ``alpha_p`` the pure-slip peaks) and
  ``s = |(s_x, s_y)|``, ``F_x = F_x0(s kappa_p) s_x/s`` and
  ``F_y = F_y0(s alpha_p) s_y/s``.  Pure slip reproduces the magic formula, the
  small-slip stiffnesses are unchanged, and the resultant stays inside the
  friction ellipse ``(F_x/F_x,max)^2 + (F_y/F_y,max)^2 <= 1``;
* quasi-static load transfer from the accelerations of the previous sub-step
  (longitudinal ``m a_x h / L``, lateral ``m a_y h / T_w`` shared by the axles
  in proportion to their static load);
* rolling resistance ``f_rr m g`` (regularised through zero speed) and
  aerodynamic drag ``c_aero v_x |v_x|``.

Slips: ``kappa = (omega R_w - v_l) / max(|v_l|, v_eps)`` and
``alpha = -atan(v_t / max(|v_l|, v_eps))`` with (v_l, v_t) the wheel-centre
velocity in wheel axes, so nothing divides by zero at standstill (below
``v_eps`` = 1 m/s the slips become slip *velocities* scaled by 1/v_eps).  The
plant targets forward driving.

Integration: semi-implicit Euler with a fixed sub-step ``h`` (default 1 ms,
50 per 50 ms control period) under ``lax.scan``.  The wheel spin mode is stiff
(time constant ``I_w v / (R_w^2 dF_x/dkappa)``, 0.1-1.5 ms while the tyre is
in its linear range), so each wheel speed gets a linearly implicit (one Newton
step of backward Euler) update with the *local* slope of the combined-slip
tyre force, ``k_i = R_w^2 max(dF_x,i/dkappa, 0) / max(|v_l,i|, v_eps)``::

    I_w (omega_i+ - omega_i) / h = T_eff,i - R_w F_x,i+,
    F_x,i+ = clip(F_x,i + (k_i / R_w) (omega_i+ - omega_i), -mu F_z,i, mu F_z,i).

In the linear range this is L-stable for the spin mode (same fixed points as
the ODE); once the tyre saturates the slope is ~0 or negative, the clip at 0
makes the update explicit and the wheel spins up or locks at the rate
``(T - R_w F_x) / I_w`` of the ODE.  (An upper bound of the slope, as an earlier
version used, adds a spurious inertia ``h k`` for a saturated tyre -- about
I_w at 2.6 m/s on mu 0.3, up to 10 I_w at v_eps on mu 1, with h = 1 ms -- and
the wheel speeds then depend on the step.)  The
body then uses the tyre forces at the *updated* wheel speeds, linearised in
kappa: ``F_x,i+`` above (the force the wheel reacted against) and
``F_y,i+ = F_y,i + dF_y,i/dkappa dkappa_i``, limited to the friction circle
``|F_i| <= mu F_z,i`` that the tyre model itself satisfies.  Without this the
body would see the wheels one step late, an O(h) error multiplied by the slip
stiffness.  The result converges at first order in ``h`` with small
constants (tests/vehicle/test_plant.py compares the default step with a 20x finer one
through wheel spin and lock-up).  Brake torque (negative torque) is regularised
so it holds a wheel at standstill instead of spinning it backwards:
``T_eff = T clip(omega / omega_eps, -1, 1)`` for ``T < 0``, also treated
linearly implicitly below ``omega_eps``.

The controllers' linear models (``ampc_jax.vehicle``) are *not* this plant.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import Array
from jax.typing import DTypeLike

from .params import CONTROL_DT, Measurement, VehicleParams, wheel_angles, wheel_positions

__all__ = [
    "PLANT_DT",
    "PlantState",
    "initial_state",
    "measure",
    "plant_step",
    "tyre_forces",
    "understeer_gradient",
]

PLANT_DT = 1e-3
"""Default integration sub-step (s)."""


class PlantState(NamedTuple):
    """State of the double-track plant (scalars shape (), wheels shape (4,))."""

    X: Array  # m, global position
    Y: Array  # m
    psi: Array  # rad, heading
    v_x: Array  # m/s, body-frame longitudinal speed
    v_y: Array  # m/s, body-frame lateral speed
    r: Array  # rad/s, yaw rate
    omega: Array  # (4,) rad/s, wheel spin [FL, FR, RL, RR]
    a_x: Array  # m/s^2, last body-frame acceleration (for load transfer)
    a_y: Array  # m/s^2


def initial_state(
    v0: Array,
    params: VehicleParams,
    X0: Array = 0.0,
    Y0: Array = 0.0,
    psi0: Array = 0.0,
    dtype: DTypeLike | None = None,
) -> PlantState:
    """Straight running at speed ``v0`` with free-rolling wheels ``omega = v0/R_w``."""
    dtype = dtype or jnp.result_type(float)
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    v0 = f(v0)
    z = jnp.zeros((), dtype)
    return PlantState(f(X0), f(Y0), f(psi0), v0, z, z, jnp.full((4,), v0 / params.R_w), z, z)


def _mf(s: Array, C: float) -> tuple[Array, Array]:
    """Normalised magic formula and its slope, ``f(s)`` and ``f'(s)``.

    ``f(s) = sin(C atan(B_n s))`` with ``B_n = tan(pi/(2C))`` (peak 1 at s = 1),
    ``f'(s) = C B_n cos(C atan(B_n s)) / (1 + B_n^2 s^2)``.
    """
    bn = jnp.tan(jnp.pi / (2.0 * C))
    phi = C * jnp.arctan(bn * s)
    return jnp.sin(phi), C * bn * jnp.cos(phi) / (1.0 + (bn * s) ** 2)


def _peaks(params: VehicleParams, dtype) -> tuple[Array, Array]:
    """Pure-slip peak positions: kappa_p (scalar) and alpha_p per wheel (4,)."""
    p = params
    kp = jnp.tan(jnp.pi / (2.0 * p.C_x)) / p.B_x
    ap_f = jnp.tan(jnp.pi / (2.0 * p.C_y)) / p.B_yf
    ap_r = jnp.tan(jnp.pi / (2.0 * p.C_y)) / p.B_yr
    return jnp.asarray(kp, dtype), jnp.stack([ap_f, ap_f, ap_r, ap_r]).astype(dtype)


def _tyre_model(
    kappa: Array, alpha: Array, F_z: Array, mu: Array, params: VehicleParams
) -> tuple[Array, Array, Array, Array]:
    """Combined-slip forces and their slopes in kappa (alpha held), each shape (4,).

    With ``D = mu F_z``, ``s_x = kappa/kappa_p``, ``s_y = alpha/alpha_p``,
    ``s = |(s_x, s_y)|``, ``c_x = s_x/s``, ``c_y = s_y/s`` and ``f_x``, ``f_y``
    the normalised magic formulas (:func:`_mf`)::

        F_x = D f_x(s) c_x,    F_y = D f_y(s) c_y,
        dF_x/dkappa = (D/kappa_p) [f_x'(s) c_x^2 + (f_x(s)/s) (1 - c_x^2)],
        dF_y/dkappa = (D/kappa_p) [f_y'(s) - f_y(s)/s] c_x c_y

    (``ds/ds_x = c_x``, ``dc_x/ds_x = (1 - c_x^2)/s``, ``dc_y/ds_x = -c_x c_y/s``).
    At zero slip ``dF_x/dkappa = B_x C_x D`` (``f(s)/s -> C B_n``); beyond the
    pure-slip peak it is negative.  ``s`` carries a 1e-12 floor inside the
    root, so nothing divides by zero at zero slip.

    Returns
    -------
    F_x, F_y, dF_x/dkappa, dF_y/dkappa
    """
    p = params
    kp, ap = _peaks(p, jnp.result_type(kappa))
    sx = kappa / kp
    sy = alpha / ap
    s = jnp.sqrt(sx**2 + sy**2 + 1e-12)
    cx, cy = sx / s, sy / s
    D = mu * F_z
    fx, dfx = _mf(s, p.C_x)
    fy, dfy = _mf(s, p.C_y)
    Fx = D * fx * cx
    Fy = D * fy * cy
    dFx = D / kp * (dfx * cx**2 + fx / s * (1.0 - cx**2))
    dFy = D / kp * (dfy - fy / s) * cx * cy
    return Fx, Fy, dFx, dFy


def tyre_forces(
    kappa: Array, alpha: Array, F_z: Array, mu: Array, params: VehicleParams
) -> tuple[Array, Array]:
    """Combined-slip tyre forces (wheel axes), shapes (4,), (4,).

    ``F_x = mu F_z f_x(s) s_x/s`` and ``F_y = mu F_z f_y(s) s_y/s`` with
    ``s_x = kappa/kappa_p``, ``s_y = alpha/alpha_p``, ``s = |(s_x, s_y)|`` and
    ``f(s) = sin(C atan(tan(pi/(2C)) s))`` (peak 1 at s = 1), so
    ``|F| <= mu F_z``.

    Parameters
    ----------
    kappa, alpha : Array, shape (4,)
        Longitudinal slip ratio and slip angle (rad) per wheel [FL, FR, RL, RR].
    F_z : Array, shape (4,)
        Vertical loads (N).
    mu : Array, shape () or (4,)
        Road friction (peak force = mu F_z in both directions).
    """
    Fx, Fy, _, _ = _tyre_model(kappa, alpha, F_z, mu, params)
    return Fx, Fy


def understeer_gradient(mu: Array, params: VehicleParams) -> Array:
    """The plant's own linear understeer gradient K (s^2/m, rad per m/s^2).

    ``K = (m/L) (b/C_f - a/C_r)`` with axle cornering stiffnesses
    ``C_f = B_yf C_y mu m g b / L`` and ``C_r = B_yr C_y mu m g a / L`` (static
    loads, load transfer is linear in F_z and cancels on each axle); the
    steady-state yaw rate is then ``v delta / (L + K v^2)``.
    """
    p = params
    Cf = p.B_yf * p.C_y * mu * p.m * p.g * p.b / p.L
    Cr = p.B_yr * p.C_y * mu * p.m * p.g * p.a / p.L
    return p.m / p.L * (p.b / Cf - p.a / Cr)


class _Forces(NamedTuple):
    """Tyre quantities at a state (wheel axes, each shape (4,))."""

    Fx: Array
    Fy: Array
    dFx: Array  # dF_x/dkappa at the current slips (alpha held)
    dFy: Array  # dF_y/dkappa
    Fz: Array
    kappa: Array
    alpha: Array
    v_den: Array  # max(|v_l|, v_eps): dkappa/domega = R_w / v_den
    cos_d: Array  # cos / sin of the wheel angles
    sin_d: Array


def _forces(state: PlantState, delta: Array, mu: Array, params: VehicleParams) -> _Forces:
    """Loads, slips and combined-slip tyre forces (with slopes) at ``state``."""
    p = params
    dt = state.v_x.dtype
    xw, yw = (x.astype(dt) for x in wheel_positions(p))
    # quasi-static loads
    share = jnp.array([p.b, p.b, p.a, p.a], dt) / p.L
    Fz_static = 0.5 * p.m * p.g * share
    dlong = p.m * state.a_x * p.h_cg / p.L * 0.5 * jnp.array([-1.0, -1.0, 1.0, 1.0], dt)
    dlat = p.m * state.a_y * p.h_cg / p.T_w * share * jnp.array([-1.0, 1.0, -1.0, 1.0], dt)
    Fz = jnp.maximum(Fz_static + dlong + dlat, 0.0)
    # wheel-centre velocities in wheel axes
    vwx = state.v_x - state.r * yw
    vwy = state.v_y + state.r * xw
    c, s = jnp.cos(delta), jnp.sin(delta)
    vl = vwx * c + vwy * s
    vt = -vwx * s + vwy * c
    v_den = jnp.maximum(jnp.abs(vl), p.v_eps)
    kappa = (state.omega * p.R_w - vl) / v_den
    alpha = -jnp.arctan(vt / v_den)
    Fx, Fy, dFx, dFy = _tyre_model(kappa, alpha, Fz, mu, p)
    return _Forces(Fx, Fy, dFx, dFy, Fz, kappa, alpha, v_den, c, s)


def _body_loads(
    Fx: Array, Fy: Array, f: _Forces, v_x: Array, params: VehicleParams
) -> tuple[Array, Array, Array]:
    """Net body-frame forces and yaw moment: ``(sum F_x,body - F_res, sum F_y,body, M_z)``.

    Wheel-axis forces turned by the wheel angle, ``F_res = f_rr m g
    clip(v_x/0.5, -1, 1) + c_aero v_x |v_x|`` and
    ``M_z = sum (x_i F_y,body,i - y_i F_x,body,i)``.
    """
    p = params
    xw, yw = (x.astype(v_x.dtype) for x in wheel_positions(p))
    fxb = Fx * f.cos_d - Fy * f.sin_d
    fyb = Fx * f.sin_d + Fy * f.cos_d
    res = p.f_rr * p.m * p.g * jnp.clip(v_x / 0.5, -1.0, 1.0)
    res = res + p.c_aero * v_x * jnp.abs(v_x)
    return jnp.sum(fxb) - res, jnp.sum(fyb), jnp.sum(xw * fyb - yw * fxb)


def _substep(
    state: PlantState, delta: Array, torques: Array, mu: Array, params: VehicleParams, h: float
) -> PlantState:
    """One sub-step of length ``h``: wheels linearly implicit, then the body explicit.

    Wheels (per wheel, see the module docstring)::

        k_T = -dT_eff/domega >= 0 (brake hold below omega_eps),
        k   = R_w^2 max(dF_x/dkappa, 0) / v_den,
        domega_lin = h (T_eff - R_w F_x) / (I_w + h (k + k_T)),
        F_x+ = clip(F_x + k domega_lin / R_w, -mu F_z, mu F_z),
        domega = h (T_eff - R_w F_x+) / (I_w + h k_T).

    Without the clip ``domega = domega_lin`` (the two lines are the same linear
    equation); with it, ``domega`` solves ``I_w domega/h = T_eff - k_T domega -
    R_w clip(F_x + k domega/R_w)`` (the right side is monotone in domega, so the
    root is unique).  The body's explicit Euler step then uses ``F_x+`` and
    ``F_y+ = F_y + (dF_y/dkappa) R_w domega / v_den`` limited to
    ``|F_y+| <= sqrt((mu F_z)^2 - F_x+^2)``.
    """
    p = params
    f = _forces(state, delta, mu, p)
    # wheels: linearly implicit Euler on I_w omega' = T_eff - R_w F_x
    brake = torques < 0
    ratio = jnp.clip(state.omega / p.omega_eps, -1.0, 1.0)
    T_eff = jnp.where(brake, torques * ratio, torques)
    k_brake = jnp.where(brake & (jnp.abs(state.omega) < p.omega_eps), -torques / p.omega_eps, 0.0)
    k_tyre = p.R_w**2 * jnp.maximum(f.dFx, 0.0) / f.v_den  # d(R_w F_x)/d omega, clipped >= 0
    domega = h * (T_eff - p.R_w * f.Fx) / (p.I_w + h * (k_tyre + k_brake))
    D = mu * f.Fz
    Fx = jnp.clip(f.Fx + k_tyre / p.R_w * domega, -D, D)
    domega = h * (T_eff - p.R_w * Fx) / (p.I_w + h * k_brake)
    omega = state.omega + domega
    # lateral force at the updated slip, inside the friction circle |F| <= D
    dkappa = p.R_w * domega / f.v_den
    Fy_max = jnp.sqrt(jnp.maximum(D**2 - Fx**2, 1e-12))  # floor: finite derivative
    Fy = jnp.clip(f.Fy + f.dFy * dkappa, -Fy_max, Fy_max)
    fxb, fyb, mz = _body_loads(Fx, Fy, f, state.v_x, p)
    # body: explicit Euler
    ax = fxb / p.m
    ay = fyb / p.m
    vx_dot = ax + state.r * state.v_y
    vy_dot = ay - state.r * state.v_x
    r_dot = mz / p.I_z
    cps, sps = jnp.cos(state.psi), jnp.sin(state.psi)
    return PlantState(
        X=state.X + h * (state.v_x * cps - state.v_y * sps),
        Y=state.Y + h * (state.v_x * sps + state.v_y * cps),
        psi=state.psi + h * state.r,
        v_x=state.v_x + h * vx_dot,
        v_y=state.v_y + h * vy_dot,
        r=state.r + h * r_dot,
        omega=omega,
        a_x=ax,
        a_y=ay,
    )


def plant_step(
    state: PlantState,
    steer: Array,
    torques: Array,
    mu: Array,
    params: VehicleParams,
    dt: float = CONTROL_DT,
    n_sub: int = int(round(CONTROL_DT / PLANT_DT)),
) -> PlantState:
    """Advance the plant by one control period with inputs held (zero-order hold).

    Parameters
    ----------
    state : PlantState
    steer : Array, shape ()
        Front road-wheel angle delta_f (rad), both front wheels (parallel steer).
    torques : Array, shape (4,)
        Wheel torques [FL, FR, RL, RR] (Nm, positive drives).
    mu : Array, shape () or (4,)
        Road friction (per wheel if (4,)).
    params : VehicleParams
    dt : float
        Control period (s), static.
    n_sub : int
        Number of sub-steps (static); sub-step ``dt / n_sub``.

    Returns
    -------
    PlantState
        State after ``dt``; dtype follows ``state``.
    """
    dtype = state.v_x.dtype
    delta = wheel_angles(jnp.asarray(steer, dtype))
    torques = jnp.asarray(torques, dtype)
    mu = jnp.asarray(mu, dtype)
    h = dt / n_sub

    def body(s: PlantState, _: None) -> tuple[PlantState, None]:
        return _substep(s, delta, torques, mu, params, h), None

    out, _ = jax.lax.scan(body, state, None, length=n_sub)
    return out


def measure(
    state: PlantState, steer: Array, torques: Array, mu: Array, params: VehicleParams
) -> Measurement:
    """What the controller measures/estimates at the current state.

    ``torques`` (4,) is accepted for interface symmetry (force estimates here are
    the plant's true tyre forces at the current slips; they do not depend on the
    torques directly).  Accelerations are those of the last sub-step.
    """
    del torques
    dtype = state.v_x.dtype
    delta = wheel_angles(jnp.asarray(steer, dtype))
    f = _forces(state, delta, jnp.asarray(mu, dtype), params)
    return Measurement(
        v_x=state.v_x,
        v_y=state.v_y,
        yaw_rate=state.r,
        omega=state.omega,
        F_x=f.Fx,
        F_y=f.Fy,
        F_z=f.Fz,
        slip=f.kappa,
        slip_angle=f.alpha,
        a_x=state.a_x,
        a_y=state.a_y,
    )
