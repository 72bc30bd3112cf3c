"""The vehicle examples as objects: one :class:`VehicleExample` per example, and their registry.

An example says everything the closed loop, the runtime and the reports need
to know about it: its agents and their input sizes, its objectives with their
outputs C_j and agent groups S_j, its settings (weights, bounds, horizon), the
tuned solver defaults, the control model built at every step, the map from
agent inputs to wheel torques, what the vehicle does without the MPC, and the
baseline the paper compares it with. Adding an example is one file: a
subclass and a call to :func:`register_example` (``tests/vehicle/test_examples.py``
builds one that way and runs it in closed loop).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp
import numpy as np
from jax import Array

from .models import ControlModel, ExampleSettings
from .params import Measurement, VehicleParams

__all__ = ["EXAMPLES", "VehicleExample", "example", "register_example"]


@dataclass(frozen=True, eq=False)
class VehicleExample:
    """One of the paper's vehicle examples (static; hashed and compared by identity:
    each example is one registered object).

    Attributes
    ----------
    name : registry name (``"cruise"``, ``"stability"``).
    title : a few words for reports.
    agents : agent names in the example's order; ``agent_sizes`` their input counts.
    input_names : names of the example's agent inputs (columns of logs), in order.
    objectives : objective names in the example's order.
    outputs : per objective, C_j (rows over the state ``states``).
    groups : per objective, the agent group S_j (names).
    states : names of the prediction model's state X.
    settings_type : the :class:`ExampleSettings` subclass of its settings.
    solver_defaults : tuned defaults of the closed loop's solver options
        (``SimConfig`` fields; ``docs/results.md``, "Solver tuning"; an option
        left out is the paper's iteration's: no relaxation, acceleration or
        exact finish, eq.opt_ro's rho* unscaled), and
        ``consensus_rho_scale``, the rho factor of Formulations 1 and 2 when
        ``rho_scale`` is not given (default 1.0 when absent).
    no_mpc_label : what drives the vehicle without the MPC (``--formulation none``).
    """

    name: str
    title: str
    agents: tuple[str, ...]
    agent_sizes: tuple[int, ...]
    input_names: tuple[str, ...]
    objectives: tuple[str, ...]
    outputs: Mapping[str, tuple[tuple[float, ...], ...]]
    groups: Mapping[str, tuple[str, ...]]
    states: tuple[str, ...]
    settings_type: type
    solver_defaults: Mapping[str, Any]
    no_mpc_label: str

    # -- sizes -----------------------------------------------------------------------
    @property
    def n_inputs(self) -> int:
        """Number of agent inputs (the log's input columns)."""
        return int(sum(self.agent_sizes))

    @property
    def n_x(self) -> int:
        return len(self.states)

    def input_columns(self, agents: tuple[int, ...]) -> np.ndarray:
        """Columns of the example's inputs held by the agents ``agents`` (indices, static)."""
        offs = np.cumsum([0, *self.agent_sizes])
        return np.concatenate([np.arange(offs[i], offs[i + 1]) for i in agents]).astype(int)

    # -- to be given by each example --------------------------------------------------
    def settings(self, **overrides: Any) -> ExampleSettings:
        """The example's default settings, with ``overrides``, validated."""
        return self.settings_type(**overrides).validate()

    def weights(self, settings: ExampleSettings) -> tuple[tuple[Array, ...], tuple[Array, ...]]:
        """(Q_j per objective, R_(i) per agent), in the example's orders: by default
        the settings' own ``Q()`` and ``R()``."""
        return settings.Q(), settings.R()

    def model(
        self,
        meas: Measurement,
        steer: Array,
        driver_torque: Array,
        v_ref: Array,
        mu: Array,
        vehicle: VehicleParams,
        settings: ExampleSettings,
    ) -> ControlModel:
        """The control model at the measurement (per-agent B, bounds; per-objective refs)."""
        raise NotImplementedError

    def wheel_torques(self, u: Array, driver_torque: Array) -> Array:
        """Wheel torques [FL, FR, RL, RR] (Nm) from the (n_inputs,) agent inputs."""
        raise NotImplementedError

    def driver_torque_seen(self, driver_torque: Array, mpc: bool) -> Array:
        """The driver torque T_DTR the vehicle gets (cruise with the MPC: none, its
        DTR agent tracks the speed); by default the driver's own."""
        return driver_torque

    def no_mpc_scenario(self, scenario: Any) -> Any:
        """The scenario as driven without the MPC (cruise: the driver's speed PI on)."""
        return scenario

    def no_mpc_inputs(self, driver_torque: Array, settings: ExampleSettings) -> Array:
        """The agent inputs without the MPC; zeros by default."""
        return jnp.zeros((self.n_inputs,), jnp.result_type(driver_torque))

    def wheel_speed_reference(
        self, meas: Measurement, driver_torque: Array, vehicle: VehicleParams, settings: Any
    ) -> Array:
        """() rear wheel-speed reference to log (rad/s); NaN when the example has none."""
        return jnp.full((), jnp.nan, jnp.result_type(meas.v_x))

    def logs_speed_reference(self, scenario: Any) -> Array:
        """() bool: whether the driver tracks a target speed (else v_ref is logged NaN)."""
        return jnp.ones((), bool)

    def slip_target(self, settings: Any) -> float | None:
        """The desired slip ratio to draw in figures, or None."""
        return None

    def baseline(self) -> dict[str, Any]:
        """The ``SimConfig`` fields of the run the paper compares this example with,
        and a description: ``{"disabled": ..., "formulation": ..., "what": ...}``."""
        raise NotImplementedError


EXAMPLES: dict[str, VehicleExample] = {}
"""Registry: name -> example (:func:`register_example`)."""


def register_example(ex: VehicleExample) -> VehicleExample:
    """Add ``ex`` to :data:`EXAMPLES` (ValueError if another one has its name)."""
    if ex.name in EXAMPLES and EXAMPLES[ex.name] is not ex:
        raise ValueError(f"example: {ex.name!r} is already registered")
    EXAMPLES[ex.name] = ex
    return ex


def example(name: str | VehicleExample) -> VehicleExample:
    """The registered example ``name`` (ValueError naming ``example`` otherwise)."""
    if isinstance(name, VehicleExample):
        return name
    if name not in EXAMPLES:
        raise ValueError(f"example: expected one of {sorted(EXAMPLES)}, got {name!r}")
    return EXAMPLES[name]
