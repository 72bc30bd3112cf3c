"""Tests of ampc_jax.closed_loop.config: SimConfig's validation, the examples'
solver defaults, and the split into a static Simulator and LoopParams."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.closed_loop import (
    ControllerParams,
    LoopParams,
    SimConfig,
    baseline_config,
    config_for,
    controller_for,
    simulator_for,
    with_settings,
)
from ampc_jax.formulations import IntegratedADMM, LocalExplicit
from ampc_jax.vehicle import CRUISE, STABILITY, CruiseSettings, StabilitySettings

pytestmark = pytest.mark.timeout(60)


# --------------------------------------------------------------------------- --disable
def test_disable_builds_reduced_topology():
    c = controller_for(SimConfig("cruise", disabled=("YRT",)))
    T, agents, objs = c.topology, c.agent_indices, c.objective_indices
    assert T.agent_names == ("DTR", "FDB") and agents == (0, 2)
    assert T.objective_names == ("LST",) and T.groups == ((0, 1),) and objs == (0,)
    np.testing.assert_array_equal(c.input_columns, [0, 2, 3])
    c = controller_for(SimConfig("stability", disabled=("VSC",)))
    assert c.topology.agent_names == ("TCR", "RTV") and c.topology.objective_names == ("WSC",)
    assert c.objective_indices == (1,)
    np.testing.assert_array_equal(c.input_columns, [0, 1])
    T = controller_for(config_for("stability_dlc")).topology
    assert T.agent_names == ("TCR", "RTV", "FDB") and T.groups == ((1, 2), (0, 1))
    with pytest.raises(
        ValueError, match=r"^disable: 'VSC' is not an objective of the cruise example"
    ):
        SimConfig("cruise", disabled=("VSC",))
    with pytest.raises(
        ValueError, match=r"^disable: every objective is disabled; use formulation 'none'"
    ):
        SimConfig("cruise", disabled=("LST", "YRT"))
    # with no MPC nothing is solved: no controller, and disabling every objective is allowed
    none = SimConfig("cruise", disabled=("LST", "YRT"), formulation="none")
    assert controller_for(none) is None and simulator_for(none).controller is None


# --------------------------------------------------------------------------- solver options
@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"rho_scale": (1.0, 2.0, 3.0)}, "rho_scale"),
        ({"rho_scale": ()}, "rho_scale"),
        ({"rho_scale": -1.0}, "rho_scale"),
        ({"rho_scale": (1.0, float("nan"))}, "rho_scale"),
        ({"rho_scale": "fast"}, "rho_scale"),
        ({"relaxation": 2.0}, "relaxation"),
        ({"relaxation": 0.0}, "relaxation"),
        ({"relaxation": "1.5"}, "relaxation"),
        ({"integrated_rho_scale": 0.0}, "integrated_rho_scale"),
        ({"integrated_rho_scale": (1.0, 1.0)}, "integrated_rho_scale"),
        ({"shadow_rho_scale": float("inf")}, "shadow_rho_scale"),
        ({"shadow_relaxation": 2.5}, "shadow_relaxation"),
        ({"warm_shift": 2}, "warm_shift"),
        ({"warm_shift": True}, "warm_shift"),
        ({"anderson": 4}, "anderson"),
        ({"anderson": -1}, "anderson"),
        ({"anderson": 2.0}, "anderson"),
    ],
)
def test_solver_options_are_validated(kw, field):
    with pytest.raises(ValueError, match=rf"^{field}: "):
        SimConfig("cruise", **kw)


@pytest.mark.parametrize(
    ("name", "ex"), [("cruise_lane_change", CRUISE), ("stability_dlc", STABILITY)]
)
def test_solver_options_defaults_and_pass_through(name, ex):
    """The example's tuned defaults fill the config; the static options reach the
    solvers, the numbers reach LoopParams (controller, integrated controller, shadow)."""
    d = ex.solver_defaults
    c = config_for(name)
    assert c.rho_scale == tuple(d["rho_scale"]) and c.relaxation == d["relaxation"]
    assert c.integrated_rho_scale == d["integrated_rho_scale"]
    assert c.warm_shift == d["warm_shift"] and c.anderson == d["anderson"]
    assert hash(c) == hash(config_for(name))  # still hashable (static)
    sim = simulator_for(c)
    assert sim == simulator_for(config_for(name)) and hash(sim) == hash(
        simulator_for(config_for(name))
    )
    le = sim.controller.solver
    assert isinstance(le, LocalExplicit)
    assert (le.anderson, le.max_iter) == (c.anderson, c.max_iter)
    assert sim.controller.warm_shift == sim.shadow.warm_shift == c.warm_shift
    p = c.loop_params()
    np.testing.assert_array_equal(p.controller.solver.rho, c.rho_scale)
    assert float(p.controller.solver.relaxation) == c.relaxation
    assert (float(p.controller.solver.tol_primal), float(p.controller.solver.tol_dual)) == (
        c.tol_primal,
        c.tol_dual,
    )
    # the integrated controller: its own rho factor, the same relaxation and tolerances
    ci = config_for(name, formulation="integrated")
    ia = simulator_for(ci).controller.solver
    assert isinstance(ia, IntegratedADMM)
    assert ia.anderson == ia.merged.anderson == c.anderson
    pi = ci.loop_params().controller.solver
    np.testing.assert_array_equal(pi.rho, [c.integrated_rho_scale])
    assert float(pi.relaxation) == c.relaxation
    assert (float(pi.tol_primal), float(pi.tol_dual)) == (c.tol_primal, c.tol_dual)
    # the shadow stays plain ADMM at its own rho factor and relaxation
    sh = sim.shadow
    assert sh.solver.anderson == 0 and sh.max_iter == c.shadow_max_iter == 5000
    np.testing.assert_array_equal(p.shadow.rho, [c.shadow_rho_scale])
    assert float(p.shadow.relaxation) == c.shadow_relaxation == d["shadow_relaxation"]
    assert float(p.shadow.tol_primal) == float(p.shadow.tol_dual) == 1e-8


def test_disabled_objectives_keep_the_enabled_factors():
    # --disable keeps the enabled objectives' factors
    lst = config_for("cruise_lane_change", disabled=("YRT",), rho_scale=(0.7, 0.3))
    assert lst.enabled_rho_scale == 0.7
    np.testing.assert_array_equal(lst.loop_params().controller.solver.rho, [0.7])
    assert controller_for(lst).solver.n_rho == 1
    wsc = config_for("stability_dlc", disabled=("VSC",), rho_scale=(0.7, 0.3))
    assert wsc.enabled_rho_scale == 0.3
    np.testing.assert_array_equal(wsc.loop_params().controller.solver.rho, [0.3])
    # one float applies to every objective; the paper's solver is rho* and alpha = 1
    one = SimConfig("stability", rho_scale=2, relaxation=1)
    assert one.rho_scale == 2.0 and one.enabled_rho_scale == 2.0
    assert isinstance(one.relaxation, float)
    np.testing.assert_array_equal(one.loop_params().controller.solver.rho, [2.0, 2.0])


# --------------------------------------------------------------------------- the split
def test_simulator_is_static_and_loop_params_carry_the_numbers():
    """What a compiled loop is specialised on (Simulator) does not change with the
    rho scales, relaxation, tolerances, weights or bounds; the horizon does."""
    base = config_for("cruise_lane_change", shadow=False)
    sim = simulator_for(base)
    for kw in (
        {"rho_scale": (0.3, 3.0)},
        {"relaxation": 1.1},
        {"tol_primal": 1e-3, "tol_dual": 1e-2},
        {"integrated_rho_scale": 2.0},
    ):
        other = config_for("cruise_lane_change", shadow=False, **kw)
        assert other != base
        assert simulator_for(other) == sim and hash(simulator_for(other)) == hash(sim), kw
        assert jax.tree.structure(other.loop_params()) == jax.tree.structure(base.loop_params())
    weights = with_settings(base, q_yrt=2.0e3, dtr_max=1500.0)
    assert simulator_for(weights) == sim
    assert jax.tree.structure(weights.loop_params()) == jax.tree.structure(base.loop_params())
    assert float(weights.loop_params().controller.settings.q_yrt) == 2.0e3
    longer = with_settings(base, horizon=3)
    assert simulator_for(longer) != sim and simulator_for(longer).controller.horizon == 3
    # static options change the Simulator
    for kw in ({"max_iter": 50}, {"anderson": 1}, {"warm_shift": 0}, {"warm_start": False}):
        assert simulator_for(config_for("cruise_lane_change", shadow=False, **kw)) != sim, kw
    assert simulator_for(config_for("cruise_lane_change")) != sim  # the shadow on


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_loop_params_dtype_and_shadow_floor(dtype):
    c = config_for("stability_launch_brake")
    p = c.loop_params(dtype)
    assert isinstance(p, LoopParams) and isinstance(p.controller, ControllerParams)
    assert isinstance(p.controller.settings, StabilitySettings)
    assert p.controller.settings.horizon == c.horizon == 3
    for leaf in jax.tree.leaves(p):
        assert leaf.dtype == dtype, leaf
    # the shadow's tolerances are floored at 1e-4 Nm^2 in float32 (its resolution)
    expect = 1e-4 if dtype == jnp.float32 else 1e-8
    assert float(p.shadow.tol_primal) == pytest.approx(expect, rel=1e-6)
    assert float(p.shadow.tol_dual) == pytest.approx(expect, rel=1e-6)
    assert float(p.controller.solver.tol_primal) == 1.0


# --------------------------------------------------------------------------- input validation
@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"tol_primal": -1.0}, "tol_primal"),
        ({"tol_primal": 0.0}, "tol_primal"),
        ({"tol_dual": float("nan")}, "tol_dual"),
        ({"shadow_tol_primal": float("inf")}, "shadow_tol_primal"),
        ({"max_iter": 0}, "max_iter"),
        ({"max_iter": 10.0}, "max_iter"),
        ({"max_iter": True}, "max_iter"),
        ({"shadow_max_iter": -5}, "shadow_max_iter"),
        ({"warm_start": "yes"}, "warm_start"),
        ({"formulation": "admm"}, "formulation"),
        ({"settings": StabilitySettings()}, "settings"),
        ({"settings": CruiseSettings(q_yrt=-5.0)}, "q_yrt"),
        ({"settings": CruiseSettings(horizon=0)}, "horizon"),
        ({"settings": CruiseSettings(dt=0.0)}, "dt"),
    ],
)
def test_config_fields_are_validated(kw, field):
    with pytest.raises(ValueError, match=rf"^{field}: "):
        SimConfig("cruise", **kw)


def test_with_settings_is_validated_and_numbers_canonical():
    with pytest.raises(ValueError, match=r"^r_rtv: expected a weight > 0"):
        with_settings(config_for("cruise_lane_change"), r_rtv=0.0)
    c = SimConfig("cruise", tol_primal=1, max_iter=np.int64(5))
    assert isinstance(c.tol_primal, float) and type(c.max_iter) is int
    assert hash(c) == hash(SimConfig("cruise", tol_primal=1.0, max_iter=5))


def test_settings_replace_is_checked_by_simconfig_and_with_settings_works():
    """``settings.replace`` validates nothing itself; SimConfig does (naming the field)."""
    bad = CruiseSettings().replace(q_yrt=-5.0)  # no error here
    with pytest.raises(ValueError, match=r"^q_yrt: expected a weight >= 0"):
        SimConfig("cruise", settings=bad)
    with pytest.raises(ValueError, match=r"^horizon: "):
        SimConfig("cruise", settings=CruiseSettings().replace(horizon=0))
    base = config_for("cruise_lane_change", relaxation=1.2)
    c = with_settings(base, q_yrt=2000.0, horizon=3)
    assert c.settings == CruiseSettings(q_yrt=2000.0, horizon=3)
    assert c.horizon == 3 and controller_for(c).topology.horizon == 3
    assert c.relaxation == 1.2 and c.rho_scale == base.rho_scale  # the rest kept
    assert float(c.loop_params().controller.settings.q_yrt) == 2000.0
    assert base.settings == CruiseSettings()  # a copy, not an edit
    with pytest.raises(TypeError, match=r"unknown field\(s\) \['q_vsc'\]"):
        with_settings(base, q_vsc=1.0)


def test_tuned_settings_are_the_defaults():
    """One source of truth: the scenarios run the examples' default settings."""
    assert CruiseSettings().horizon == 2 and CruiseSettings().q_yrt == 1.0e4
    assert StabilitySettings().horizon == 3
    assert config_for("cruise_lane_change").settings == CruiseSettings()
    assert config_for("stability_launch_brake").settings == StabilitySettings()
    assert config_for("stability_dlc").settings == StabilitySettings()


# --------------------------------------------------------------------------- baseline
def test_baseline_is_the_papers_comparison():
    """--compare's baseline: LST alone for cruise control (same solver settings),
    the driver alone for stability control; a run that is the baseline is refused."""
    cruise = config_for("cruise_lane_change", relaxation=1.2)
    base = baseline_config(cruise)
    assert base.enabled == ("LST",) and base.formulation == "local_explicit"
    assert base.relaxation == 1.2 and base.rho_scale == cruise.rho_scale
    stab = baseline_config(config_for("stability_dlc", disabled=("WSC",)))
    assert stab.formulation == "none"
    with pytest.raises(ValueError, match=r"^compare: this run already is .* \(LST alone\)"):
        baseline_config(base)
    with pytest.raises(ValueError, match=r"the driver alone"):
        baseline_config(stab)
    # cruise control without the MPC has nothing to compare LST alone with
    none = config_for("cruise_lane_change", formulation="none")
    with pytest.raises(
        ValueError, match=r"^compare: this run has no MPC \(no MPC \(driver PI\)\): no baseline"
    ):
        baseline_config(none)


# --------------------------------------------------------------------------- builders
def test_builders_sit_beside_what_they_build():
    """controller_for, shadow_for and simulator_for build from the pure-data
    config; SimConfig's former builder methods give the same objects."""
    from ampc_jax.closed_loop import controller_for, shadow_for, simulator_for

    c = config_for("cruise_lane_change")
    ctrl = controller_for(c)
    assert ctrl == controller_for(c) and ctrl.horizon == c.horizon
    sim = simulator_for(c)
    assert sim == simulator_for(c) and sim.controller == ctrl
    assert sim.shadow == shadow_for(c, ctrl.topology) and sim.shadow.max_iter == c.shadow_max_iter
    quiet = config_for("cruise_lane_change", shadow=False)
    assert shadow_for(quiet, ctrl.topology) is None and simulator_for(quiet).shadow is None
    none = SimConfig("cruise", formulation="none")
    assert controller_for(none) is None and simulator_for(none).controller is None
