"""The closed loop: the controller step, the shadow observer, the simulated run,
its metrics and its timing replay (section "Experimental Studies").

* :mod:`~.config` -- :class:`SimConfig` and its split into a static
  :class:`Simulator` and the :class:`LoopParams` a compiled loop takes;
* :mod:`~.controller` -- :class:`Controller` (``init`` / ``step``), the piece a
  runtime or a replay calls unchanged;
* :mod:`~.shadow` -- the integrated MPC in shadow (e_sub);
* :mod:`~.loop` -- the scan over control periods, :func:`simulate`;
* :mod:`~.metrics` -- :class:`SimResult` (e_sub, iterations, tracking, warnings);
* :mod:`~.timing` -- eq.t_ratio by replay.
"""

from .config import (
    DURATION_MAX,
    FORMULATIONS,
    MU_MAX,
    PAPER_SOLVER_OPTIONS,
    ControllerParams,
    LoopParams,
    SimConfig,
    baseline_config,
    check_duration,
    check_mu,
    config_for,
    with_settings,
)
from .controller import Controller, ControllerState, DriverInputs, StepInfo
from .loop import SimLog, Simulator, run_closed_loop, simulate, simulate_batch
from .metrics import SimResult
from .shadow import IntegratedShadow
from .timing import replay_timing

__all__ = [
    "DURATION_MAX",
    "FORMULATIONS",
    "MU_MAX",
    "PAPER_SOLVER_OPTIONS",
    "Controller",
    "ControllerParams",
    "ControllerState",
    "DriverInputs",
    "IntegratedShadow",
    "LoopParams",
    "SimConfig",
    "SimLog",
    "SimResult",
    "Simulator",
    "StepInfo",
    "baseline_config",
    "check_duration",
    "check_mu",
    "config_for",
    "replay_timing",
    "run_closed_loop",
    "simulate",
    "simulate_batch",
    "with_settings",
]
