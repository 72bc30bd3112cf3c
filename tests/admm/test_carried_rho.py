"""rho_method="carried": eq.opt_ro's rho* estimated at a cold start and carried by the
warm start, the same optimum as the per-step estimate, one decision per batch."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(300)


def _problem():
    p = random_problem(3, 2, shared="chain")
    d = p.data()
    # a second step: the model and the state moved (as along a drive)
    d2 = d._replace(x0=d.x0 * 0.8 + 0.05, A=d.A * 0.9)
    return p.topology, d, d2


def test_carried_rho_same_optimum_and_no_new_estimate():
    T, d, d2 = _problem()
    power = LocalExplicit(T, max_iter=5000)
    carried = LocalExplicit(T, max_iter=5000, rho_method="carried", rho_refresh=5000)
    q = power.params(rho=(1.0, 0.3), tol_primal=1e-12, tol_dual=1e-12)
    r0p = jax.jit(power.solve)(d, q)
    r0c = jax.jit(carried.solve)(d, q)
    # cold: the same estimate
    np.testing.assert_allclose(np.asarray(r0c.rho), np.asarray(r0p.rho), rtol=1e-12)
    star0 = np.asarray(r0c.state.rho_star)
    assert np.all(star0 > 0)
    r1p = jax.jit(power.solve)(d2, q, power.shift(r0p.state))
    r1c = jax.jit(carried.solve)(d2, q, carried.shift(r0c.state))
    # warm: the carried rho* (not the new step's estimate), the same optimum
    np.testing.assert_allclose(np.asarray(r1c.rho), star0 * np.array([1.0, 0.3]), rtol=1e-12)
    assert not np.allclose(np.asarray(r1c.rho), np.asarray(r1p.rho), rtol=1e-9)
    assert int(r1c.status) == Status.SOLVED and int(r1p.status) == Status.SOLVED
    np.testing.assert_allclose(np.asarray(r1c.u), np.asarray(r1p.u), atol=1e-3)
    # with the exact finish both are the optimum itself
    fin_p = LocalExplicit(T, max_iter=5000, finish="active_set")
    fin_c = LocalExplicit(T, max_iter=5000, finish="active_set", rho_method="carried")
    f1p = jax.jit(fin_p.solve)(d2, q, fin_p.shift(r0p.state))
    f1c = jax.jit(fin_c.solve)(d2, q, fin_c.shift(r0c.state))
    assert np.all(np.asarray(f1c.dual_residual) == 0)  # a verified finish
    np.testing.assert_allclose(np.asarray(f1c.u), np.asarray(f1p.u), atol=1e-7)


def test_carried_rho_batched_decision_and_refresh():
    """Under vmap, a case that carries none is estimated (as the per-step rule
    does), a case that carries one keeps it; a slow solve passes none on."""
    T, d, d2 = _problem()
    carried = LocalExplicit(T, max_iter=5000, rho_method="carried")
    power = LocalExplicit(T, max_iter=5000)
    q = carried.params(tol_primal=1e-10, tol_dual=1e-10)
    cold = carried.cold_state()
    warm = cold._replace(rho_star=jnp.asarray([2.0, 3.0]))
    states = jax.tree.map(lambda a, b: jnp.stack([a, b]), cold, warm)
    datas = jax.tree.map(lambda a, b: jnp.stack([a, b]), d2, d2)
    res = jax.jit(jax.vmap(carried.solve, in_axes=(0, None, 0)))(datas, q, states)
    est = np.asarray(jax.jit(power.solve)(d2, q).rho)
    np.testing.assert_allclose(np.asarray(res.rho[0]), est, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(res.rho[1]), [2.0, 3.0], rtol=1e-12)
    slow = LocalExplicit(T, max_iter=5000, rho_method="carried", rho_refresh=1)
    r = jax.jit(slow.solve)(d2, q)
    assert int(r.iterations) > 1 and np.all(np.asarray(r.state.rho_star) == 0)


def test_carried_rho_differentiates():
    """solve_fixed with a carried rho*: gradients finite and equal to the given-rho
    solve's at the same rho (the carried value is a constant)."""
    T, d, _ = _problem()
    carried = LocalExplicit(T, rho_method="carried")
    given = LocalExplicit(T, rho_method="given")
    q = carried.params()
    warm = carried.cold_state()._replace(rho_star=jnp.asarray([0.5, 2.0]))

    def loss(solver, x0, p, w):
        return jnp.sum(solver.solve_fixed(d._replace(x0=x0), 20, p, w).u ** 2)

    g_c = jax.grad(lambda x: loss(carried, x, q, warm))(d.x0)
    g_g = jax.grad(lambda x: loss(given, x, q._replace(rho=jnp.asarray([0.5, 2.0])), warm))(d.x0)
    assert np.all(np.isfinite(np.asarray(g_c)))
    np.testing.assert_allclose(np.asarray(g_c), np.asarray(g_g), rtol=1e-8, atol=1e-12)
    g_cold = jax.grad(lambda x: loss(carried, x, q, None))(d.x0)  # estimated: its own derivative
    assert np.all(np.isfinite(np.asarray(g_cold)))
