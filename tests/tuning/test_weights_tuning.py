"""Weight tuning through the differentiable closed loop (fixed ADMM iterations)."""

from __future__ import annotations

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.closed_loop import SimConfig, controller_for, simulator_for
from ampc_jax.closed_loop.controller import Controller
from ampc_jax.sweep.families import family
from ampc_jax.tuning.weights import (
    LossOptions,
    log_weights,
    loop_loss,
    tune_weights,
    weight_fields,
)

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def cases():
    return family("cruise_lane_change").sample(2, seed=0)


@pytest.mark.timeout(40)
@pytest.mark.parametrize("bad", [0, -3, 2.5, True, "10"])
def test_fixed_iterations_is_validated(bad):
    with pytest.raises(ValueError, match="fixed_iterations"):
        SimConfig(fixed_iterations=bad)
    ex = SimConfig().vehicle_example
    with pytest.raises(ValueError, match="fixed_iterations"):
        Controller(ex, ("LST",), 2, fixed_iterations=bad)


@pytest.mark.timeout(40)
def test_fixed_iterations_default_and_pass_through():
    assert SimConfig().fixed_iterations is None
    assert controller_for(SimConfig()).fixed_iterations is None
    assert controller_for(SimConfig(fixed_iterations=np.int64(7))).fixed_iterations == 7


@pytest.mark.timeout(240)  # compiles the loop and its gradient: ~55 s on a loaded 2-core machine
def test_closed_loop_gradient_matches_central_differences(cases):
    """d L / d log w over a 20-step run with K = 3 against central differences."""
    cfg = replace(cases.config, fixed_iterations=3, shadow=False)
    sim, params = simulator_for(cfg), cfg.loop_params(jnp.float64)
    fields = weight_fields(cfg.settings)
    sc = jax.tree.map(lambda x: jnp.asarray(x, jnp.float64)[:1], cases.scenarios)
    opts = LossOptions((5, 20), slip_limit=0.005, slip_temperature=0.002)
    theta = log_weights(cfg.settings, fields, jnp.float64)

    def f(th):
        return loop_loss(th, sim, params, sc, 20, fields, opts)[0]

    fj = jax.jit(f)
    g = np.asarray(jax.jit(jax.grad(f))(theta))
    h = 1e-4
    fd = np.array(
        [
            (float(fj(theta.at[k].add(h))) - float(fj(theta.at[k].add(-h)))) / (2 * h)
            for k in range(len(fields))
        ]
    )
    scale = np.max(np.abs(fd))
    assert scale > 0
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-4 * scale)


@pytest.mark.timeout(40)
@pytest.mark.slow  # 18 s, mostly compiling; the gradient test covers the loop
def test_three_tuning_steps_lower_the_loss(cases):
    res = tune_weights(
        cases.config,
        cases,
        steps=3,
        iterations=3,
        lr=0.05,
        duration=1.0,
        focus=(0.5, 1.0),
        progress=False,
        evaluate=False,
    )
    losses = [h["loss"] for h in res.history]
    assert len(losses) == 4 and np.all(np.isfinite(losses))
    assert losses[-1] < losses[0]
    assert set(res.settings) == set(weight_fields(cases.config.settings))
    assert all(v > 0 for v in res.settings.values())


@pytest.mark.timeout(40)
def test_tune_weights_rejects_bad_arguments(cases):
    with pytest.raises(ValueError, match="steps"):
        tune_weights(cases.config, cases, steps=0, iterations=3)
    with pytest.raises(ValueError, match="fields"):
        tune_weights(cases.config, cases, steps=1, iterations=3, fields=("q_nope",))
    with pytest.raises(ValueError, match="train_cases"):
        tune_weights(cases.config, cases, steps=1, iterations=3, train_cases=5)
