"""Closed-loop vehicle simulation of section "Experimental Studies" under ``lax.scan``.

One control period (``CONTROL_DT`` = 50 ms, 20 Hz) of the closed loop is

1. the driver (:func:`~ampc_jax.manoeuvres.driver_step`): steering, driver
   torque T_DTR, target speed v_ref;
2. the plant measurement (:func:`~ampc_jax.plant.measure`);
3. re-linearisation: the example's control model (eq.CC_system or
   eq.VSC_system, :mod:`ampc_jax.vehicle`) at the measurement, restricted to
   the *enabled* objectives and their agents, and :func:`make_data`;
4. the controller: Local Explicit (Formulation 3, eq.integMPC_F3 to
   eq.F3_multiplier; warm started from the previous step's shifted iterate, or
   cold started as in the paper), the JAX-native integrated MPC
   (:class:`~ampc_jax.integrated.IntegratedADMM`), or none (zero agent inputs:
   the driver alone);
5. in shadow, the integrated MPC (eq.integMPC) solved at a tight tolerance, so
   the suboptimality of eq.suboptimality,
   ``e_sub = |U_distributed^(0) - U_integrated^(0)|`` (Nm, per agent input), is
   logged at every step with the iteration counts and statuses;
6. the fallback guard: a solve whose status is not ``solved`` or
   ``max_iter_reached``, or whose U^(0) is not finite, is not applied; the
   previous command clipped to the current bounds is held instead (zero where
   that is not finite) and the warm start is reset. The plant therefore never
   receives NaN or out-of-bound torques;
7. the plant (:func:`~ampc_jax.plant.plant_step`, 50 sub-steps of 1 ms).

The whole run is one compiled ``lax.scan``; per-step data of the controller
(the :class:`~ampc_jax.topology.ProblemData` and the warm start it received)
are logged so that the time ratio of eq.t_ratio, which cannot be timed inside
a scan, is measured afterwards by :func:`replay_timing`.

Batching follows Brax: :func:`run_closed_loop` handles one scenario;
:func:`simulate_batch` vmaps it over stacked scenarios (and friction values).
On 2-core CPUs batched programs can deadlock intermittently
(``docs/results.md``); pin the process to one core when batching.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .formulations import LocalExplicit, _anderson_memory, cold_state, shift_state
from .integrated import IntegratedADMM, merged_topology
from .manoeuvres import (
    SCENARIOS,
    DriverParams,
    Scenario,
    ScenarioSpec,
    driver_step,
    initial_driver_state,
    initial_plant_state,
    path_y,
)
from .plant import measure, plant_step
from .topology import ProblemData, Topology, make_data
from .vehicle import (
    CONTROL_DT,
    CRUISE_AGENTS,
    CRUISE_C,
    CRUISE_GROUPS,
    CRUISE_OBJECTIVES,
    STABILITY_AGENTS,
    STABILITY_C,
    STABILITY_GROUPS,
    STABILITY_OBJECTIVES,
    CruiseSettings,
    Measurement,
    StabilitySettings,
    VehicleParams,
    cruise_control_model,
    cruise_wheel_torques,
    stability_control_model,
    stability_wheel_torques,
    wheel_speed_reference,
    yaw_rate_reference,
)

__all__ = [
    "CONTROLLER_DEFAULTS",
    "FORMULATIONS",
    "PAPER_SOLVER_OPTIONS",
    "SCENARIO_SETTINGS",
    "SimConfig",
    "SimLog",
    "SimResult",
    "Simulator",
    "DURATION_MAX",
    "MU_MAX",
    "baseline_config",
    "build_topology",
    "check_duration",
    "check_mu",
    "config_for",
    "controller_solver",
    "integrated_solver",
    "local_explicit_solver",
    "reduced_data",
    "replay_timing",
    "run_closed_loop",
    "simulate",
    "simulate_batch",
    "with_settings",
    "add_cli_commands",
]

FORMULATIONS = ("local_explicit", "integrated", "none")
"""Controllers of the closed loop: Local Explicit, IntegratedADMM, or the driver alone."""

_OK_STATUS = (0, 1)  # solved, max_iter_reached: applied; anything else falls back

# Cruise "none": no MPC, so a speed PI of the driver plays DTR (as in tests/test_manoeuvres.py).
_CRUISE_DRIVER_PI = (1500.0, 200.0)

V_X_BACKWARDS = -0.1
"""m/s: a run whose v_x falls below this went backwards (:meth:`SimResult.warnings`);
the margin keeps a car braked to a stop, which may creep by a few mm/s, out."""

DURATION_MAX = 3600.0
"""Longest simulated time (s) :func:`simulate` accepts in one run: 72,000
control steps, whose log (with each step's problem data) fills a few hundred MB."""

MU_MAX = 2.0
"""Largest road friction :func:`simulate` accepts (dry asphalt is about 1; the
tyre model of :mod:`ampc_jax.plant` is not meant for more than racing slicks)."""


def check_duration(duration: Any, name: str = "duration") -> float:
    """A simulated time in s: finite, at least one control period (``CONTROL_DT``)
    and at most ``DURATION_MAX``.

    Returns it as a float; ValueError naming ``name`` otherwise.
    """
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
    """Road friction: finite and in (0, MU_MAX]; a scalar or an array (checked elementwise).

    Returns ``mu`` unchanged (traced values are not checked); ValueError naming
    ``name`` otherwise.
    """
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


def _positive_float(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
    return float(v)


def _positive_int(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {v!r}")
    return int(v)


# --------------------------------------------------------------------------- configuration
_SOLVER_OPTIONS = (
    "warm_shift",
    "rho_scale",
    "relaxation",
    "integrated_rho_scale",
    "shadow_rho_scale",
    "shadow_relaxation",
    "anderson",
)

CONTROLLER_DEFAULTS: dict[str, dict[str, Any]] = {
    # Chosen by ``bench/bench_closed_loop.py sweep`` (docs/results.md, "Solver tuning"):
    # replay of logged closed-loop steps at the controller's tolerance, warm started.
    "cruise": {
        "warm_shift": 1,  # shift the warm start one step (hold: p95 17.2 -> 18.2)
        "rho_scale": (1.0, 0.5),  # (LST, YRT): iterations p95 31 -> 17 with alpha 1.5
        "relaxation": 1.5,
        "integrated_rho_scale": 0.3,  # the integrated MPC's own best at alpha 1.5 (p95 78 -> 25)
        "shadow_rho_scale": 0.5,  # shadow to 1e-8 Nm^2: p95 269 -> 116 iterations
        "shadow_relaxation": 1.8,
        # Anderson memory 3 (also for the integrated MPC it is timed against):
        # iterations p95 17.2 -> 14, max 79 -> 30 when added (2026-11-30); 17 -> 14 and
        # 78 -> 22 on the plant of session 12 (docs/results.md)
        "anderson": 3,
    },
    "stability": {
        "warm_shift": 0,  # hold the previous iterate: p50 10 -> 4, p95 16 -> 15 (launch/brake)
        # (VSC, WSC) and alpha re-chosen in session 15 at the new actuator bounds, with
        # Anderson acceleration, by closed-loop runs and the iteration *maximum*
        # (docs/results.md, "Solver tuning"): max 24 / 25 -> 12 / 19 (launch/brake / DLC);
        # session 12's (1.5, 1.0) at alpha 1.6 came from the p95 rule on the paper's solver
        "rho_scale": (0.3, 3.0),
        "relaxation": 1.5,
        "integrated_rho_scale": 1.2,  # its own best at alpha 1.5 by the same rule (as at 1.6)
        "shadow_rho_scale": 1.0,  # shadow: p95 143 -> 84 iterations
        "shadow_relaxation": 1.8,
        # Anderson memory 3 (launch/brake / DLC, 2026-11-30, docs/results.md):
        # iterations p95 15 / 23 -> 13 / 22, max 21 / 36 -> 21 / 24, r_time
        # 1.07 / 1.08 -> 1.06 / 1.07. (It was off until then: Local Explicit's
        # step with it ran partly on XLA:CPU's thread pool, r_time 1.25 / 1.27;
        # since the warm state's counters are reset in ``init`` it does not.)
        "anderson": 3,
    },
}
"""Per-example defaults of the solver options of :class:`SimConfig` (see its docstring)."""

PAPER_SOLVER_OPTIONS: dict[str, Any] = {
    "warm_shift": 1,
    "rho_scale": 1.0,
    "relaxation": 1.0,
    "integrated_rho_scale": 1.0,
    "shadow_rho_scale": 1.0,
    "shadow_relaxation": 1.0,
    "anderson": 0,
}
"""eq.opt_ro's rho* unscaled and no over-relaxation: the paper's iteration
(``config_for(..., **PAPER_SOLVER_OPTIONS)``); the warm start (which the paper
does not use) is the standard shifted one."""


@dataclass(frozen=True)
class SimConfig:
    """Static settings of one closed-loop run (hashable: a ``jit`` static argument).

    Parameters
    ----------
    example : ``"cruise"`` or ``"stability"``.
    formulation : ``"local_explicit"``, ``"integrated"`` (IntegratedADMM as the
        controller) or ``"none"`` (zero agent inputs; for cruise a driver speed PI
        stands in for DTR).
    disabled : objectives left out of the topology (``--disable``); the agents are
        the union of the enabled objectives' groups; the others get zero input.
    settings : the example's :class:`CruiseSettings` / :class:`StabilitySettings`
        (weights, horizon N_p).
    tol_primal, tol_dual : eps_r and eps_s of eq.Convergence (squared norms) for
        the controller. Both residuals are in Nm here: the primal residual is
        the constraint rows' violation, the dual one the slack's change
        ``||Z^q - Z^(q-1)||^2`` (the core's default ``dual_residual="slack"``;
        the printed ``rho_j (Z^q - Z^(q-1))`` scales with rho_j ~ 1e-5).
        Defaults from ``docs/results.md``.
    max_iter : iteration cap of the controller.
    warm_start : warm start Local Explicit from the previous step's state
        (``False``: cold start at every step, as the paper).
    warm_shift : how the warm start is built from the previous step's iterate
        (:func:`~ampc_jax.formulations.shift_state`): 1 shifts it one step
        along the horizon, 0 holds it. Used for the controller, the shadow and
        the r_time replay alike. ``None``: the example's default.
    rho_scale : factor(s) on eq.opt_ro's rho_j* of Local Explicit, a float or
        one per objective of the *example* in its order (LST, YRT or VSC, WSC);
        with ``disabled`` objectives only the enabled entries are used.
        ``None``: the example's default in :data:`CONTROLLER_DEFAULTS`.
    relaxation : ADMM over-relaxation alpha in (0, 2) (1.0 is the paper's
        iteration), used by Local Explicit *and* by the IntegratedADMM it is
        compared with (controller ``--formulation integrated``, r_time replay),
        so that r_time compares like with like. ``None``: the example's default.
    integrated_rho_scale : factor on eq.opt_ro's rho* of the IntegratedADMM
        used as the controller and in the r_time replay (one objective, so one
        float), tuned for it by the same sweep as ``rho_scale``.
        ``None``: the example's default.
    anderson : Anderson acceleration memory (0 to 3; 0 is plain ADMM) of
        Local Explicit *and* of the IntegratedADMM it is compared with
        (``LocalExplicit.anderson``), like ``relaxation``. The shadow stays
        plain. ``None``: the example's default.
    shadow : solve the integrated MPC in shadow (e_sub of eq.suboptimality).
    shadow_tol_primal, shadow_tol_dual, shadow_max_iter : tolerances and cap of
        the shadow IntegratedADMM (warm started from its own previous step);
        tight enough for about 1e-3 Nm against Clarabel.
    shadow_rho_scale, shadow_relaxation : rho* factor and over-relaxation of
        the shadow. They only change how fast the shadow reaches its tight
        tolerance, not the optimum it reports. ``None``: the example's default.
    params, driver : vehicle and driver data.

    Every field is checked on construction (ValueError naming the field):
    tolerances positive and finite, iteration caps integers >= 1, the
    settings by their ``validate()`` (horizon >= 1, dt > 0, weights Q >= 0
    and R > 0, bounds >= 0, all finite). ``settings.dt`` is the prediction
    model's step; the closed loop itself always runs at ``CONTROL_DT``.

    The example defaults (``CONTROLLER_DEFAULTS``) and how they were chosen
    (an offline sweep over rho_scale x relaxation on logged closed-loop steps,
    ``bench/bench_closed_loop.py sweep``) are in ``docs/results.md``, "Solver
    tuning".
    """

    example: str = "cruise"
    formulation: str = "local_explicit"
    disabled: tuple[str, ...] = ()
    settings: Any = None
    tol_primal: float = 1.0
    tol_dual: float = 1.0
    max_iter: int = 200
    warm_start: bool = True
    warm_shift: int | None = None
    rho_scale: float | tuple[float, ...] | None = None
    relaxation: float | None = None
    integrated_rho_scale: float | None = None
    anderson: int | None = None
    shadow: bool = True
    shadow_tol_primal: float = 1e-8
    shadow_tol_dual: float = 1e-8
    shadow_max_iter: int = 5000
    shadow_rho_scale: float | None = None
    shadow_relaxation: float | None = None
    params: VehicleParams = field(default_factory=VehicleParams)
    driver: DriverParams = field(default_factory=DriverParams)

    def __post_init__(self) -> None:
        if self.example not in ("cruise", "stability"):
            raise ValueError(f"example: expected 'cruise' or 'stability', got {self.example!r}")
        if self.formulation not in FORMULATIONS:
            raise ValueError(
                f"formulation: expected one of {FORMULATIONS}, got {self.formulation!r}"
            )
        kind = CruiseSettings if self.example == "cruise" else StabilitySettings
        if self.settings is None:
            object.__setattr__(self, "settings", kind())
        if not isinstance(self.settings, kind):
            raise ValueError(
                f"settings: expected {kind.__name__} for the {self.example} example, "
                f"got {type(self.settings).__name__}"
            )
        self.settings.validate()
        for name in ("tol_primal", "tol_dual", "shadow_tol_primal", "shadow_tol_dual"):
            object.__setattr__(self, name, _positive_float(name, getattr(self, name)))
        for name in ("max_iter", "shadow_max_iter"):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name)))
        for name in ("warm_start", "shadow"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name}: expected True or False, got {getattr(self, name)!r}")
            object.__setattr__(self, name, bool(getattr(self, name)))
        objectives = self.objectives_all
        for name in self.disabled:
            if name not in objectives:
                raise ValueError(
                    f"--disable {name}: unknown objective for the {self.example} example; "
                    f"expected one of {list(objectives)}"
                )
        if not self.enabled and self.formulation != "none":
            raise ValueError("every objective is disabled; use --formulation none instead")
        self._resolve_solver_options()

    def _resolve_solver_options(self) -> None:
        """Fill ``None`` solver options from CONTROLLER_DEFAULTS and validate them all."""
        defaults = CONTROLLER_DEFAULTS[self.example]
        for name in _SOLVER_OPTIONS:
            if getattr(self, name) is None:
                object.__setattr__(self, name, defaults[name])
        ws = self.warm_shift
        if isinstance(ws, bool) or ws not in (0, 1):
            raise ValueError(f"warm_shift: expected 0 (hold) or 1 (shift), got {ws!r}")
        object.__setattr__(self, "warm_shift", int(ws))
        object.__setattr__(self, "anderson", _anderson_memory(self.anderson))
        n_obj = len(self.objectives_all)
        scale = self.rho_scale
        try:
            arr = np.atleast_1d(np.asarray(scale, dtype=float))
        except (TypeError, ValueError):
            arr = np.array([np.nan])
        if arr.ndim != 1 or arr.size not in (1, n_obj):
            raise ValueError(
                f"rho_scale: expected a float or {n_obj} values (one per objective of the "
                f"{self.example} example: {', '.join(self.objectives_all)}), got {scale!r}"
            )
        if not np.all(np.isfinite(arr) & (arr > 0)):
            raise ValueError(f"rho_scale: expected positive finite values, got {scale!r}")
        # hashable and canonical: a float, or a tuple of floats (one per objective)
        object.__setattr__(
            self, "rho_scale", float(arr[0]) if arr.size == 1 else tuple(float(x) for x in arr)
        )
        for name in ("integrated_rho_scale", "shadow_rho_scale"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise ValueError(f"{name}: expected a positive finite float, got {v!r}")
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite float, got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("relaxation", "shadow_relaxation"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise ValueError(f"{name}: expected a float in (0, 2), got {v!r}")
            if not 0.0 < float(v) < 2.0:
                raise ValueError(f"{name}: expected a value in (0, 2), got {v!r}")
            object.__setattr__(self, name, float(v))

    # -- the example's static structure --------------------------------------------
    @property
    def agents_all(self) -> tuple[str, ...]:
        return CRUISE_AGENTS if self.example == "cruise" else STABILITY_AGENTS

    @property
    def objectives_all(self) -> tuple[str, ...]:
        return CRUISE_OBJECTIVES if self.example == "cruise" else STABILITY_OBJECTIVES

    @property
    def enabled(self) -> tuple[str, ...]:
        """Enabled objectives, in the example's order."""
        return tuple(o for o in self.objectives_all if o not in self.disabled)

    @property
    def agent_sizes_all(self) -> tuple[int, ...]:
        return (1, 1, 2)

    @property
    def input_names(self) -> tuple[str, ...]:
        """Names of the example's four agent inputs (columns of the logged inputs)."""
        a = self.agents_all
        return (a[0], a[1], f"{a[2]}_L", f"{a[2]}_R")

    @property
    def horizon(self) -> int:
        return int(self.settings.horizon)

    @property
    def enabled_rho_scale(self) -> float | tuple[float, ...]:
        """``rho_scale`` restricted to the enabled objectives (what Local Explicit gets)."""
        if isinstance(self.rho_scale, float):
            return self.rho_scale
        keep = [self.rho_scale[self.objectives_all.index(o)] for o in self.enabled]
        return keep[0] if len(keep) == 1 else tuple(keep)

    def solver_options(self) -> dict[str, Any]:
        """The solver options as resolved (for metrics.json)."""
        out: dict[str, Any] = {name: getattr(self, name) for name in _SOLVER_OPTIONS}
        out["rho_scale"] = (
            list(self.rho_scale) if isinstance(self.rho_scale, tuple) else self.rho_scale
        )
        return out


SCENARIO_SETTINGS: dict[str, dict[str, Any]] = {
    "cruise_lane_change": {},
    "stability_launch_brake": {},
    "stability_dlc": {},
}
"""Overrides of :class:`SimConfig` fields per scenario (none at present).

The weights and horizons the scenarios use are the defaults of
:class:`~ampc_jax.vehicle.CruiseSettings` (N_p = 2, Q_YRT = 1e4) and
:class:`~ampc_jax.vehicle.StabilitySettings` (N_p = 3), the single source of
truth (``docs/results.md``, "Settings"); the solver options are the example's
:data:`CONTROLLER_DEFAULTS`. The ``--disable`` comparisons (LST alone, driver
alone) use the same settings."""


def config_for(spec: ScenarioSpec | str, **overrides: Any) -> SimConfig:
    """The :class:`SimConfig` of a registered scenario: its example, the settings table, overrides."""
    spec = SCENARIOS[spec] if isinstance(spec, str) else spec
    kw: dict[str, Any] = {"example": spec.example, **SCENARIO_SETTINGS.get(spec.name, {})}
    kw.update({k: v for k, v in overrides.items() if v is not None})
    return SimConfig(**kw)


def baseline_config(config: SimConfig) -> SimConfig:
    """The run the paper compares ``config`` with (section "Experimental Studies").

    Cruise control: LST alone (YRT disabled), same solver settings, so the
    comparison shows what YRT adds (fig_CC_vehicle). Stability control: the
    driver alone, no MPC (fig_VSC_straight_vehicle, fig_VSC_DLC_vehicle).
    ValueError if ``config`` already is that run, or runs no MPC (nothing to
    compare).
    """
    if config.example == "cruise":
        if config.formulation == "none":
            raise ValueError("compare: this run has no MPC (the driver's speed PI): no baseline")
        base, what = replace(config, disabled=("YRT",)), "LST alone"
        same = base.enabled == config.enabled
    else:
        base, what = replace(config, formulation="none", disabled=()), "the driver alone"
        same = config.formulation == "none"
    if same:
        raise ValueError(
            f"compare: this run already is the {config.example} example's baseline ({what})"
        )
    return base


def build_topology(config: SimConfig) -> tuple[Topology, tuple[int, ...], tuple[int, ...]]:
    """Topology of the enabled objectives (``--disable``).

    Returns
    -------
    topology : agents = union of the enabled objectives' groups S_j (in the
        example's agent order), objectives = the enabled ones.
    agent_idx : indices of the topology's agents in the example's agent list.
    objective_idx : indices of the enabled objectives in the example's list.
    """
    agents = config.agents_all
    groups_all = CRUISE_GROUPS if config.example == "cruise" else STABILITY_GROUPS
    c_all = CRUISE_C if config.example == "cruise" else STABILITY_C
    enabled = config.enabled
    used = sorted({agents.index(a) for o in enabled for a in groups_all[o]})
    agent_idx = tuple(used)
    objective_idx = tuple(config.objectives_all.index(o) for o in enabled)
    groups = [tuple(agent_idx.index(agents.index(a)) for a in groups_all[o]) for o in enabled]
    topo = Topology.build(
        n_x=len(next(iter(c_all.values()))[0]),
        horizon=config.horizon,
        agent_names=[agents[i] for i in agent_idx],
        agent_sizes=[config.agent_sizes_all[i] for i in agent_idx],
        objective_names=list(enabled),
        output_sizes=[len(c_all[o]) for o in enabled],
        groups=groups,
    )
    return topo, agent_idx, objective_idx


def _input_columns(config: SimConfig, agent_idx: tuple[int, ...]) -> np.ndarray:
    """Columns of the example's 4 inputs held by the topology's agents (static)."""
    offs = np.cumsum([0, *config.agent_sizes_all])
    return np.concatenate([np.arange(offs[i], offs[i + 1]) for i in agent_idx]).astype(int)


def reduced_data(
    config: SimConfig,
    topology: Topology,
    agent_idx: tuple[int, ...],
    objective_idx: tuple[int, ...],
    model: Any,
) -> ProblemData:
    """:class:`ProblemData` (eq.eq_linear, eq.integMPC) of the enabled objectives (jittable).

    ``model`` is the example's :class:`~ampc_jax.vehicle.ControlModel`; the
    weights Q_j, R_(i) come from ``config.settings``.
    """
    c_all = CRUISE_C if config.example == "cruise" else STABILITY_C
    dtype = model.x0.dtype
    Qs, Rs = config.settings.Q(), config.settings.R()
    names = config.objectives_all
    return make_data(
        topology,
        A=model.A,
        B=tuple(model.B[i] for i in agent_idx),
        x0=model.x0,
        C=tuple(jnp.asarray(c_all[names[j]], dtype) for j in objective_idx),
        Q=tuple(Qs[j] for j in objective_idx),
        ref=tuple(model.ref[j] for j in objective_idx),
        R=tuple(Rs[i] for i in agent_idx),
        lb=tuple(model.lb[i] for i in agent_idx),
        ub=tuple(model.ub[i] for i in agent_idx),
        w=model.w,
        dtype=dtype,
    )


def local_explicit_solver(
    config: SimConfig, topology: Topology, max_iter: int | None = None
) -> LocalExplicit:
    """Local Explicit with the controller's tolerances, rho_scale and relaxation."""
    return LocalExplicit(
        topology,
        max_iter=config.max_iter if max_iter is None else max_iter,
        tol_primal=config.tol_primal,
        tol_dual=config.tol_dual,
        rho_scale=config.enabled_rho_scale,
        relaxation=config.relaxation,
        anderson=config.anderson,
    )


def integrated_solver(
    config: SimConfig, topology: Topology, max_iter: int | None = None
) -> IntegratedADMM:
    """IntegratedADMM with the controller's tolerances and relaxation, its own rho scale."""
    return IntegratedADMM(
        topology,
        max_iter=config.max_iter if max_iter is None else max_iter,
        tol_primal=config.tol_primal,
        tol_dual=config.tol_dual,
        rho_scale=config.integrated_rho_scale,
        relaxation=config.relaxation,
        anderson=config.anderson,
    )


def controller_solver(config: SimConfig, topology: Topology) -> LocalExplicit | IntegratedADMM:
    """The closed loop's controller for ``config.formulation`` (not ``"none"``)."""
    if config.formulation == "integrated":
        return integrated_solver(config, topology)
    return local_explicit_solver(config, topology)


# --------------------------------------------------------------------------- the log
class SimLog(NamedTuple):
    """Per-step arrays of one closed-loop run (leading axis: control step k).

    Inputs are the example's four agent inputs (``SimConfig.input_names``, e.g.
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
    u: Any  # (K, 4) applied agent inputs (Nm)
    u_ctrl: Any  # (K, 4) the controller's U^(0) before the fallback guard
    u_shadow: Any  # (K, 4) the shadow integrated MPC's U^(0) (nan: no shadow)
    e_sub: Any  # (K, 4) |u_ctrl - u_shadow| (eq.suboptimality), nan for disabled agents
    torques: Any  # (K, 4) wheel torques sent to the plant (Nm)
    iterations: Any  # (K,) controller iterations
    status: Any  # (K,) controller status code (results.STATUS)
    shadow_iterations: Any  # (K,)
    shadow_status: Any  # (K,)
    fallback: Any  # (K,) bool, the guard replaced the controller's output
    data: Any  # ProblemData per step (for replay_timing); None for "none"
    warm: Any  # ADMMState the controller started from, per step; None for "none"


class _Carry(NamedTuple):
    plant: Any
    driver: Any
    warm: Any
    shadow_warm: Any
    u_prev: Any  # (n_u_red,) last applied command (reduced topology)


@dataclass(frozen=True)
class Simulator:
    """The closed loop of one :class:`SimConfig` (static, hashable; jit over :meth:`run`)."""

    config: SimConfig

    # -- static pieces ---------------------------------------------------------------------
    @property
    def structure(self) -> tuple[Topology, tuple[int, ...], tuple[int, ...]]:
        return build_topology(self.config)

    @property
    def topology(self) -> Topology:
        return self.structure[0]

    def controller(self) -> LocalExplicit | IntegratedADMM:
        """The controller: Local Explicit or IntegratedADMM with the config's solver options."""
        return controller_solver(self.config, self.topology)

    def shadow_solver(self, dtype: Any = None) -> IntegratedADMM:
        """The shadow integrated MPC; in float32 its tolerances are floored at 1e-4 Nm^2."""
        c = self.config
        floor = 1e-4 if dtype is not None and jnp.dtype(dtype) == jnp.float32 else 0.0
        return IntegratedADMM(
            self.topology,
            max_iter=c.shadow_max_iter,
            tol_primal=max(c.shadow_tol_primal, floor),
            tol_dual=max(c.shadow_tol_dual, floor),
            rho_scale=c.shadow_rho_scale,
            relaxation=c.shadow_relaxation,
        )

    def _controller_topology(self) -> Topology:
        T = self.topology
        return merged_topology(T) if self.config.formulation == "integrated" else T

    # -- one control step --------------------------------------------------------------------
    def model(self, meas: Measurement, steer: Any, driver_torque: Any, v_ref: Any, mu: Any) -> Any:
        """The example's re-linearised control model (eq.CC_system / eq.VSC_system)."""
        c = self.config
        if c.example == "cruise":
            return cruise_control_model(meas, steer, v_ref, mu, c.params, c.settings)
        return stability_control_model(meas, steer, driver_torque, mu, c.params, c.settings)

    def wheel_torques(self, u_full: Any, driver_torque: Any) -> Any:
        """Wheel torques [FL, FR, RL, RR] from the four agent inputs."""
        parts = (u_full[0:1], u_full[1:2], u_full[2:4])
        if self.config.example == "cruise":
            return cruise_wheel_torques(parts)
        return stability_wheel_torques(parts, driver_torque)

    def run(self, scenario: Scenario, n_steps: int, fault: Any = None) -> SimLog:
        """Run the closed loop for ``n_steps`` control periods (pure; jit with n_steps static).

        Parameters
        ----------
        scenario : the manoeuvre's arrays (its dtype sets the simulation's dtype).
        n_steps : number of control steps (static).
        fault : optional (n_steps,) bool; where True the controller receives a
            NaN measurement (to exercise the fallback guard).
        """
        c = self.config
        T, agent_idx, objective_idx = self.structure
        cols = _input_columns(c, agent_idx)
        dtype = jnp.result_type(scenario.v0)
        p, dp = c.params, c.driver
        if c.example == "cruise" and c.formulation == "none":
            kp, ki = _CRUISE_DRIVER_PI
            scenario = scenario._replace(
                speed_kp=jnp.asarray(kp, dtype), speed_ki=jnp.asarray(ki, dtype)
            )
        mu = scenario.mu
        n_u = 4
        use_ctrl = c.formulation != "none"
        ctrl = self.controller() if use_ctrl else None
        shadow = self.shadow_solver(dtype) if (use_ctrl and c.shadow) else None
        ctrl_cold = cold_state(self._controller_topology(), dtype) if use_ctrl else None
        shadow_cold = cold_state(merged_topology(T), dtype) if shadow is not None else None
        fault = jnp.zeros((n_steps,), bool) if fault is None else jnp.asarray(fault, bool)
        nan = jnp.asarray(jnp.nan, dtype)

        def step(carry: _Carry, xs: Any) -> tuple[_Carry, Any]:
            k, bad = xs
            ps, ds = carry.plant, carry.driver
            # the loop runs at the control period (plant_step, driver_step);
            # settings.dt is only the prediction model's step
            t = k.astype(dtype) * CONTROL_DT
            ds, steer, T_drv, v_ref = driver_step(ds, ps, t, scenario, dp)
            if c.example == "cruise" and use_ctrl:
                T_drv = jnp.zeros_like(T_drv)  # the MPC's DTR tracks v_ref
            meas = measure(ps, steer, jnp.zeros(4, dtype), mu, p)
            meas_c = jax.tree.map(lambda x: jnp.where(bad, nan, x), meas)
            model = self.model(meas_c, steer, T_drv, v_ref, mu)
            u_full = jnp.zeros((n_u,), dtype)
            u_ctrl_full = jnp.full((n_u,), nan)
            u_sh_full = jnp.full((n_u,), nan)
            iters = jnp.zeros((), jnp.int32)
            status = jnp.zeros((), jnp.int32)
            sh_iters = jnp.zeros((), jnp.int32)
            sh_status = jnp.full((), -1, jnp.int32)
            fb = jnp.zeros((), bool)
            warm_new, sh_warm_new, u_prev = carry.warm, carry.shadow_warm, carry.u_prev
            data = warm_in = None
            if use_ctrl:
                data = reduced_data(c, T, agent_idx, objective_idx, model)
                warm_in = carry.warm if c.warm_start else ctrl_cold
                res = ctrl.solve(data, warm=warm_in)
                u0 = res.u0
                ok = jnp.isin(res.status, jnp.asarray(_OK_STATUS)) & jnp.all(jnp.isfinite(u0))
                lb0 = jnp.where(jnp.isfinite(data.lb[0]), data.lb[0], 0.0)
                ub0 = jnp.where(jnp.isfinite(data.ub[0]), data.ub[0], 0.0)
                hold = jnp.where(jnp.isfinite(carry.u_prev), carry.u_prev, 0.0)
                hold = jnp.clip(hold, jnp.minimum(lb0, ub0), jnp.maximum(lb0, ub0))
                u_app = jnp.where(ok, u0, hold)
                fb = ~ok
                warm_new = jax.tree.map(
                    lambda a, b: jnp.where(ok, a, b),
                    shift_state(res.state, c.warm_shift),
                    ctrl_cold,
                )
                u_prev = u_app
                u_full = u_full.at[cols].set(u_app)
                u_ctrl_full = u_ctrl_full.at[cols].set(u0)
                iters, status = res.iterations, res.status
                if shadow is not None:
                    sh = shadow.solve(data, warm=carry.shadow_warm)
                    sh_ok = jnp.isin(sh.status, jnp.asarray(_OK_STATUS)) & jnp.all(
                        jnp.isfinite(sh.u0)
                    )
                    sh_warm_new = jax.tree.map(
                        lambda a, b: jnp.where(sh_ok, a, b),
                        shift_state(sh.state, c.warm_shift),
                        shadow_cold,
                    )
                    u_sh_full = u_sh_full.at[cols].set(sh.u0)
                    sh_iters, sh_status = sh.iterations, sh.status
            if c.example == "cruise" and not use_ctrl:
                # no MPC: the driver's speed PI plays DTR, within DTR's bounds
                dtr_max = jnp.asarray(c.settings.dtr_max, dtype)
                u_full = u_full.at[0].set(jnp.clip(T_drv, -dtr_max, dtr_max))
            torques = self.wheel_torques(u_full, T_drv)
            y_ref = yaw_rate_reference(meas.v_x, steer, mu, p)
            om_ref = (
                wheel_speed_reference(meas.v_x, T_drv, p, c.settings.slip_des)[0]
                if c.example == "stability"
                else nan
            )
            out = SimLog(
                t=t,
                X=ps.X,
                Y=ps.Y,
                psi=ps.psi,
                v_x=ps.v_x,
                v_y=ps.v_y,
                yaw_rate=ps.r,
                omega=ps.omega,
                slip=meas.slip,
                steer=steer,
                driver_torque=T_drv,
                # the stability drivers' open-loop torque tracks no speed: no v_ref
                v_ref=(
                    jnp.where((scenario.speed_kp == 0) & (scenario.speed_ki == 0), nan, v_ref)
                    if c.example == "stability"
                    else v_ref
                ),
                yaw_ref=y_ref,
                omega_ref=jnp.asarray(om_ref, dtype),
                path_y=path_y(scenario.path, ps.X).astype(dtype),
                u=u_full,
                u_ctrl=u_ctrl_full,
                u_shadow=u_sh_full,
                e_sub=jnp.abs(u_ctrl_full - u_sh_full),
                torques=torques,
                iterations=iters,
                status=status,
                shadow_iterations=sh_iters,
                shadow_status=sh_status,
                fallback=fb,
                data=data,
                warm=warm_in,
            )
            ps = plant_step(ps, steer, torques, mu, p)
            return _Carry(ps, ds, warm_new, sh_warm_new, u_prev), out

        n_red = T.n_u
        init = _Carry(
            initial_plant_state(scenario, p, dtype),
            initial_driver_state(dtype),
            ctrl_cold,
            shadow_cold,
            jnp.zeros((n_red,), dtype),
        )
        _, log = jax.lax.scan(step, init, (jnp.arange(n_steps), fault))
        return log


def _cast(tree: Any, dtype: Any) -> Any:
    """Cast floating leaves to ``dtype``.

    ``manoeuvres`` builds scenarios as NumPy float64 (dtype-safe whatever the
    x64 setting at import time). A scenario built by hand from float32 JAX
    arrays is widened through the shortest decimal representation, so 0.3
    becomes 0.3 and not 0.30000001192.
    """

    def cast(x: Any) -> Any:
        a = np.asarray(x)
        if not np.issubdtype(a.dtype, np.floating):
            return x
        if a.dtype == np.float32 and jnp.dtype(dtype) == np.float64:
            a = a.astype(str).astype(np.float64)
        return jnp.asarray(a, dtype)

    return jax.tree.map(cast, tree)


def run_closed_loop(
    config: SimConfig, scenario: Scenario, n_steps: int, fault: Any = None, dtype: Any = None
) -> SimLog:
    """Pure closed loop of one scenario (see :meth:`Simulator.run`); jit/vmap friendly.

    ``dtype`` casts the scenario (default: float64 when x64 is enabled).
    """
    dtype = dtype or jnp.result_type(float)
    scenario = jax.tree.map(
        lambda x: (
            jnp.asarray(x).astype(dtype)
            if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)
            else x
        ),
        scenario,
    )
    return Simulator(config).run(scenario, n_steps, fault)


_run_jit = jax.jit(run_closed_loop, static_argnums=(0, 2, 4))
_COMPILED: dict[Any, Any] = {}


def _compiled_run(
    config: SimConfig, sc: Scenario, n: int, fault: Any, dtype: Any
) -> tuple[Any, float]:
    """AOT-compiled closed loop, cached per (config, n, dtype); returns (fn, compile seconds)."""
    key = (config, n, jnp.dtype(dtype).name)
    if key in _COMPILED:
        return _COMPILED[key], 0.0
    t0 = time.perf_counter()
    fn = _run_jit.lower(config, sc, n, fault, dtype).compile()
    _COMPILED[key] = fn
    return fn, time.perf_counter() - t0


def simulate_batch(
    config: SimConfig, scenarios: Scenario, n_steps: int, mu: Any = None, dtype: Any = None
) -> SimLog:
    """Closed loop vmapped over stacked scenarios (``manoeuvres.stack_scenarios``).

    ``mu`` (batch,) overrides the friction of each case. Batched programs can
    deadlock intermittently on 2-core CPUs (``docs/results.md``): run with
    ``taskset -c 0`` or the XLA flags documented there.
    """
    n_steps = _positive_int("n_steps", n_steps)
    dtype = dtype or jnp.result_type(float)
    scenarios = _cast(scenarios, dtype)
    if mu is not None:
        scenarios = scenarios._replace(mu=jnp.asarray(check_mu(mu), dtype))

    def one(sc: Scenario) -> SimLog:
        return run_closed_loop(config, sc, n_steps, None, dtype)

    return jax.jit(jax.vmap(one))(scenarios)


# --------------------------------------------------------------------------- results
def _finite(x: np.ndarray, reduce: Any) -> float:
    """``reduce`` over the finite entries of ``x``; NaN when there are none."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(reduce(x)) if x.size else float("nan")


def _pct(x: np.ndarray, q: float) -> float:
    return _finite(x, lambda v: np.percentile(v, q))


def _max(x: np.ndarray) -> float:
    return _finite(x, np.max)


def _min(x: np.ndarray) -> float:
    return _finite(x, np.min)


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


@dataclass
class SimResult:
    """A finished run: the log (numpy), its configuration and timings, and :meth:`metrics`.

    Attributes
    ----------
    log : SimLog of numpy arrays.
    config : the SimConfig.
    scenario : scenario name.  focus : (t0, t1) window where both objectives act.
    duration : simulated time (s).  wall_time : run time of the compiled scan
    (s): the median of three executions after the first, whose one-time costs
    it leaves out (runs over 0.5 s: the first execution alone).
    compile_time : trace + compile time (s).  first_run_time : the first
    execution (s), one-time costs included.
    timing : per-step replay timings (:func:`replay_timing`), or None.
    """

    log: SimLog
    config: SimConfig
    scenario: str
    focus: tuple[float, float]
    duration: float
    wall_time: float
    compile_time: float
    timing: dict[str, np.ndarray] | None = None
    first_run_time: float | None = None

    @property
    def focus_mask(self) -> np.ndarray:
        t = np.asarray(self.log.t)
        return (t >= self.focus[0]) & (t <= self.focus[1])

    def metrics(self) -> dict[str, Any]:
        """Headline numbers: e_sub (eq.suboptimality), iterations, r_time (eq.t_ratio), tracking.

        ``e_sub`` statistics pool every enabled agent input of every step (Nm);
        ``focus`` restricts to the scenario's focus window (``focus_steps``
        control steps; the ``*_focus`` numbers are NaN when the run ends before
        the window starts). ``rho_scale_enabled`` is the part of ``rho_scale``
        that Local Explicit uses (the enabled objectives'). ``yaw_rms`` is the
        RMS of ``yaw_rate - yaw_ref``; rear slip statistics use wheels RL, RR
        and ``rear_slip_excess_rms`` is the RMS of ``max(|slip| - S_x,des, 0)``.
        """
        lg, c = self.log, self.config
        fm = self.focus_mask
        es = np.asarray(lg.e_sub, float)
        it = np.asarray(lg.iterations, float)
        yaw_err = np.asarray(lg.yaw_rate) - np.asarray(lg.yaw_ref)
        rear = np.abs(np.asarray(lg.slip)[:, 2:])
        slip_des = float(getattr(c.settings, "slip_des", 0.15))
        excess = np.maximum(rear - slip_des, 0.0)
        active = c.formulation != "none"
        m: dict[str, Any] = {
            "scenario": self.scenario,
            "example": c.example,
            "formulation": c.formulation,
            "objectives": list(c.enabled),
            "warm_start": c.warm_start,
            "horizon": c.horizon,
            "max_iter": c.max_iter,
            "tol_primal": c.tol_primal,
            "tol_dual": c.tol_dual,
            **c.solver_options(),
            "rho_scale_enabled": (
                list(c.enabled_rho_scale)
                if isinstance(c.enabled_rho_scale, tuple)
                else c.enabled_rho_scale
            ),
            "steps": int(len(lg.t)),
            "duration_s": self.duration,
            "focus_s": list(self.focus),
            "focus_steps": int(np.sum(fm)),
            "yaw_rms": _rms(yaw_err),
            "yaw_rms_focus": _rms(yaw_err[fm]),
            # NaN (null) where the driver tracks no speed (stability examples)
            "speed_rms": _rms(np.asarray(lg.v_x) - np.asarray(lg.v_ref)),
            "v_x_min": _min(np.asarray(lg.v_x)),
            "lateral_error_max": _max(np.abs(np.asarray(lg.Y) - np.asarray(lg.path_y))),
            "rear_slip_abs_max": _max(rear),
            "rear_slip_abs_p95": _pct(rear, 95),
            "rear_slip_excess_rms": _rms(excess),
            "rear_slip_excess_rms_focus": _rms(excess[fm]),
            "fallbacks": int(np.sum(np.asarray(lg.fallback))),
            "wall_time_s": self.wall_time,
            "first_run_s": self.first_run_time,
            "compile_time_s": self.compile_time,
            "realtime_factor": self.duration / self.wall_time if self.wall_time > 0 else None,
        }
        if active:
            for name, mask in (("", slice(None)), ("_focus", fm)):
                e = es[mask]
                m[f"e_sub_p50{name}"] = _pct(e, 50)
                m[f"e_sub_p95{name}"] = _pct(e, 95)
                m[f"e_sub_max{name}"] = _max(e)
                i = it[mask]
                m[f"iterations_p50{name}"] = _pct(i, 50)
                m[f"iterations_p95{name}"] = _pct(i, 95)
                m[f"iterations_max{name}"] = _max(i)
            m["e_sub_max_per_input"] = {
                n: _max(es[:, k])
                for k, n in enumerate(c.input_names)
                if np.isfinite(es[:, k]).any()
            }
            st = np.asarray(lg.status)
            m["status_counts"] = {int(s): int(np.sum(st == s)) for s in np.unique(st)}
            sst = np.asarray(lg.shadow_status)
            m["shadow_not_solved"] = int(np.sum(sst != 0)) if c.shadow else None
            m["shadow_iterations_max"] = _max(np.asarray(lg.shadow_iterations, float))
        if self.timing is not None:
            r = self.timing["r_time"]
            m["r_time_median"] = _pct(r, 50)
            m["r_time_p95"] = _pct(r, 95)
            m["r_time_median_focus"] = _pct(r[fm], 50)
            m["t_distributed_median_us"] = _pct(self.timing["t_distributed"], 50) * 1e6
            m["t_integrated_median_us"] = _pct(self.timing["t_integrated"], 50) * 1e6
            m["integrated_iterations_p50"] = _pct(self.timing["integrated_iterations"], 50)
            m["timing_note"] = self.timing_note()
        m["warnings"] = self.warnings()
        return m

    def warnings(self) -> list[str]:
        """What makes parts of this run unreliable, one sentence each (empty: none).

        * the vehicle went backwards: the plant's slip and slip angles and the
          drivers are written for forward driving, so the rest of the run is not
          physical (e.g. ``cruise_lane_change --mu 0.3``, which spins the car);
        * control steps that stopped at ``max_iter`` without meeting eps_r/eps_s,
          or fell back (failed or non-finite solve, previous command held);
        * steps where the shadow integrated MPC did not converge: e_sub there
          compares with an unconverged reference.
        """
        lg, c = self.log, self.config
        out = []
        vx = np.asarray(lg.v_x, float)
        back = vx < V_X_BACKWARDS
        if np.any(back):
            k = int(np.argmax(back))
            out.append(
                f"the vehicle went backwards (v_x {np.nanmin(vx):.3g} m/s; first at "
                f"t = {float(lg.t[k]):g} s): the plant and the drivers model forward "
                "driving only, so the run is not physical from there on"
            )
        if c.formulation != "none":
            st = np.asarray(lg.status)
            n = len(st)
            capped = int(np.sum(st == 1))
            if capped:
                out.append(
                    f"{capped} of {n} control steps stopped at max_iter = {c.max_iter} "
                    "without meeting eps_r / eps_s"
                )
            fb = int(np.sum(np.asarray(lg.fallback)))
            if fb:
                out.append(
                    f"{fb} of {n} control steps fell back to the previous command "
                    "(a failed or non-finite solve)"
                )
            if c.shadow:
                bad = int(np.sum(np.asarray(lg.shadow_status) != 0))
                if bad:
                    out.append(
                        f"the shadow integrated MPC did not converge on {bad} of {n} steps: "
                        "e_sub there compares with an unconverged reference"
                    )
        return out

    def timing_note(self) -> str:
        return (
            "per step, median of repeats of one compiled call: full control step "
            "(make_data output -> local costs H_j/E_j, rho (eq.opt_ro), Cholesky, "
            "ADMM while_loop to tolerance, result) for Local Explicit and for IntegratedADMM "
            f"(same tolerances eps_r={self.config.tol_primal:g}, eps_s={self.config.tol_dual:g}, "
            f"same relaxation {self.config.relaxation:g}, rho* scaled by "
            f"{self.config.enabled_rho_scale} and {self.config.integrated_rho_scale:g} "
            "respectively, same warm/cold start policy)"
        )


def simulate(
    scenario: str | ScenarioSpec,
    config: SimConfig | None = None,
    *,
    duration: float | None = None,
    mu: float | None = None,
    fault: Any = None,
    dtype: Any = None,
    timing: bool = False,
    repeats: int = 3,
) -> SimResult:
    """Compile and run one scenario's closed loop; optionally replay it for r_time.

    Parameters
    ----------
    scenario : a name of ``manoeuvres.SCENARIOS`` or a ScenarioSpec.
    config : SimConfig (default :func:`config_for` the scenario).
    duration : simulated time in s (default: the scenario's): finite and at
        least one control period, ``CONTROL_DT``, and at most ``DURATION_MAX``
        (:func:`check_duration`); rounded to whole control periods.
    mu : road friction override, finite in (0, MU_MAX] (:func:`check_mu`).
    fault : optional (n_steps,) bool mask of NaN measurements.
    dtype : float64 (default with x64) or float32.
    timing : replay the run for eq.t_ratio (:func:`replay_timing`).
    """
    spec = SCENARIOS[scenario] if isinstance(scenario, str) else scenario
    config = config or config_for(spec)
    if mu is not None and np.size(check_mu(mu)) != 1:
        raise ValueError(
            f"mu: expected one friction value (simulate_batch runs several), got {mu!r}"
        )
    sc = spec.scenario if mu is None else spec.scenario._replace(mu=np.asarray(mu, np.float64))
    dur = check_duration(spec.duration if duration is None else duration)
    n = max(1, int(round(dur / CONTROL_DT)))
    dtype = dtype or jnp.result_type(float)
    sc = _cast(sc, dtype)
    fault_arr = jnp.zeros((n,), bool) if fault is None else jnp.asarray(fault, bool)
    if fault_arr.shape != (n,):
        raise ValueError(
            f"fault: expected a ({n},) mask (one entry per control step), got shape "
            f"{fault_arr.shape}"
        )
    compiled, t_compile = _compiled_run(config, sc, n, fault_arr, dtype)
    t0 = time.perf_counter()
    log = jax.block_until_ready(compiled(sc, fault_arr))
    first = time.perf_counter() - t0
    wall = _warm_wall_time(lambda: compiled(sc, fault_arr), first)
    log_np = jax.tree.map(np.asarray, log)
    res = SimResult(
        log_np, config, spec.name, spec.focus, n * CONTROL_DT, wall, t_compile, first_run_time=first
    )
    if timing and config.formulation != "none":
        res.timing = replay_timing(config, log, repeats=repeats)
    return res


def _warm_wall_time(run: Callable[[], Any], first: float) -> float:
    """Median wall time of ``_WARM_RUNS`` further executions of a compiled run.

    The first execution of a compiled closed loop carries one-time costs
    (about 25 ms in float32 here, against 6 to 16 ms for a whole 9 to 16 s
    run after it), so the run time reported is that of the runs after it;
    runs whose first execution took over ``_WARM_BUDGET_S`` are not repeated
    (their one-time cost is small beside them), and the first time is kept.
    """
    if first > _WARM_BUDGET_S:
        return first
    walls = []
    for _ in range(_WARM_RUNS):
        t0 = time.perf_counter()
        jax.block_until_ready(run())
        walls.append(time.perf_counter() - t0)
    return float(np.median(walls))


_WARM_RUNS = 3
_WARM_BUDGET_S = 0.5


# --------------------------------------------------------------------------- r_time
def replay_timing(
    config: SimConfig,
    log: SimLog,
    repeats: int = 3,
    progress: Callable[[int], Any] | None = None,
) -> dict[str, np.ndarray]:
    """Time eq.t_ratio per step by replaying the logged ProblemData.

    What is timed, for both Local Explicit and IntegratedADMM: one call of an
    ahead-of-time compiled full control step on the logged
    :class:`ProblemData` -- local costs (H_j, E_j), rho (eq.opt_ro), Cholesky
    factorisation, the ADMM ``while_loop`` to the *controller's* tolerance
    ``config.tol_primal``, ``config.tol_dual`` and the result -- with ``block_until_ready``; the median of
    ``repeats`` calls per step. Building the model and ``make_data`` are not
    timed (identical for both). Both use ``config.relaxation``; Local Explicit
    scales eq.opt_ro's rho* by ``config.rho_scale`` (enabled objectives),
    IntegratedADMM by its own ``config.integrated_rho_scale``, each tuned by
    the same sweep (``docs/results.md``). Warm start: Local Explicit gets the warm state
    it had in the loop; IntegratedADMM is replayed sequentially from its own
    shifted previous solution at the same tolerance (cold at every step when
    ``config.warm_start`` is False).

    ``progress``, if given, is called with 1 after every replayed step (a
    progress bar's ``update``).

    Returns
    -------
    dict with (K,) arrays ``t_distributed``, ``t_integrated`` (s), ``r_time``
    and ``integrated_iterations``, ``distributed_iterations``.
    """
    T = build_topology(config)[0]
    le = local_explicit_solver(config, T)
    ia = integrated_solver(config, T, max_iter=max(config.max_iter, 2000))
    if config.formulation == "integrated":
        raise ValueError(
            "replay_timing compares Local Explicit with IntegratedADMM; run local_explicit"
        )
    data, warm = log.data, log.warm
    K = int(np.shape(log.t)[0])
    dtype = data.A.dtype
    cold_i = cold_state(merged_topology(T), dtype)
    d0 = jax.tree.map(lambda x: x[0], data)
    w0 = jax.tree.map(lambda x: x[0], warm)
    f_le = jax.jit(le.solve).lower(d0, None, w0).compile()
    f_ia = jax.jit(ia.solve).lower(d0, None, cold_i).compile()
    datas = [jax.device_put(jax.tree.map(lambda x, k=k: np.asarray(x[k]), data)) for k in range(K)]
    warms = [jax.device_put(jax.tree.map(lambda x, k=k: np.asarray(x[k]), warm)) for k in range(K)]
    t_d = np.zeros(K)
    t_i = np.zeros(K)
    it_d = np.zeros(K, int)
    it_i = np.zeros(K, int)
    w_i = cold_i
    for k in range(K):
        jax.block_until_ready(f_le(datas[k], None, warms[k]))  # warm caches
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = jax.block_until_ready(f_le(datas[k], None, warms[k]))
            ts.append(time.perf_counter() - t0)
        t_d[k] = np.median(ts)
        it_d[k] = int(r.iterations)
        jax.block_until_ready(f_ia(datas[k], None, w_i))
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = jax.block_until_ready(f_ia(datas[k], None, w_i))
            ts.append(time.perf_counter() - t0)
        t_i[k] = np.median(ts)
        it_i[k] = int(r.iterations)
        ok = int(r.status) in _OK_STATUS and bool(np.all(np.isfinite(np.asarray(r.u))))
        w_i = shift_state(r.state, config.warm_shift) if (config.warm_start and ok) else cold_i
        if progress is not None:
            progress(1)
    return {
        "t_distributed": t_d,
        "t_integrated": t_i,
        "r_time": t_d / t_i,
        "distributed_iterations": it_d,
        "integrated_iterations": it_i,
    }


# --------------------------------------------------------------------------- CLI hook
def add_cli_commands(sub: Any) -> None:
    """Register ``ampc simulate`` and ``ampc demo`` (see :mod:`ampc_jax.reporting`)."""
    from .reporting import add_cli_commands as _add

    _add(sub)


def with_settings(config: SimConfig, **fields: Any) -> SimConfig:
    """A copy of ``config`` with some fields of its settings replaced (e.g. ``q_yrt=...``)."""
    return replace(config, settings=config.settings._replace(**fields))
