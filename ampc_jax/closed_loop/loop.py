"""The closed loop of section "Experimental Studies" under one ``lax.scan``.

One control period (``CONTROL_DT`` = 50 ms, 20 Hz) of the closed loop is

1. the driver (:func:`~ampc_jax.vehicle.manoeuvres.driver_step`): steering,
   driver torque T_DTR, target speed v_ref;
2. the plant measurement (:func:`~ampc_jax.vehicle.plant.measure`), NaN where
   a fault is injected;
3. the controller step (:meth:`~ampc_jax.closed_loop.controller.Controller.step`:
   model, solve, fallback guard, warm start, wheel torques), or the example's
   driver alone (``formulation="none"``);
4. in shadow, the integrated MPC on the controller's problem
   (:class:`~ampc_jax.closed_loop.shadow.IntegratedShadow`), for e_sub;
5. logging, and the plant (:func:`~ampc_jax.vehicle.plant.plant_step`, 50
   sub-steps of 1 ms).

The static structure (:class:`Simulator`) and the numbers (:class:`LoopParams`:
solver parameters, weights, bounds) are separate arguments of the compiled
loop, so one compilation serves every rho point of a sweep. Per-step problem
data and warm starts are logged, so that eq.t_ratio, which cannot be timed
inside a scan, is measured afterwards (:mod:`~ampc_jax.closed_loop.timing`).

Batching follows Brax: :func:`run_closed_loop` handles one scenario;
:func:`simulate_batch` vmaps it over stacked scenarios (and friction values).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..vehicle.actuators import ACTUATORS, ActuatorLimits, bridge_actuators
from ..vehicle.examples import VehicleExample
from ..vehicle.manoeuvres import (
    DriverParams,
    Scenario,
    ScenarioSpec,
    driver_step,
    initial_driver_state,
    initial_plant_state,
    path_y,
)
from ..vehicle.manoeuvres import scenario as scenario_spec
from ..vehicle.models import yaw_rate_reference
from ..vehicle.params import CONTROL_DT, VehicleParams
from ..vehicle.plant import measure, plant_step
from .compile import loop_compiler_options
from .config import (
    LoopParams,
    SimConfig,
    check_duration,
    check_mu,
    check_steps,
    config_for,
)
from .controller import Controller, DriverInputs, controller_for
from .log import SimLog
from .metrics import SimResult
from .shadow import IntegratedShadow, shadow_for
from .timing import replay_timing

__all__ = [
    "PreparedRun",
    "SimLog",
    "Simulator",
    "compile_run",
    "finish",
    "prepare",
    "run_closed_loop",
    "simulate",
    "simulate_batch",
    "simulator_for",
    "time_run",
]


class _Carry(NamedTuple):
    plant: Any
    driver: Any
    actuators: Any  # (4,) int32, the bridge limiter's output in 2 Nm steps
    controller: Any  # ControllerState, or None without an MPC
    shadow: Any  # the shadow's ADMMState, or None


@dataclass(frozen=True)
class Simulator:
    """The static closed loop: example, controller, shadow, vehicle, driver (hashable).

    ``controller`` None: no MPC (the example's driver alone); ``shadow`` None:
    no e_sub; ``actuators`` None: the plant gets the commanded torques, else
    the CAN bridge's limiter with these limits stands between
    (:func:`~ampc_jax.vehicle.actuators.bridge_actuators`; ``torques`` logs
    what the plant got). Build it with :func:`simulator_for`.
    """

    example: VehicleExample
    controller: Controller | None
    shadow: IntegratedShadow | None
    vehicle: VehicleParams
    driver: DriverParams
    actuators: ActuatorLimits | None = None

    def run(
        self, scenario: Scenario, params: LoopParams, n_steps: int, fault: Any = None
    ) -> SimLog:
        """Run the closed loop for ``n_steps`` control periods (pure; jit with
        ``self`` and ``n_steps`` static, ``params`` traced).

        Parameters
        ----------
        scenario : the manoeuvre's arrays (its dtype sets the simulation's dtype).
        params : the numbers (:meth:`SimConfig.loop_params`).
        n_steps : number of control steps (static).
        fault : optional (n_steps,) bool; where True the controller receives a
            NaN measurement (to exercise the fallback guard).
        """
        ex, ctrl, shadow = self.example, self.controller, self.shadow
        dtype = jnp.result_type(scenario.v0)
        vp, dp = self.vehicle, self.driver
        settings = params.controller.settings
        if ctrl is None:
            scenario = ex.no_mpc_scenario(scenario)
        mu = scenario.mu
        fault = jnp.zeros((n_steps,), bool) if fault is None else jnp.asarray(fault, bool)
        nan = jnp.asarray(jnp.nan, dtype)
        n_in = ex.n_inputs
        cols = ctrl.input_columns if ctrl is not None else None

        def step(carry: _Carry, xs: Any) -> tuple[_Carry, Any]:
            k, bad = xs
            ps, ds = carry.plant, carry.driver
            # the loop runs at the control period (plant_step, driver_step);
            # settings.dt is only the prediction model's step
            t = k.astype(dtype) * CONTROL_DT
            ds, steer, T_drv, v_ref = driver_step(ds, ps, t, scenario, dp)
            meas = measure(ps, steer, jnp.zeros(4, dtype), mu, vp)
            meas_c = jax.tree.map(lambda x: jnp.where(bad, nan, x), meas)
            u_sh_full = jnp.full((n_in,), nan)
            sh_iters = jnp.zeros((), jnp.int32)
            sh_status = jnp.full((), -1, jnp.int32)
            ctrl_state, sh_state = carry.controller, carry.shadow
            if ctrl is not None:
                torques, ctrl_state, info = ctrl.step(
                    ctrl_state, params.controller, meas_c, DriverInputs(steer, T_drv, v_ref, mu)
                )
                T_drv = info.driver_torque
                u_full, u_ctrl_full = info.u, info.u_ctrl
                iters, status, fb = info.iterations, info.status, info.fallback
                data, warm_in = info.data, info.warm
                if shadow is not None:
                    sh_state, sh = shadow.observe(sh_state, params.shadow, data)
                    u_sh_full = u_sh_full.at[cols].set(sh.u0)
                    sh_iters, sh_status = sh.iterations, sh.status
            else:
                u_full = ex.no_mpc_inputs(T_drv, settings)
                u_ctrl_full = jnp.full((n_in,), nan)
                iters = jnp.zeros((), jnp.int32)
                status = jnp.zeros((), jnp.int32)
                fb = jnp.zeros((), bool)
                data = warm_in = None
                torques = ex.wheel_torques(u_full, T_drv)
            act = carry.actuators
            if self.actuators is not None:
                act, torques = bridge_actuators(act, torques, self.actuators)
            y_ref = yaw_rate_reference(meas.v_x, steer, mu, vp)
            om_ref = ex.wheel_speed_reference(meas, T_drv, vp, settings)
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
                v_ref=jnp.where(ex.logs_speed_reference(scenario), v_ref, nan),
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
            ps = plant_step(ps, steer, torques, mu, vp)
            return _Carry(ps, ds, act, ctrl_state, sh_state), out

        init = _Carry(
            initial_plant_state(scenario, vp, dtype),
            initial_driver_state(dtype),
            jnp.zeros((4,), jnp.int32),
            ctrl.init(dtype) if ctrl is not None else None,
            shadow.init(dtype) if shadow is not None else None,
        )
        _, log = jax.lax.scan(step, init, (jnp.arange(n_steps), fault))
        return log


def simulator_for(config: SimConfig) -> Simulator:
    """The static closed loop of ``config``: its controller
    (:func:`~.controller.controller_for`), shadow (:func:`~.shadow.shadow_for`),
    vehicle, driver and actuator model."""
    ctrl = controller_for(config)
    shadow = shadow_for(config, ctrl.topology) if ctrl is not None else None
    limits = ACTUATORS if config.actuators == "bridge" else None
    return Simulator(config.vehicle_example, ctrl, shadow, config.vehicle, config.driver, limits)


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
    simulator: Simulator,
    scenario: Scenario,
    params: LoopParams,
    n_steps: int,
    fault: Any = None,
) -> SimLog:
    """Pure closed loop of one scenario (:meth:`Simulator.run`); jit with
    ``simulator`` and ``n_steps`` static, vmap over scenarios and params.

    The scenario's floating leaves are cast to the dtype of ``params``.
    """
    dtype = jnp.result_type(params.shadow.rho)
    scenario = jax.tree.map(
        lambda x: (
            jnp.asarray(x).astype(dtype)
            if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)
            else x
        ),
        scenario,
    )
    return simulator.run(scenario, params, n_steps, fault)


_run_jit = jax.jit(run_closed_loop, static_argnums=(0, 3))
_COMPILED: dict[Any, Any] = {}


class PreparedRun(NamedTuple):
    """One scenario's closed loop, traced and lowered, before its compile (:func:`prepare`).

    ``lowered`` is None when this process already compiled the same program
    (``compiled`` holds it). Compile ``lowered`` with
    :func:`~ampc_jax.closed_loop.compile.loop_compiler_options` (or several at once,
    :class:`~ampc_jax.closed_loop.compile.Compiler`), then :func:`finish`.
    """

    spec: ScenarioSpec
    config: SimConfig
    scenario: Scenario
    params: LoopParams
    fault: Any
    n_steps: int
    key: Any
    lowered: Any
    compiled: Any
    lower_time: float

    def log_shapes(self) -> SimLog:
        """The log's shapes and dtypes (``jax.ShapeDtypeStruct`` leaves, a leading
        step axis), without running the loop."""
        out = self.lowered.out_info if self.lowered is not None else self.compiled.out_info
        return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype), out)


def prepare(
    scenario: str | ScenarioSpec,
    config: SimConfig | None = None,
    *,
    duration: float | None = None,
    mu: float | None = None,
    fault: Any = None,
    dtype: Any = None,
) -> PreparedRun:
    """Check the arguments of :func:`simulate` and trace and lower its closed loop
    (the part of a compile that holds the GIL); nothing is compiled or run."""
    t0 = time.perf_counter()
    spec = scenario_spec(scenario)
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
    fault_arr = np.zeros((n,), bool) if fault is None else np.asarray(fault, bool)
    if fault_arr.shape != (n,):
        raise ValueError(
            f"fault: expected a ({n},) mask (one entry per control step), got shape "
            f"{fault_arr.shape}"
        )
    params = config.loop_params(dtype)
    sim = simulator_for(config)
    key = (
        sim,
        n,
        jax.tree.structure(params),
        tuple(jnp.result_type(x).name for x in jax.tree.leaves(params)),
    )
    compiled = _COMPILED.get(key)
    lowered = None if compiled is not None else _run_jit.lower(sim, sc, params, n, fault_arr)
    return PreparedRun(
        spec, config, sc, params, fault_arr, n, key, lowered, compiled, time.perf_counter() - t0
    )


def compile_run(prep: PreparedRun) -> tuple[Any, float]:
    """Compile ``prep`` here (:data:`~.compile.LOOP_COMPILER_OPTIONS`): (program, seconds)."""
    if prep.lowered is None:
        return prep.compiled, 0.0
    t0 = time.perf_counter()
    fn = prep.lowered.compile(compiler_options=loop_compiler_options() or None)
    return fn, time.perf_counter() - t0


def finish(
    prep: PreparedRun,
    compiled: Any,
    compile_seconds: float,
    *,
    timing: bool = False,
    repeats: int = 3,
    time_runs: bool = True,
) -> SimResult:
    """Run the compiled closed loop of ``prep`` (:func:`simulate`'s second half).

    ``time_runs`` False: the run time is the first execution's alone; time the
    run later with :func:`time_run` (e.g. once other programs have compiled:
    a compile beside the run slows it).
    """
    _COMPILED[prep.key] = compiled
    sc, params, fault_arr = prep.scenario, prep.params, prep.fault
    t0 = time.perf_counter()
    log = jax.block_until_ready(compiled(sc, params, fault_arr))
    first = time.perf_counter() - t0
    log_np = jax.tree.map(np.asarray, log)
    spent = prep.lower_time + compile_seconds if prep.lowered is not None else 0.0
    res = SimResult(
        log_np,
        prep.config,
        prep.spec.name,
        prep.spec.focus,
        prep.n_steps * CONTROL_DT,
        first,
        spent,
        first_run_time=first,
    )
    if time_runs:
        time_run(prep, res)
    if timing and prep.config.mpc:
        res.timing = replay_timing(prep.config, log_np, repeats=repeats)
    return res


def time_run(prep: PreparedRun, res: SimResult) -> SimResult:
    """Set ``res.wall_time``: the run time of the compiled loop of ``prep`` after its
    first execution (:func:`_warm_wall_time`); returns ``res``."""
    compiled = _COMPILED[prep.key]
    sc, params, fault_arr = prep.scenario, prep.params, prep.fault
    res.wall_time = _warm_wall_time(
        lambda: compiled(sc, params, fault_arr), res.first_run_time or 0.0
    )
    return res


def simulate_batch(
    config: SimConfig,
    scenarios: Scenario,
    n_steps: int,
    mu: Any = None,
    dtype: Any = None,
    params: LoopParams | None = None,
) -> SimLog:
    """Closed loop vmapped over stacked scenarios (``manoeuvres.stack_scenarios``).

    ``mu`` (batch,) overrides the friction of each case. ``params``: a
    :class:`LoopParams` with a leading batch axis on every leaf (one parameter
    point per case), or None for ``config.loop_params(dtype)`` for all.
    """
    n_steps = check_steps(n_steps)
    dtype = dtype or jnp.result_type(float)
    scenarios = _cast(scenarios, dtype)
    if mu is not None:
        scenarios = scenarios._replace(mu=jnp.asarray(check_mu(mu), dtype))
    sim = simulator_for(config)
    opts = loop_compiler_options() or None
    if params is None:
        p = config.loop_params(dtype)
        run = jax.jit(
            jax.vmap(lambda sc: run_closed_loop(sim, sc, p, n_steps)), compiler_options=opts
        )
        return run(scenarios)
    run = jax.jit(
        jax.vmap(lambda sc, pp: run_closed_loop(sim, sc, pp, n_steps)), compiler_options=opts
    )
    return run(scenarios, params)


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
    prep = prepare(scenario, config, duration=duration, mu=mu, fault=fault, dtype=dtype)
    return finish(prep, *compile_run(prep), timing=timing, repeats=repeats)


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
