"""Gradient tuning of the solver (ampc_jax.tuning.solver)."""

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import PAPER_ITERATION, formulation
from ampc_jax.sweep import family
from ampc_jax.tuning.solver import (
    Theta,
    reference_inputs,
    theta_of,
    tune_solver,
    unpack,
    unrolled_loss,
)

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def batch():
    cases = family("cruise_step").sample(2, seed=0, dtype=jnp.float64)
    solver = formulation("local_explicit", cases.topology, **PAPER_ITERATION)
    u_star = jnp.asarray(reference_inputs(cases.topology, cases.data))
    return solver, cases, u_star


@pytest.mark.timeout(60)
def test_parametrisation_round_trips():
    th = theta_of((0.5, 2.0), 1.6, 2, jnp.float64)
    rho, alpha = unpack(th)
    np.testing.assert_allclose(np.asarray(rho), [0.5, 2.0], rtol=1e-12)
    assert abs(float(alpha) - 1.6) < 1e-12
    rho, alpha = unpack(Theta(jnp.zeros(2), jnp.asarray(50.0)))
    assert float(alpha) <= 2.0 and np.all(np.asarray(rho) == 1.0)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("loss", ["error", "residual"])
def test_unrolled_gradient_matches_central_differences(batch, loss):
    solver, cases, u_star = batch
    K, s = 6, float(cases.topology.horizon * cases.topology.n_u)
    th0 = theta_of((0.7, 1.3), 1.2, 2, jnp.float64)

    def f(th):
        return unrolled_loss(solver, th, cases.data, u_star, K, s, loss)

    fj = jax.jit(f)
    g = jax.jit(jax.grad(f))(th0)
    flat0, unravel = jax.flatten_util.ravel_pytree(th0)
    gflat = np.asarray(jax.flatten_util.ravel_pytree(g)[0])
    assert gflat.shape == (3,)  # log rho of each objective, the relaxation logit
    h = 1e-5  # central differences: truncation ~h^2, round-off ~1e-16 / h
    for k in range(3):
        e = jnp.zeros_like(flat0).at[k].set(h)
        fd = (float(fj(unravel(flat0 + e))) - float(fj(unravel(flat0 - e)))) / (2 * h)
        assert abs(gflat[k] - fd) <= 1e-4 * max(abs(fd), 1e-8), (k, gflat[k], fd)
        assert abs(fd) > 0  # each parameter moves the loss


@pytest.mark.timeout(60)
def test_short_tuning_lowers_the_loss():
    res = tune_solver(
        "cruise_step", cases=4, steps=12, iterations=6, lr=0.1, evaluate=False, progress=False
    )
    losses = [h["loss"] for h in res.history]
    assert len(losses) == 13 and min(losses[1:]) < losses[0]
    assert len(res.rho_scale) == 2 and 0 < res.relaxation < 2
    assert res.settings["example"] == "cruise" and res.evaluation == {}


@pytest.mark.timeout(60)
def test_evaluation_table_rows():
    from ampc_jax.tuning.solver import evaluation_table

    res = tune_solver(
        "cruise_step", cases=2, steps=2, iterations=4, heldout_cases=4, progress=False
    )
    (ev,) = res.evaluation.values()
    names = [r["name"] for r in ev["rows"]]
    assert names == ["eq.opt_ro", "grid best", "example defaults", "tuned"]
    assert len(ev["grid"]) == 13
    for r in ev["rows"]:
        assert r["converged"] == 1.0 and r["median"] > 0 and r["u0_rel_error"] < 0.05
    assert "grid best" in evaluation_table(res.evaluation)
