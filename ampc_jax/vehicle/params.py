"""The vehicle: its data, wheel geometry and what the controllers measure of it.

Conventions
-----------
* Wheels are ordered ``[FL, FR, RL, RR]``; wheel torques are in Nm, positive
  drives the wheel forward, negative brakes.
* Body axes: x forward, y to the left, yaw rate positive counter-clockwise.
* Steering: both front wheels turn by the same road-wheel angle
  (:func:`wheel_angles`, parallel steer; the plant uses the same function).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array

__all__ = [
    "CONTROL_DT",
    "WHEELS",
    "Measurement",
    "VehicleParams",
    "wheel_angles",
    "wheel_positions",
]

CONTROL_DT = 0.05
"""Control period in s (the paper's controllers run at 20 Hz)."""

WHEELS = ("FL", "FR", "RL", "RR")
"""Wheel order of every per-wheel array."""


class VehicleParams(NamedTuple):
    """Vehicle and tyre data (table_param plus what the plant needs).

    The first eight fields are Table I of the paper.  ``I_w`` is read as a wheel
    inertia (paper-notes item 2).  The rest are choices for the stand-in plant
    (``ampc_jax.vehicle.plant``), typical of a large rear-wheel-drive sedan; see
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
    I_w: float = 1.6  # kg m^2, wheel spin inertia (paper-notes item 2)
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

    Produced by ``ampc_jax.vehicle.plant.measure``.  Scalars have shape () (or (batch,)
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
