"""Example 1 of the paper, cruise control (eq.CC_system_1, eq.CC_objective, eq.CC_system).

X = [v_x, v_y, yaw rate]; agents DTR (drive torque, rear axle), RTV (rear
torque vectoring), FDB (front differential braking, two wheels); objectives
LST (longitudinal speed tracking, C = [1, 0, 0]: paper-notes item 1, printed
swapped) and YRT (yaw-rate tracking, C = [0, 0, 1]); FDB is shared
(fig_example_1). The steering STR is a disturbance. Deviations from the
printed model: :mod:`ampc_jax.vehicle.models`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
from jax import Array

from .actuators import FRONT_MIN_NM, REAR_MAX_NM
from .examples import VehicleExample, register_example
from .models import (
    ControlModel,
    ExampleSettings,
    fdb_columns,
    settings_dataclass,
    str_rows,
    yaw_rate_reference,
)
from .params import CONTROL_DT, Measurement, VehicleParams, wheel_angles

__all__ = [
    "CRUISE",
    "CruiseControl",
    "CruiseSettings",
    "cruise_bounds",
    "cruise_control_model",
    "cruise_wheel_torques",
]

DRIVER_PI = (1500.0, 200.0)
"""Nm/(m/s) and Nm/m: the driver's speed PI that plays DTR without the MPC."""


@settings_dataclass
class CruiseSettings(ExampleSettings):
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

    ``horizon``, ``dt`` and ``literal`` are static; the weights and bounds are
    array leaves of a compiled closed loop (:class:`~ampc_jax.vehicle.models.ExampleSettings`).
    """

    WEIGHTS = ("q_lst", "q_yrt")
    INPUT_WEIGHTS = ("r_dtr", "r_rtv", "r_fdb")
    BOUNDS = ("dtr_max", "rtv_max", "fdb_max")

    dt: float = CONTROL_DT  # s, the prediction model's step (the loop runs at CONTROL_DT)
    horizon: int = 2  # N_p, prediction steps (static)
    q_lst: float = 4.0  # (m/s)^-2, Q_LST
    q_yrt: float = 1.0e4  # (rad/s)^-2, Q_YRT
    r_dtr: float = 1.0 / 2000.0**2  # Nm^-2, R_(DTR)
    r_rtv: float = 1.0 / 500.0**2  # Nm^-2, R_(RTV)
    r_fdb: float = 1.0 / 1000.0**2  # Nm^-2, R_(FDB) (each of the two inputs)
    # bounds from the actuators (vehicle.actuators): |DTR/2| + |RTV| fills a rear
    # wheel's range, FDB a front wheel's (docs/vehicle.md, "Actuator bounds")
    dtr_max: float = REAR_MAX_NM  # Nm, |T_DTR| bound (1000 per rear wheel)
    rtv_max: float = REAR_MAX_NM / 2  # Nm, |T_RTV| bound
    fdb_max: float = -FRONT_MIN_NM  # Nm, FDB brakes in [-fdb_max, 0]
    literal: bool = False  # True: paper's literal W_d (paper-notes item 9)

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
        (paper-notes item 9), else the operating-point-exact affine form.

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
    fx, fy, fr = fdb_columns(delta, p)
    B_fdb = dt * jnp.stack([fx, fy, fr]).astype(dtype)
    sx, sy, sr = str_rows(delta, p)
    B_str = dt * jnp.stack([sx, sy, sr]).astype(dtype)
    w_paper = B_str @ meas.F_y.astype(dtype)
    # paper-notes item 9: A applied to the absolute state gives dt*(2 r v_y, -2 r v_x)
    # for the coupling terms; subtract one copy so the model is exact at X^(0).
    w_fix = dt * jnp.stack([-r * vy, r * vx, 0 * r]).astype(dtype)
    w = w_paper + jnp.where(s.literal, 0.0, 1.0) * w_fix

    x0 = jnp.stack([vx, vy, r]).astype(dtype)
    r_ref = yaw_rate_reference(vx, steer, mu, p).astype(dtype)
    ref = (jnp.reshape(jnp.asarray(v_ref, dtype), (1,)), r_ref[None])
    lb, ub = cruise_bounds(s, dtype)
    return ControlModel(A, (B_dtr, B_rtv, B_fdb), w, x0, ref, lb, ub)


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


@dataclass(frozen=True, eq=False)
class CruiseControl(VehicleExample):
    """The cruise-control example (see the module docstring)."""

    def model(self, meas, steer, driver_torque, v_ref, mu, vehicle, settings) -> ControlModel:
        return cruise_control_model(meas, steer, v_ref, mu, vehicle, settings)

    def wheel_torques(self, u: Array, driver_torque: Array) -> Array:
        return cruise_wheel_torques((u[0:1], u[1:2], u[2:4]))

    def driver_torque_seen(self, driver_torque: Array, mpc: bool) -> Array:
        # with the MPC its DTR agent tracks v_ref: no driver torque besides it
        return jnp.zeros_like(driver_torque) if mpc else driver_torque

    def no_mpc_scenario(self, scenario: Any) -> Any:
        dt = jnp.result_type(scenario.v0)
        kp, ki = DRIVER_PI
        return scenario._replace(speed_kp=jnp.asarray(kp, dt), speed_ki=jnp.asarray(ki, dt))

    def no_mpc_inputs(self, driver_torque: Array, settings: Any) -> Array:
        # no MPC: the driver's speed PI plays DTR, within DTR's bounds
        dt = jnp.result_type(driver_torque)
        dtr_max = jnp.asarray(settings.dtr_max, dt)
        u = jnp.zeros((self.n_inputs,), dt)
        return u.at[0].set(jnp.clip(driver_torque, -dtr_max, dtr_max))

    def baseline(self) -> dict[str, Any]:
        return {"disabled": ("YRT",), "formulation": None, "what": "LST alone"}


CRUISE = register_example(
    CruiseControl(
        name="cruise",
        title="cruise control (LST, YRT)",
        agents=("DTR", "RTV", "FDB"),
        agent_sizes=(1, 1, 2),
        input_names=("DTR", "RTV", "FDB_L", "FDB_R"),
        objectives=("LST", "YRT"),
        outputs={"LST": ((1.0, 0.0, 0.0),), "YRT": ((0.0, 0.0, 1.0),)},
        groups={"LST": ("DTR", "FDB"), "YRT": ("RTV", "FDB")},
        states=("v_x", "v_y", "yaw_rate"),
        settings_type=CruiseSettings,
        solver_defaults={
            # bench/bench_closed_loop.py sweep (docs/results.md, "Solver tuning"):
            # the fewest iterations on replayed closed-loop steps, warm started
            "warm_shift": 1,  # shift the warm start one step along the horizon
            "rho_scale": (1.0, 0.5),  # (LST, YRT) factors on eq.opt_ro's rho*
            "relaxation": 1.5,
            "integrated_rho_scale": 0.3,  # the integrated MPC's own best at alpha 1.5
            "shadow_rho_scale": 0.5,  # the shadow reaches 1e-8 Nm^2 in fewest iterations
            "shadow_relaxation": 1.8,
            "consensus_rho_scale": 1.0,  # Formulations 1 and 2 (docs/formulations.md)
            "anderson": 3,  # also for the integrated MPC it is timed against
            # the paper's iteration alone: the exact finish changes the reproduction's
            # iterations and e_sub (docs/results.md, "The exact finish in closed loop")
            "finish": "none",
        },
        no_mpc_label="no MPC (driver PI)",
    )
)
"""The cruise-control example."""
