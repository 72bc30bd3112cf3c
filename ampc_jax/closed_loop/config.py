"""What a closed-loop run is: :class:`SimConfig`, validated configuration as pure data.

A :class:`SimConfig` holds every setting of a run (example, formulation,
objectives, solver options, settings of the example, vehicle and driver). It
imports nothing of what is built from it; the builders sit beside what they
build:

* the static part -- :func:`~ampc_jax.closed_loop.controller.controller_for`,
  :func:`~ampc_jax.closed_loop.shadow.shadow_for` and
  :func:`~ampc_jax.closed_loop.loop.simulator_for`: a hashable
  :class:`~ampc_jax.closed_loop.loop.Simulator` of the controller and
  shadow's static options (iteration caps, Anderson memory, warm start,
  horizon), what a compiled closed loop is specialised on;
* :meth:`SimConfig.loop_params` -- :class:`LoopParams`, a pytree of arrays:
  the controller's and the shadow's :class:`~ampc_jax.admm.SolverParams`
  (rho scales, relaxation, tolerances) and the example's weights and bounds.
  These are arguments of the compiled loop: every rho point of a sweep runs
  the same program, and they can be vmapped and differentiated.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..admm.acceleration import anderson_memory
from ..admm.core import FormulationInfo
from ..admm.finish import FINISHES
from ..admm.learned_start import StartModel
from ..admm.params import SolverParams, solver_params
from ..formulations.registry import DEFAULT_FORMULATION, formulation_info, formulation_names
from ..validation import check_count, check_flag, check_positive, check_relaxation
from ..vehicle.examples import VehicleExample, example
from ..vehicle.manoeuvres import DriverParams, ScenarioSpec, scenario
from ..vehicle.models import ExampleSettings
from ..vehicle.params import CONTROL_DT, VehicleParams

__all__ = [
    "DURATION_MAX",
    "MU_MAX",
    "NO_MPC",
    "PAPER_SOLVER_OPTIONS",
    "SOLVER_OPTIONS",
    "ControllerParams",
    "LoopParams",
    "SimConfig",
    "baseline_config",
    "check_duration",
    "check_mu",
    "check_steps",
    "config_for",
    "loop_formulations",
    "with_settings",
]

NO_MPC = "none"
"""The closed loop's controller choice for no MPC (the example's driver alone)."""


def loop_formulations() -> tuple[str, ...]:
    """The controllers a closed loop may run: every registered formulation that
    serves closed loops (:func:`~ampc_jax.formulations.formulation_names`), then
    :data:`NO_MPC`."""
    return (*formulation_names(closed_loop=True), NO_MPC)


def __getattr__(name: str) -> Any:
    # FORMULATIONS: the former constant, now read from the registry when asked
    if name == "FORMULATIONS":
        return loop_formulations()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


DURATION_MAX = 3600.0
"""Longest simulated time (s) one run accepts: 72,000 control steps, whose log
(with each step's problem data) fills a few hundred MB."""

MU_MAX = 2.0
"""Largest road friction accepted (dry asphalt is about 1; the plant's tyre
model is not meant for more than racing slicks)."""

ACTUATOR_MODELS = ("ideal", "bridge")
"""What stands between the controller's torques and the plant (``SimConfig.actuators``)."""

SOLVER_OPTIONS = (
    "warm_shift",
    "rho_scale",
    "relaxation",
    "integrated_rho_scale",
    "shadow_rho_scale",
    "shadow_relaxation",
    "anderson",
    "finish",
)
"""The :class:`SimConfig` fields whose ``None`` means the example's tuned default."""

PAPER_SOLVER_OPTIONS: dict[str, Any] = {
    "warm_shift": 1,
    "rho_scale": 1.0,
    "relaxation": 1.0,
    "integrated_rho_scale": 1.0,
    "shadow_rho_scale": 1.0,
    "shadow_relaxation": 1.0,
    "anderson": 0,
    "finish": "none",
}
"""eq.opt_ro's rho* unscaled and no over-relaxation, acceleration or exact finish: the
paper's iteration (``config_for(..., **PAPER_SOLVER_OPTIONS)``); the warm start
(which the paper does not use) is the standard shifted one."""


def check_duration(duration: Any, name: str = "duration") -> float:
    """A simulated time in s: finite, at least one control period (``CONTROL_DT``)
    and at most ``DURATION_MAX``. Returns it as a float; ValueError naming ``name``."""
    if isinstance(duration, bool) or not isinstance(
        duration, (int, float, np.integer, np.floating)
    ):
        raise ValueError(f"{name}: expected a number of seconds, got {duration!r}")
    d = float(duration)
    # a few ulps of slack: 0.05 typed by hand is one control period
    if not (np.isfinite(d) and d >= CONTROL_DT * (1.0 - 1e-9)):
        raise ValueError(
            f"{name}: expected a finite time of at least one control period "
            f"({CONTROL_DT:g} s), got {duration!r}"
        )
    if d > DURATION_MAX:
        raise ValueError(
            f"{name}: expected at most {DURATION_MAX:g} s ({round(DURATION_MAX / CONTROL_DT)} "
            f"control steps) in one run, got {duration!r}; split longer runs"
        )
    return d


def check_mu(mu: Any, name: str = "mu") -> Any:
    """Road friction: finite and in (0, MU_MAX]; a scalar or an array (checked
    elementwise). Returns ``mu`` unchanged (traced values are not checked);
    ValueError naming ``name`` otherwise."""
    if isinstance(mu, jax.core.Tracer):
        return mu
    if isinstance(mu, bool):
        raise ValueError(f"{name}: expected a friction coefficient, got {mu!r}")
    try:
        a = np.asarray(mu, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a friction coefficient, got {mu!r}") from None
    if a.size == 0 or not np.all(np.isfinite(a) & (a > 0) & (a <= MU_MAX)):
        raise ValueError(f"{name}: expected a finite road friction in (0, {MU_MAX:g}], got {mu!r}")
    return mu


def check_steps(n_steps: Any, name: str = "n_steps") -> int:
    """A number of control steps: an integer >= 1 (ValueError naming ``name``)."""
    return check_count(n_steps, name)


class ControllerParams(NamedTuple):
    """The controller's numbers (a pytree): its solver's parameters and the
    example's settings (weights and bounds as leaves; horizon static)."""

    solver: SolverParams
    settings: ExampleSettings


class LoopParams(NamedTuple):
    """Every number a compiled closed loop takes as an argument (a pytree)."""

    controller: ControllerParams
    shadow: SolverParams


@dataclass(frozen=True)
class SimConfig:
    """Settings of one closed-loop run (validated on construction; hashable).

    Parameters
    ----------
    example : a registered vehicle example's name (``"cruise"`` or ``"stability"``).
    formulation : a registered formulation that serves closed loops
        (:func:`loop_formulations`: ``"local_explicit"``, the default,
        ``"fully_distributed"``, ``"virtual_center"`` (the paper's Formulations
        1 and 2), ``"integrated"`` (IntegratedADMM as the controller)) or
        ``"none"`` (no MPC: the example's driver alone).
    disabled : objectives left out (``--disable``); the agents are the union of
        the enabled objectives' groups, the others get zero input.
    settings : the example's settings (weights, bounds, horizon N_p; default
        the example's defaults).
    tol_primal, tol_dual : eps_r and eps_s of eq.Convergence for the controller
        (squared norms in Nm^2; the dual test is on the slack's change, the
        formulations' default). Default 1.0.
    max_iter : the controller's iteration cap (default 200).
    fixed_iterations : ``None`` (default): the controller solves each step to
        ``tol_primal`` / ``tol_dual`` (a ``while_loop``, capped at ``max_iter``).
        An integer K >= 1: exactly K iterations per step (the formulation's
        ``solve_fixed``, a ``lax.scan``), which makes the closed loop
        reverse-mode differentiable with respect to :class:`LoopParams` (weight
        tuning, :mod:`ampc_jax.tuning.weights`; run it with ``shadow=False``:
        the shadow still solves to tolerance). ``max_iter`` is then unused.
    warm_start : warm start from the previous step's state (default True;
        ``False``: cold start at every step, as the paper).
    warm_shift : 1 shifts the previous iterate one step along the horizon, 0
        holds it (controller, shadow and r_time replay alike). ``None``: the
        example's tuned default.
    rho_scale : factor(s) on eq.opt_ro's rho_j* of Local Explicit (a formulation
        whose ``info.rho_basis`` is ``"hessian"``, Formulations 1 and 2: on
        sqrt(lambda_min lambda_max) of H_j), a float or one per objective of
        the *example* in its order; with ``disabled`` objectives only the
        enabled entries are used. ``None``: the example's default for the
        formulation (``consensus_rho_scale`` for the ``"hessian"`` basis).
    relaxation : over-relaxation alpha in (0, 2) (1.0 is the paper's iteration),
        used by Local Explicit *and* the IntegratedADMM it is compared with, so
        that r_time compares like with like. ``None``: the example's default.
    integrated_rho_scale : factor on rho* of the IntegratedADMM (the controller of a
        one-rho formulation, ``"integrated"``, and r_time replay), tuned for it
        by the same sweep.
    anderson : Anderson memory 0..3 of Local Explicit and the IntegratedADMM it
        is compared with (0 is plain ADMM); the shadow stays plain.
    finish : the exact finish of the controller's solves and of the
        IntegratedADMM it is compared with (``"none"``: the paper's iteration
        alone; ``"active_set"``: :mod:`~ampc_jax.admm.finish`), for a
        formulation that has one (Local Explicit, ``"integrated"``; Formulations
        1 and 2 have none and ignore it). ``None``: the example's default
        (``"none"``: the closed-loop reproduction's figures are the paper's
        iteration's, ``docs/results.md``; the runtime's step runs
        ``"active_set"``, :mod:`ampc_jax.runtime.step`). The shadow always
        finishes (its optimum is the reference of e_sub).
    shadow : solve the integrated MPC in shadow, for e_sub (eq.suboptimality).
    shadow_tol_primal, shadow_tol_dual, shadow_max_iter : the shadow's
        tolerances (default 1e-8 Nm^2; floored at 1e-4 in float32) and cap (5000).
    shadow_rho_scale, shadow_relaxation : the shadow's rho* factor and
        over-relaxation; they change how fast it reaches its tolerance, not
        the optimum. ``None``: the example's default.
    learned_start : a trained :class:`~ampc_jax.admm.learned_start.StartModel`
        (``ampc tune --objective warm_start``; a tuned-parameters file's
        ``warm_start``) the controller starts each solve from: a ``"loop"``
        network corrects the previous step's iterate, a ``"step"`` network
        replaces it with its prediction from the step's data. ``None``
        (default): the previous step's iterate (``warm_start``). Only for a
        formulation that serves a learned start (``info.learned_start``: Local
        Explicit).
    actuators : ``"ideal"`` (default: the plant gets the controller's torques) or
        ``"bridge"`` (the CAN bridge's limiter between them: the wheels' ranges
        and rates of :data:`~ampc_jax.vehicle.actuators.ACTUATORS` on the 2 Nm
        grid, as a run over the bus applies them).
    vehicle, driver : vehicle and driver data (static: the plant, not tunables).

    Every field is checked on construction (ValueError naming the field). The
    examples' defaults and how they were chosen: ``docs/results.md``,
    "Solver tuning".
    """

    example: str = "cruise"
    formulation: str = DEFAULT_FORMULATION
    disabled: tuple[str, ...] = ()
    settings: Any = None
    tol_primal: float = 1.0
    tol_dual: float = 1.0
    max_iter: int = 200
    fixed_iterations: int | None = None
    warm_start: bool = True
    warm_shift: int | None = None
    rho_scale: float | tuple[float, ...] | None = None
    relaxation: float | None = None
    integrated_rho_scale: float | None = None
    anderson: int | None = None
    finish: str | None = None
    shadow: bool = True
    shadow_tol_primal: float = 1e-8
    shadow_tol_dual: float = 1e-8
    shadow_max_iter: int = 5000
    shadow_rho_scale: float | None = None
    shadow_relaxation: float | None = None
    learned_start: StartModel | None = None
    actuators: str = "ideal"
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    driver: DriverParams = field(default_factory=DriverParams)

    def __post_init__(self) -> None:
        ex = example(self.example)
        if self.formulation not in loop_formulations():
            raise ValueError(
                f"formulation: expected one of {loop_formulations()}, got {self.formulation!r}"
            )
        if self.settings is None:
            object.__setattr__(self, "settings", ex.settings_type())
        if not isinstance(self.settings, ex.settings_type):
            raise ValueError(
                f"settings: expected {ex.settings_type.__name__} for the {ex.name} example, "
                f"got {type(self.settings).__name__}"
            )
        self.settings.validate()
        for name in ("tol_primal", "tol_dual", "shadow_tol_primal", "shadow_tol_dual"):
            object.__setattr__(self, name, check_positive(getattr(self, name), name))
        for name in ("max_iter", "shadow_max_iter"):
            object.__setattr__(self, name, check_count(getattr(self, name), name))
        if self.fixed_iterations is not None:
            fixed = self.fixed_iterations
            if isinstance(fixed, bool) or not isinstance(fixed, (int, np.integer)) or fixed < 1:
                raise ValueError(
                    f"fixed_iterations: expected None (solve to tolerance) or an integer "
                    f"K >= 1 (iterations per step), got {fixed!r}"
                )
            object.__setattr__(self, "fixed_iterations", int(fixed))
        for name in ("warm_start", "shadow"):
            object.__setattr__(self, name, check_flag(getattr(self, name), name))
        object.__setattr__(self, "disabled", tuple(self.disabled))
        for name in self.disabled:
            if name not in ex.objectives:
                raise ValueError(
                    f"disable: {name!r} is not an objective of the {ex.name} example; "
                    f"expected one of {list(ex.objectives)}"
                )
        if self.actuators not in ACTUATOR_MODELS:
            raise ValueError(
                f"actuators: expected one of {ACTUATOR_MODELS}, got {self.actuators!r}"
            )
        if not self.enabled and self.mpc:
            raise ValueError("disable: every objective is disabled; use formulation 'none'")
        if self.learned_start is not None:
            if not isinstance(self.learned_start, StartModel):
                raise ValueError(
                    f"learned_start: expected a StartModel or None, got "
                    f"{type(self.learned_start).__name__}"
                )
            if not self.mpc or not formulation_info(self.formulation).learned_start:
                raise ValueError(
                    f"learned_start: formulation {self.formulation!r} serves no learned start "
                    f"(those that do: {list(formulation_names(learned_start=True))})"
                )
        self._resolve_solver_options(ex)

    def _resolve_solver_options(self, ex: VehicleExample) -> None:
        """Fill ``None`` solver options from the example's defaults and validate them all."""
        info = self.formulation_info
        if self.rho_scale is None and info is not None and info.rho_basis == "hessian":
            object.__setattr__(
                self, "rho_scale", ex.solver_defaults.get("consensus_rho_scale", 1.0)
            )
        for name in SOLVER_OPTIONS:
            if getattr(self, name) is None:  # one the example leaves out: the paper's
                default = ex.solver_defaults.get(name, PAPER_SOLVER_OPTIONS[name])
                object.__setattr__(self, name, default)
        ws = self.warm_shift
        if isinstance(ws, bool) or ws not in (0, 1):
            raise ValueError(f"warm_shift: expected 0 (hold) or 1 (shift), got {ws!r}")
        object.__setattr__(self, "warm_shift", int(ws))
        object.__setattr__(self, "anderson", anderson_memory(self.anderson))
        if self.finish not in FINISHES:
            raise ValueError(f"finish: expected one of {FINISHES}, got {self.finish!r}")
        n_obj = len(ex.objectives)
        scale = self.rho_scale
        try:
            arr = np.atleast_1d(np.asarray(scale, dtype=float))
        except (TypeError, ValueError):
            arr = np.array([np.nan])
        if arr.ndim != 1 or arr.size not in (1, n_obj):
            raise ValueError(
                f"rho_scale: expected a float or {n_obj} values (one per objective of the "
                f"{ex.name} example: {', '.join(ex.objectives)}), got {scale!r}"
            )
        if not np.all(np.isfinite(arr) & (arr > 0)):
            raise ValueError(f"rho_scale: expected positive finite values, got {scale!r}")
        # hashable and canonical: a float, or a tuple of floats (one per objective)
        object.__setattr__(
            self, "rho_scale", float(arr[0]) if arr.size == 1 else tuple(float(x) for x in arr)
        )
        for name in ("integrated_rho_scale", "shadow_rho_scale"):
            object.__setattr__(self, name, check_positive(getattr(self, name), name))
        for name in ("relaxation", "shadow_relaxation"):
            object.__setattr__(self, name, check_relaxation(getattr(self, name), name))

    # -- the controller ---------------------------------------------------------------
    @property
    def mpc(self) -> bool:
        """Whether an MPC runs (every formulation but :data:`NO_MPC`)."""
        return self.formulation != NO_MPC

    @property
    def formulation_info(self) -> FormulationInfo | None:
        """The controller's :class:`~ampc_jax.admm.core.FormulationInfo` (None without MPC)."""
        return formulation_info(self.formulation) if self.mpc else None

    # -- the example's structure -------------------------------------------------------
    @property
    def vehicle_example(self) -> VehicleExample:
        return example(self.example)

    @property
    def enabled(self) -> tuple[str, ...]:
        """Enabled objectives, in the example's order."""
        return tuple(o for o in self.vehicle_example.objectives if o not in self.disabled)

    @property
    def input_names(self) -> tuple[str, ...]:
        return self.vehicle_example.input_names

    @property
    def horizon(self) -> int:
        return int(self.settings.horizon)

    @property
    def enabled_rho_scale(self) -> float | tuple[float, ...]:
        """``rho_scale`` restricted to the enabled objectives (what Local Explicit gets)."""
        if isinstance(self.rho_scale, float):
            return self.rho_scale
        objs = self.vehicle_example.objectives
        keep = [self.rho_scale[objs.index(o)] for o in self.enabled]
        return keep[0] if len(keep) == 1 else tuple(keep)

    def solver_options(self) -> dict[str, Any]:
        """The solver options as resolved (for metrics.json)."""
        out: dict[str, Any] = {name: getattr(self, name) for name in SOLVER_OPTIONS}
        if isinstance(self.rho_scale, tuple):
            out["rho_scale"] = list(self.rho_scale)
        return out

    # -- the numbers a compiled loop takes ---------------------------------------------
    def loop_params(self, dtype: Any = None) -> LoopParams:
        """The run's numbers as a :class:`LoopParams` pytree of ``dtype`` arrays.

        The shadow's tolerances are floored at 1e-4 Nm^2 in float32 (its
        resolution at these torques)."""
        dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
        info = self.formulation_info
        if info is not None and info.rho == "one":  # the integrated problem's one rho
            rho, n_rho = self.integrated_rho_scale, 1
        else:  # no enabled objective: no MPC, no solver runs
            rho = self.enabled_rho_scale if self.enabled else 1.0
            n_rho = max(1, len(self.enabled))
        controller = solver_params(
            n_rho,
            rho=rho,
            relaxation=self.relaxation,
            tol_primal=self.tol_primal,
            tol_dual=self.tol_dual,
            dtype=dt,
        )
        floor = 1e-4 if dt == jnp.float32 else 0.0
        shadow = solver_params(
            1,
            rho=self.shadow_rho_scale,
            relaxation=self.shadow_relaxation,
            tol_primal=max(self.shadow_tol_primal, floor),
            tol_dual=max(self.shadow_tol_dual, floor),
            dtype=dt,
        )
        return LoopParams(ControllerParams(controller, self.settings.as_arrays(dt)), shadow)


def config_for(spec: ScenarioSpec | str, **overrides: Any) -> SimConfig:
    """The :class:`SimConfig` of a registered scenario: its example, then ``overrides``
    (``None`` values are left out: the defaults stay)."""
    spec = scenario(spec)
    kw: dict[str, Any] = {"example": spec.example}
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return SimConfig(**kw)


def baseline_config(config: SimConfig) -> SimConfig:
    """The run the paper compares ``config`` with (section "Experimental Studies").

    The example says which (:meth:`VehicleExample.baseline`): cruise control,
    LST alone with the same solver settings (what YRT adds, fig_CC_vehicle);
    stability control, the driver alone (fig_VSC_*_vehicle). ValueError
    (starting with ``compare:``) when ``config`` already is that run, or runs no
    MPC where the baseline needs one.
    """
    base = config.vehicle_example.baseline()
    what = base["what"]
    if base["formulation"] is None and not config.mpc:
        raise ValueError(
            f"compare: this run has no MPC ({config.vehicle_example.no_mpc_label}): no baseline"
        )
    changes: dict[str, Any] = {"disabled": base["disabled"]}
    if base["formulation"] is not None:
        changes["formulation"] = base["formulation"]
    out = replace(config, **changes)
    same = (
        out.enabled == config.enabled
        if base["formulation"] is None
        else config.formulation == base["formulation"]
    )
    if same:
        raise ValueError(
            f"compare: this run already is the {config.example} example's baseline ({what})"
        )
    return out


def with_settings(config: SimConfig, **fields: Any) -> SimConfig:
    """A copy of ``config`` with some fields of its settings replaced (e.g. ``q_yrt=...``)."""
    return replace(config, settings=config.settings.replace(**fields))
