"""Tests of ampc_jax.vehicle.examples: the examples as objects, their registry, and
adding a third example in one file (this one) that runs in closed loop."""

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.closed_loop import SimConfig, baseline_config, config_for, controller_for, simulate
from ampc_jax.closed_loop.config import SOLVER_OPTIONS
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status
from ampc_jax.vehicle import (
    CONTROL_DT,
    CRUISE,
    EXAMPLES,
    SCENARIOS,
    STABILITY,
    CruiseSettings,
    ExampleSettings,
    Measurement,
    ScenarioSpec,
    StabilitySettings,
    VehicleExample,
    VehicleParams,
    example,
    register_example,
    register_scenario,
)
from ampc_jax.vehicle.cruise import cruise_control_model, cruise_wheel_torques
from ampc_jax.vehicle.manoeuvres import make_scenario, single_lane_change
from ampc_jax.vehicle.models import settings_dataclass

pytestmark = pytest.mark.timeout(180)

P = VehicleParams()


def _meas():
    f = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    z4 = jnp.zeros(4)
    return Measurement(
        f(14.0),
        f(0.2),
        f(0.1),
        f([40.0, 40.2, 41.0, 41.5]),
        f([0.0, 0.0, 400.0, 420.0]),
        f([2000.0, 1800.0, 2100.0, 1900.0]),
        z4,
        z4,
        z4,
        f(0.0),
        f(0.0),
    )


# --------------------------------------------------------------------------- the two examples
@pytest.mark.parametrize(
    ("ex", "kind", "T_drv"), [(CRUISE, CruiseSettings, 0.0), (STABILITY, StabilitySettings, 700.0)]
)
def test_examples_structure_matches_their_models(ex, kind, T_drv):
    """Agents, objectives, groups, outputs and input names agree with the model the
    example builds: B column counts = agent_sizes, C rows over the state, one
    reference entry per C row, weights and bounds sized per agent/objective."""
    assert EXAMPLES[ex.name] is ex and example(ex.name) is ex and example(ex) is ex
    assert ex.settings_type is kind
    # every SimConfig solver option, and Formulations 1 and 2's rho factor
    assert set(ex.solver_defaults) == {*SOLVER_OPTIONS, "consensus_rho_scale"}
    assert len(ex.agents) == len(ex.agent_sizes) and len(set(ex.agents)) == len(ex.agents)
    assert len(ex.input_names) == ex.n_inputs == sum(ex.agent_sizes)
    assert ex.n_x == len(ex.states)
    assert tuple(ex.outputs) == ex.objectives == tuple(ex.groups)
    for o in ex.objectives:
        assert set(ex.groups[o]) <= set(ex.agents), o
    s = kind()
    cm = ex.model(_meas(), 0.03, T_drv, 14.5, 1.0, P, s)
    assert cm.A.shape == (ex.n_x, ex.n_x) and cm.x0.shape == cm.w.shape == (ex.n_x,)
    assert [b.shape for b in cm.B] == [(ex.n_x, n) for n in ex.agent_sizes]
    assert [lb.shape[0] for lb in cm.lb] == list(ex.agent_sizes)
    assert [ub.shape[0] for ub in cm.ub] == list(ex.agent_sizes)
    assert len(cm.ref) == len(ex.objectives)
    for o, ref in zip(ex.objectives, cm.ref, strict=True):
        C = np.asarray(ex.outputs[o])
        assert C.shape == (ref.shape[0], ex.n_x), o
        # each row picks one named state (the outputs are states of the model)
        assert np.all(np.sort(C, axis=1)[:, -1] == 1.0) and np.all(np.sum(C, axis=1) == 1.0)
    Q, R = ex.weights(s)
    assert [q.shape for q in Q] == [(len(ex.outputs[o]),) * 2 for o in ex.objectives]
    assert [r.shape for r in R] == [(n, n) for n in ex.agent_sizes]
    # input columns of a subset of agents, in the example's input order
    np.testing.assert_array_equal(ex.input_columns((0, 2)), [0, 2, 3])
    np.testing.assert_array_equal(ex.input_columns(tuple(range(len(ex.agents)))), range(4))
    # the wheel-torque map takes the (n_inputs,) input vector
    assert ex.wheel_torques(jnp.zeros(ex.n_inputs), jnp.asarray(T_drv)).shape == (4,)
    # hashed by identity (a static jit argument; one registered object per name)
    twin = dataclasses.replace(ex)
    assert twin != ex and hash(twin) != hash(ex) and ex == ex


def test_cruise_and_stability_labels():
    assert CRUISE.no_mpc_label == "no MPC (driver PI)"
    assert STABILITY.no_mpc_label == "driver alone"
    assert CRUISE.baseline()["what"] == "LST alone"
    assert STABILITY.baseline() == {
        "disabled": (),
        "formulation": "none",
        "what": "the driver alone",
    }


def test_registry_errors():
    with pytest.raises(ValueError, match=r"^example: expected one of \['cruise', 'stability"):
        example("bicycle")
    with pytest.raises(ValueError, match=r"^example: "):
        SimConfig("bicycle")
    # another object under a registered name is refused; the same object is not
    with pytest.raises(ValueError, match=r"^example: 'cruise' is already registered"):
        register_example(dataclasses.replace(CRUISE))
    assert register_example(CRUISE) is CRUISE
    assert EXAMPLES["cruise"] is CRUISE
    spec = SCENARIOS["cruise_lane_change"]
    with pytest.raises(ValueError, match=r"^scenario: 'cruise_lane_change' is already registered"):
        register_scenario(spec._replace(duration=3.0))
    assert register_scenario(spec) is spec
    assert SCENARIOS["cruise_lane_change"] is spec and spec.duration == 16.0


# --------------------------------------------------------------------------- a third example
@settings_dataclass
class HeavyCruiseSettings(ExampleSettings):
    """Cruise control of a loaded vehicle: stiffer speed tracking, a longer horizon,
    more drive torque, less torque vectoring."""

    WEIGHTS = ("q_lst", "q_yrt")
    INPUT_WEIGHTS = ("r_dtr", "r_rtv", "r_fdb")
    BOUNDS = ("dtr_max", "rtv_max", "fdb_max")

    dt: float = CONTROL_DT
    horizon: int = 3
    q_lst: float = 16.0
    q_yrt: float = 2.0e3
    r_dtr: float = 1.0 / 3000.0**2
    r_rtv: float = 1.0 / 400.0**2
    r_fdb: float = 1.0 / 1000.0**2
    dtr_max: float = 3000.0
    rtv_max: float = 600.0
    fdb_max: float = 1500.0
    literal: bool = False

    def Q(self):
        return (jnp.array([[self.q_lst]]), jnp.array([[self.q_yrt]]))

    def R(self):
        return (jnp.array([[self.r_dtr]]), jnp.array([[self.r_rtv]]), self.r_fdb * jnp.eye(2))


@dataclass(frozen=True, eq=False)
class HeavyCruise(VehicleExample):
    """The cruise model with its own settings and groups: RTV and FDB are shared."""

    def weights(self, settings):
        return settings.Q(), settings.R()

    def model(self, meas, steer, driver_torque, v_ref, mu, vehicle, settings):
        return cruise_control_model(meas, steer, v_ref, mu, vehicle, settings)

    def wheel_torques(self, u, driver_torque):
        return cruise_wheel_torques((u[0:1], u[1:2], u[2:4]))

    def driver_torque_seen(self, driver_torque, mpc):
        return jnp.zeros_like(driver_torque) if mpc else driver_torque

    def baseline(self):
        return {"disabled": ("YRT",), "formulation": None, "what": "LST alone"}


HEAVY = HeavyCruise(
    name="test_cruise_heavy",
    title="heavy cruise control (LST, YRT)",
    agents=("DTR", "RTV", "FDB"),
    agent_sizes=(1, 1, 2),
    input_names=("DTR", "RTV", "FDB_L", "FDB_R"),
    objectives=("LST", "YRT"),
    outputs={"LST": ((1.0, 0.0, 0.0),), "YRT": ((0.0, 0.0, 1.0),)},
    # every agent that moves an objective's output is in its group (FDB brakes
    # also slow the car), so the distributed optimum is the integrated one
    groups={"LST": ("DTR", "RTV", "FDB"), "YRT": ("RTV", "FDB")},
    states=("v_x", "v_y", "yaw_rate"),
    settings_type=HeavyCruiseSettings,
    solver_defaults={
        "warm_shift": 1,
        "rho_scale": (1.0, 1.0),
        "relaxation": 1.5,
        "integrated_rho_scale": 1.0,
        "shadow_rho_scale": 1.0,
        "shadow_relaxation": 1.8,
        "anderson": 0,
    },
    no_mpc_label="no MPC (coasting)",
)

HEAVY_SCENARIO = ScenarioSpec(
    "test_heavy_lane_change",
    "test_cruise_heavy",
    1.0,
    (0.2, 0.8),
    "mu=1: a 2 m lane change at 15 m/s while speeding up to 16 m/s.",
    make_scenario(1.0, 15.0, single_lane_change(5.0, 15.0, 2.0), ([0.0, 1.0], [15.0, 16.0])),
)


@pytest.fixture(scope="module")
def heavy():
    register_example(HEAVY)
    register_scenario(HEAVY_SCENARIO)
    try:
        yield HEAVY
    finally:
        del EXAMPLES[HEAVY.name]
        del SCENARIOS[HEAVY_SCENARIO.name]


def test_third_example_runs_in_closed_loop(heavy):
    cfg = config_for("test_heavy_lane_change", shadow=False)
    assert cfg.vehicle_example is heavy and cfg.settings == HeavyCruiseSettings()
    assert cfg.rho_scale == (1.0, 1.0) and cfg.anderson == 0 and cfg.horizon == 3
    ctrl = controller_for(cfg)
    assert ctrl.topology.agent_names == ("DTR", "RTV", "FDB")
    assert ctrl.topology.groups == ((0, 1, 2), (1, 2))  # RTV and FDB are shared
    res = simulate("test_heavy_lane_change", cfg)
    lg = res.log
    assert lg.t.shape == (20,)
    assert np.all(np.isfinite(lg.u)) and np.all(np.isfinite(lg.torques))
    # its own bounds (HeavyCruiseSettings) reach the solver, and hold
    np.testing.assert_allclose(lg.data.lb[0, 0], [-3000, -600, -1500, -1500])
    np.testing.assert_allclose(lg.data.ub[0, 0], [3000, 600, 0, 0])
    lb, ub = np.asarray(lg.data.lb[:, 0]), np.asarray(lg.data.ub[:, 0])
    assert np.all(lg.u >= lb - 1e-9) and np.all(lg.u <= ub + 1e-9)
    # converged at every step, no fallback, close to the integrated optimum of
    # the step's problem (Clarabel)
    assert np.all(lg.status == Status.SOLVED), lg.status
    assert not np.any(lg.fallback)
    m = res.metrics()
    assert m["example"] == "test_cruise_heavy" and m["objectives"] == ["LST", "YRT"]
    assert m["warnings"] == [] and m["horizon"] == 3
    for k in (3, 12, 19):
        data = jax.tree.map(lambda x, k=k: np.asarray(x[k]), lg.data)
        ref = solve_reference(ctrl.topology, data)
        assert ref.status == Status.SOLVED
        np.testing.assert_allclose(lg.u[k], np.asarray(ref.u[0]), atol=5.0)
    # the controller drives: the speed follows v_ref (15 -> 16 m/s) within 0.3 m/s
    assert np.max(np.abs(lg.v_x - lg.v_ref)) < 0.3
    assert np.any(np.abs(lg.u[:, 0]) > 100.0)
    # and its baseline, LST alone, is built from the example's own description
    assert baseline_config(cfg).enabled == ("LST",)


def test_third_example_registered_and_its_settings_a_pytree(heavy):
    # the registry holds it while this module's tests run (the fixture removes it)
    assert EXAMPLES["test_cruise_heavy"] is heavy
    assert SCENARIOS["test_heavy_lane_change"] is HEAVY_SCENARIO
    assert jax.tree.structure(HeavyCruiseSettings()) != jax.tree.structure(
        HeavyCruiseSettings(horizon=2)
    )
