"""The closed loop: the controller step, the shadow observer, the simulated run,
its metrics and its timing replay (section "Experimental Studies").

* :mod:`~.config` -- :class:`SimConfig`, configuration as pure data, and the
  :class:`LoopParams` a compiled loop takes;
* :mod:`~.controller` -- :class:`Controller` (``init`` / ``step``), the piece a
  runtime or a replay calls unchanged, and its builder :func:`controller_for`;
* :mod:`~.shadow` -- the integrated MPC in shadow (e_sub), :func:`shadow_for`;
* :mod:`~.log` -- :class:`SimLog`, what a run records;
* :mod:`~.loop` -- the scan over control periods, :func:`simulate`, and the
  static :class:`Simulator`'s builder :func:`simulator_for`;
* :mod:`~.metrics` -- :class:`SimResult` (e_sub, iterations, tracking, warnings);
* :mod:`~.timing` -- eq.t_ratio by replay;
* :mod:`~.compile` -- how a command's programs compile (options, several at once).
"""

from .compile import LOOP_COMPILER_OPTIONS, Compiler, loop_compiler_options
from .config import (
    DURATION_MAX,
    MU_MAX,
    NO_MPC,
    PAPER_SOLVER_OPTIONS,
    ControllerParams,
    LoopParams,
    SimConfig,
    baseline_config,
    check_duration,
    check_mu,
    config_for,
    loop_formulations,
    with_settings,
)
from .controller import Controller, ControllerState, DriverInputs, StepInfo, controller_for
from .log import SimLog
from .loop import (
    PreparedRun,
    Simulator,
    compile_run,
    finish,
    prepare,
    run_closed_loop,
    simulate,
    simulate_batch,
    simulator_for,
    time_run,
)
from .metrics import SimResult
from .shadow import IntegratedShadow, shadow_for
from .timing import ReplayPrograms, lower_replay, replay_programs, replay_timing


def __getattr__(name: str) -> object:
    # FORMULATIONS: the former constant, now read from the registry when asked
    if name == "FORMULATIONS":
        return loop_formulations()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "LOOP_COMPILER_OPTIONS",
    "DURATION_MAX",
    "MU_MAX",
    "NO_MPC",
    "PAPER_SOLVER_OPTIONS",
    "Compiler",
    "Controller",
    "ControllerParams",
    "ControllerState",
    "DriverInputs",
    "IntegratedShadow",
    "LoopParams",
    "PreparedRun",
    "ReplayPrograms",
    "SimConfig",
    "SimLog",
    "SimResult",
    "Simulator",
    "StepInfo",
    "baseline_config",
    "check_duration",
    "check_mu",
    "compile_run",
    "config_for",
    "controller_for",
    "finish",
    "loop_compiler_options",
    "loop_formulations",
    "lower_replay",
    "prepare",
    "replay_programs",
    "replay_timing",
    "run_closed_loop",
    "shadow_for",
    "simulate",
    "simulate_batch",
    "simulator_for",
    "time_run",
    "with_settings",
]
