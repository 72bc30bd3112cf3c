"""What a closed-loop run records: :class:`SimLog`, per-step arrays (pure data).

The loop (:mod:`~.loop`) writes it; the metrics (:mod:`~.metrics`) and the
timing replay (:mod:`~.timing`) read it, so none of them imports the others
for it.
"""

from __future__ import annotations

from typing import Any, NamedTuple

__all__ = ["SimLog"]


class SimLog(NamedTuple):
    """Per-step arrays of one closed-loop run (leading axis: control step k).

    Inputs are the example's agent inputs (``VehicleExample.input_names``, e.g.
    DTR, RTV, FDB_L, FDB_R) in Nm; disabled agents hold zero. Wheels [FL, FR, RL, RR].
    """

    t: Any  # (K,) s, time at the start of the step
    X: Any  # (K,) m, position at the start of the step
    Y: Any  # (K,)
    psi: Any  # (K,) rad
    v_x: Any  # (K,) m/s
    v_y: Any  # (K,)
    yaw_rate: Any  # (K,) rad/s
    omega: Any  # (K, 4) rad/s
    slip: Any  # (K, 4) longitudinal slip ratio
    steer: Any  # (K,) rad, driver's road-wheel angle
    driver_torque: Any  # (K,) Nm, T_DTR (cruise: 0, or the PI for "none")
    v_ref: Any  # (K,) m/s
    yaw_ref: Any  # (K,) rad/s, eq.CC_objective's friction-limited reference
    omega_ref: Any  # (K,) rad/s, rear wheel-speed reference (stability; else nan)
    path_y: Any  # (K,) m, the path's lateral position at X
    u: Any  # (K, n_inputs) applied agent inputs (Nm)
    u_ctrl: Any  # (K, n_inputs) the controller's U^(0) before the fallback guard
    u_shadow: Any  # (K, n_inputs) the shadow integrated MPC's U^(0) (nan: no shadow)
    e_sub: Any  # (K, n_inputs) |u_ctrl - u_shadow| (eq.suboptimality), nan for disabled agents
    torques: Any  # (K, 4) wheel torques sent to the plant (Nm)
    iterations: Any  # (K,) controller iterations
    status: Any  # (K,) controller status code (results.Status)
    shadow_iterations: Any  # (K,)
    shadow_status: Any  # (K,)
    fallback: Any  # (K,) bool, the guard replaced the controller's output
    data: Any  # ProblemData per step (for replay_timing); None for "none"
    warm: Any  # ADMMState the controller started from, per step; None for "none"
