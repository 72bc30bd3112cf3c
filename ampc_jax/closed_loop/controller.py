"""The MPC controller of a vehicle example as an init/step pair (after optax).

:meth:`Controller.step` is one control period of the controller, whatever
calls it (the simulated closed loop, the runtime next to the CAN bridge, a
replay): re-linearise the example's model at the measurement
(eq.CC_system / eq.VSC_system), restricted to the enabled objectives and
their agents; solve (Local Explicit, eq.integMPC_F3 to eq.F3_multiplier, or
the integrated MPC), warm started from the previous step; guard the result;
map the agent inputs to wheel torques.

Fallback guard: a solve whose status is not usable
(:func:`~ampc_jax.results.usable`: solved or ``max_iter_reached`` for the ADMM
formulations), or whose U^(0) is not finite, is not applied; the
previous command clipped to the current bounds is held instead (zero where
that is not finite) and the warm start is reset to cold. So the actuators
never receive NaN or out-of-bound torques.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..admm.learned_start import LearnedStart, StartModel
from ..admm.state import ADMMState
from ..formulations import (
    DEFAULT_FORMULATION,
    Formulation,
    check_formulation,
    formulation,
    formulation_names,
    formulation_options,
)
from ..formulations.local_explicit import PAPER_ITERATION
from ..problem.data import ProblemData, make_data
from ..problem.topology import Topology
from ..results import usable
from ..validation import check_count
from ..vehicle.examples import VehicleExample
from ..vehicle.params import Measurement, VehicleParams
from .config import ControllerParams, SimConfig

__all__ = [
    "Controller",
    "ControllerState",
    "DriverInputs",
    "StepInfo",
    "controller_for",
]


class DriverInputs(NamedTuple):
    """What the driver and the road give the controller at a step (all shape ())."""

    steer: Any  # rad, front road-wheel angle
    driver_torque: Any  # Nm, T_DTR on the rear axle
    v_ref: Any  # m/s, target speed (the LST reference)
    mu: Any  # road friction


class ControllerState(NamedTuple):
    """What the controller carries from one step to the next."""

    warm: ADMMState  # the solver state the next step starts from
    u_prev: Any  # (n_u,) last applied command of the topology's inputs (Nm)


class StepInfo(NamedTuple):
    """What one :meth:`Controller.step` did (for logs; shapes for one step)."""

    u: Any  # (n_inputs,) applied agent inputs of the example (0 for agents left out)
    u_ctrl: Any  # (n_inputs,) the solver's U^(0) before the guard (NaN for agents left out)
    driver_torque: Any  # () the driver torque the vehicle got (Nm)
    iterations: Any  # () int32
    status: Any  # () int32 (results.Status)
    fallback: Any  # () bool: the guard replaced the solver's output
    primal_residual: Any  # () the largest objective's ||r_j||^2
    dual_residual: Any  # () the largest objective's ||s_j||^2
    data: ProblemData  # the step's problem (for a shadow, a replay, r_time)
    warm: ADMMState  # the state the solve started from


@dataclass(frozen=True)
class Controller:
    """Static description of one example's MPC controller (hashable; jit-static).

    Parameters
    ----------
    example : the vehicle example.
    enabled : its enabled objectives (example order); the agents are the union
        of their groups.
    horizon : N_p (must match the settings the step is given).
    formulation : a registered formulation that serves closed loops
        (``info.closed_loop``; default ``"local_explicit"``,
        :func:`~ampc_jax.formulations.formulation_names`).
    max_iter, anderson : the solver's static options (defaults 200, 0).
    finish : the solver's exact finish where the formulation has one
        (``"none"``, default: the paper's iteration; ``"active_set"``:
        :mod:`~ampc_jax.admm.finish`). rho_j is eq.opt_ro's at every step
        either way (:data:`~ampc_jax.formulations.PAPER_ITERATION`).
    warm_start : start each step from the previous step's state (default True).
    warm_shift : 1 shifts that state one step along the horizon, 0 holds it.
    vehicle : the vehicle data the model uses.
    fixed_iterations : ``None`` (default): solve to eq.Convergence's tolerance
        (``solve``, a ``while_loop``, capped at ``max_iter``). An integer K >= 1:
        exactly K iterations per step (``solve_fixed``, a ``lax.scan``), so the
        step, and a closed loop of such steps, is reverse-mode differentiable
        with respect to :class:`ControllerParams` (weights, bounds, rho,
        relaxation). The status is then ``solved`` where the K-th iterate meets
        the tolerance, else ``max_iter_reached`` (both applied); the fallback
        guard is the same.
    learned_start : a :class:`~ampc_jax.admm.learned_start.StartModel` the solve
        starts from (:attr:`solver` wraps the formulation in
        :class:`~ampc_jax.admm.learned_start.LearnedStart`): a ``"loop"`` model
        corrects the previous step's iterate, a ``"step"`` model replaces it by
        its prediction from the step's data. None (default): the previous
        step's iterate as it is.
    """

    example: VehicleExample
    enabled: tuple[str, ...]
    horizon: int
    formulation: str = DEFAULT_FORMULATION
    max_iter: int = 200
    anderson: int = 0
    finish: str = "none"
    warm_start: bool = True
    warm_shift: int = 1
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    fixed_iterations: int | None = None
    learned_start: StartModel | None = None

    def __post_init__(self) -> None:
        info = check_formulation(self.formulation, closed_loop=True)
        unknown = [o for o in self.enabled if o not in self.example.objectives]
        if unknown or not self.enabled:
            raise ValueError(
                f"enabled: expected some of {list(self.example.objectives)}, got {self.enabled!r}"
            )
        object.__setattr__(self, "enabled", tuple(self.enabled))
        if self.fixed_iterations is not None:
            k = check_count(self.fixed_iterations, "fixed_iterations")
            object.__setattr__(self, "fixed_iterations", k)
        if self.learned_start is not None:
            if not info.learned_start:
                raise ValueError(
                    f"learned_start: formulation {self.formulation!r} serves no learned start "
                    f"(those that do: {list(formulation_names(learned_start=True))})"
                )
            why = self.learned_start.mismatch(self._formulation)
            if why is not None:
                raise ValueError(f"learned_start: the start network does not fit: {why}")

    # -- static structure ---------------------------------------------------------
    @functools.cached_property
    def _structure(self) -> tuple[Topology, tuple[int, ...], tuple[int, ...]]:
        ex = self.example
        enabled = [o for o in ex.objectives if o in self.enabled]
        agent_idx = tuple(sorted({ex.agents.index(a) for o in enabled for a in ex.groups[o]}))
        objective_idx = tuple(ex.objectives.index(o) for o in enabled)
        groups = [tuple(agent_idx.index(ex.agents.index(a)) for a in ex.groups[o]) for o in enabled]
        topo = Topology.build(
            n_x=ex.n_x,
            horizon=self.horizon,
            agent_names=[ex.agents[i] for i in agent_idx],
            agent_sizes=[ex.agent_sizes[i] for i in agent_idx],
            objective_names=enabled,
            output_sizes=[len(ex.outputs[o]) for o in enabled],
            groups=groups,
        )
        return topo, agent_idx, objective_idx

    @property
    def topology(self) -> Topology:
        """Topology of the enabled objectives: agents = the union of their groups
        S_j (example order), objectives = the enabled ones."""
        return self._structure[0]

    @property
    def agent_indices(self) -> tuple[int, ...]:
        """The topology's agents as indices into the example's agents."""
        return self._structure[1]

    @property
    def objective_indices(self) -> tuple[int, ...]:
        """The enabled objectives as indices into the example's objectives."""
        return self._structure[2]

    @property
    def input_columns(self) -> np.ndarray:
        """Columns of the example's inputs the topology's agents hold."""
        return self.example.input_columns(self.agent_indices)

    @property
    def _formulation(self) -> Formulation:
        # the paper's iteration (eq.opt_ro at every step) with the finish asked for,
        # where the formulation takes those options
        opts = formulation_options(self.formulation)
        extra = {k: v for k, v in {**PAPER_ITERATION, "finish": self.finish}.items() if k in opts}
        return formulation(
            self.formulation,
            self.topology,
            max_iter=self.max_iter,
            anderson=self.anderson,
            **extra,
        )

    @property
    def solver(self) -> Formulation:
        """The formulation solving each step (started by ``learned_start`` when given)."""
        if self.learned_start is None:
            return self._formulation
        return LearnedStart(self._formulation, self.learned_start)

    # -- init / step ----------------------------------------------------------------
    def init(self, dtype: Any = None) -> ControllerState:
        """The state before the first step: a cold solver state, no previous command."""
        dt = jnp.result_type(float) if dtype is None else dtype
        return ControllerState(self.solver.cold_state(dt), jnp.zeros((self.topology.n_u,), dt))

    def problem_data(
        self, params: ControllerParams, meas: Measurement, driver: DriverInputs
    ) -> ProblemData:
        """The step's :class:`ProblemData` (eq.eq_linear, eq.integMPC) of the enabled
        objectives: the example's model at ``meas``, its weights from ``params``."""
        ex, s = self.example, params.settings
        model = ex.model(
            meas, driver.steer, driver.driver_torque, driver.v_ref, driver.mu, self.vehicle, s
        )
        dtype = model.x0.dtype
        Qs, Rs = ex.weights(s)
        names = ex.objectives
        return make_data(
            self.topology,
            A=model.A,
            B=tuple(model.B[i] for i in self.agent_indices),
            x0=model.x0,
            C=tuple(jnp.asarray(ex.outputs[names[j]], dtype) for j in self.objective_indices),
            Q=tuple(Qs[j] for j in self.objective_indices),
            ref=tuple(model.ref[j] for j in self.objective_indices),
            R=tuple(Rs[i] for i in self.agent_indices),
            lb=tuple(model.lb[i] for i in self.agent_indices),
            ub=tuple(model.ub[i] for i in self.agent_indices),
            w=model.w,
            dtype=dtype,
        )

    def step(
        self,
        state: ControllerState,
        params: ControllerParams,
        meas: Measurement,
        driver: DriverInputs,
    ) -> tuple[Any, ControllerState, StepInfo]:
        """One control period: model, solve, guard, warm start, wheel torques.

        Returns (4,) wheel torques [FL, FR, RL, RR] in Nm, the next state and a
        :class:`StepInfo`. Pure and jittable (``params`` traced: one compiled
        step for every rho, relaxation, tolerance, weight and bound); with
        ``fixed_iterations`` also reverse-mode differentiable in ``params``.
        """
        if params.settings.horizon != self.horizon:
            raise ValueError(
                f"settings.horizon: the controller was built for N_p = {self.horizon}, "
                f"got {params.settings.horizon}"
            )
        solver = self.solver
        dtype = jnp.result_type(meas.v_x)
        T_seen = self.example.driver_torque_seen(driver.driver_torque, mpc=True)
        driver = driver._replace(driver_torque=T_seen)
        data = self.problem_data(params, meas, driver)
        cold = solver.cold_state(dtype)
        warm_in = state.warm if self.warm_start else cold
        # a "step" network predicts from the data alone: no previous iterate given
        given = (
            None
            if self.learned_start is not None and self.learned_start.kind == "step"
            else warm_in
        )
        if self.fixed_iterations is None:
            res = solver.solve(data, params.solver, given)
        else:
            res = solver.solve_fixed(data, self.fixed_iterations, params.solver, given)
        u0 = res.u0
        ok = usable(res.status) & jnp.all(jnp.isfinite(u0))
        lb0 = jnp.where(jnp.isfinite(data.lb[0]), data.lb[0], 0.0)
        ub0 = jnp.where(jnp.isfinite(data.ub[0]), data.ub[0], 0.0)
        hold = jnp.where(jnp.isfinite(state.u_prev), state.u_prev, 0.0)
        hold = jnp.clip(hold, jnp.minimum(lb0, ub0), jnp.maximum(lb0, ub0))
        u_app = jnp.where(ok, u0, hold)
        warm_next = jax.tree.map(
            lambda a, b: jnp.where(ok, a, b), solver.shift(res.state, self.warm_shift), cold
        )
        cols = self.input_columns
        n = self.example.n_inputs
        u_full = jnp.zeros((n,), dtype).at[cols].set(u_app)
        u_ctrl = jnp.full((n,), jnp.nan, dtype).at[cols].set(u0)
        torques = self.example.wheel_torques(u_full, T_seen)
        info = StepInfo(
            u=u_full,
            u_ctrl=u_ctrl,
            driver_torque=T_seen,
            iterations=res.iterations,
            status=res.status,
            fallback=~ok,
            primal_residual=jnp.max(res.primal_residual),
            dual_residual=jnp.max(res.dual_residual),
            data=data,
            warm=warm_in,
        )
        return torques, ControllerState(warm_next, u_app), info


def controller_for(config: SimConfig) -> Controller | None:
    """The static controller of ``config`` (its example, enabled objectives, horizon,
    formulation and solver options), or None without MPC (``formulation="none"``)."""
    if not config.mpc:
        return None
    return Controller(
        example=config.vehicle_example,
        enabled=config.enabled,
        horizon=config.horizon,
        formulation=config.formulation,
        max_iter=config.max_iter,
        anderson=config.anderson,
        finish=config.finish,
        warm_start=config.warm_start,
        warm_shift=config.warm_shift,
        vehicle=config.vehicle,
        fixed_iterations=config.fixed_iterations,
        learned_start=config.learned_start,
    )
