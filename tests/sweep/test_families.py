"""Scenario families: seeded, reproducible, case by case; a user can add one."""

import jax
import numpy as np
import pytest

from ampc_jax.sweep import FAMILIES, Family, StepCases, family, register_family
from ampc_jax.sweep.families import ENVELOPES

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("name", ["cruise_step", "stability_step", "generated"])
def test_cases_depend_on_seed_and_index_only(name):
    a = family(name).sample(12, seed=5)
    b = family(name).sample(4, seed=5, start=8)
    c = family(name).sample(4, seed=6, start=8)
    for x, y in zip(jax.tree.leaves(a.data), jax.tree.leaves(b.data), strict=True):
        np.testing.assert_array_equal(np.asarray(x)[8:], y)
    assert not np.allclose(np.asarray(a.data.x0)[8:], c.data.x0)
    np.testing.assert_array_equal(b.columns["case"], [8, 9, 10, 11])
    assert all(np.all(np.isfinite(np.asarray(x))) for x in (a.data.A, a.data.B, a.data.x0))


def test_vehicle_draws_lie_in_the_envelope():
    cases = family("stability_step").sample(50, seed=1)
    env = ENVELOPES["stability"]
    for key in ("v_x", "mu", "slip", "driver_torque"):
        lo, hi = env[key]
        v = cases.columns[key]
        assert np.all((v >= lo) & (v <= hi)), key
    assert np.all(np.abs(cases.columns["steer"]) <= 0.5)
    # the model's speed state is the drawn speed (x0 holds the measured state)
    assert cases.topology.horizon == 3
    longer = family("cruise_step").sample(3, seed=1, horizon=6)
    assert longer.topology.horizon == 6 and longer.data.bin.shape[1] == 6


def test_loop_family():
    cases = family("cruise_lane_change").sample(3, seed=2)
    assert cases.scenarios.mu.shape == (3,)
    np.testing.assert_allclose(cases.scenarios.mu, cases.columns["mu"])
    assert cases.n_steps == 320


def test_bad_arguments_and_registration():
    with pytest.raises(ValueError, match="family"):
        family("nope")
    with pytest.raises(ValueError, match="cases"):
        family("generated").sample(0)
    with pytest.raises(ValueError, match="seed"):
        family("generated").sample(2, seed=-1)
    with pytest.raises(ValueError, match="colour"):
        family("generated").sample(2, colour=1)
    base = family("generated")

    def sampler(n, seed, start, **kw):
        c = base.sample(n, seed, start, horizon=4)
        return StepCases(None, c.topology, c.data, c.columns)

    fam = register_family(Family("user_short", "step", "generated, N_p = 4", sampler))
    try:
        assert family("user_short").sample(2).topology.horizon == 4
        with pytest.raises(ValueError, match="already"):
            register_family(fam)
    finally:
        FAMILIES.pop("user_short")
    with pytest.raises(ValueError, match="kind"):
        register_family(Family("x", "other", "", sampler))
