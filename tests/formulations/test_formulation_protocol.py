"""ampc_jax.formulations: every formulation follows one protocol and runs under
jit, vmap (over data and parameters) and grad; names are resolved with errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm import ADMMSolver
from ampc_jax.formulations import FORMULATIONS, Formulation, formulation
from ampc_jax.generate import random_problem
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(180)


@pytest.mark.parametrize("name", sorted(FORMULATIONS))
def test_every_formulation_under_jit_vmap_and_grad(name):
    problems = [random_problem(s, 2, shared="all") for s in range(3)]
    T = problems[0].topology
    f = formulation(name, T, max_iter=20000)
    assert isinstance(f, Formulation) and isinstance(f, ADMMSolver)
    q = f.params(tol_primal=1e-12, tol_dual=1e-12)
    data = jax.tree.map(lambda *x: jnp.stack(x), *[p.data() for p in problems])
    out = jax.jit(jax.vmap(f.solve, in_axes=(0, None)))(data, q)
    assert np.all(np.asarray(out.status) == Status.SOLVED)
    for b, p in enumerate(problems):
        ref = solve_reference(T, p.data()).u[0]
        np.testing.assert_allclose(out.u0[b], ref, rtol=1e-3, atol=1e-5)
    # warm start: cold state, one shifted step, the same shapes back
    cold = f.cold_state()
    again = jax.jit(f.solve)(problems[0].data(), q, f.shift(cold))
    assert jax.tree.structure(again.state) == jax.tree.structure(cold)
    # grad with respect to the parameters through the fixed-iteration runner (inputs
    # inside their bounds: at a bound the projection's derivative is zero)
    d = random_problem(7, 2, shared="all", reference_scale=0.5).data()
    g = jax.jit(jax.grad(lambda r: jnp.sum(f.solve_fixed(d, 20, r).u0 ** 2)))(q)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(g))
    assert float(jnp.max(jnp.abs(g.rho))) > 0


def test_names_are_resolved_with_a_clear_error():
    T = random_problem(0, 2).topology
    with pytest.raises(ValueError, match="formulation: expected one of"):
        formulation("admm", T)
    assert type(formulation("fully_distributed", T)).__name__ == "FullyDistributed"
    assert type(formulation("virtual_center", T)).__name__ == "VirtualCenter"
    with pytest.raises(ValueError, match="inner_iterations: expected an integer >= 1"):
        formulation("fully_distributed", T, inner_iterations=0)


@pytest.mark.parametrize("name", sorted(FORMULATIONS))
def test_a_non_finite_problem_gives_status_numerical_error_and_no_nan(name):
    p = random_problem(0, 2, shared="chain")
    f = formulation(name, p.topology, max_iter=50)
    bad = p.data()._replace(x0=p.data().x0.at[0].set(jnp.nan))
    res = jax.jit(f.solve)(bad, f.params())
    assert int(res.status) == Status.NUMERICAL_ERROR and not bool(res.converged)
    assert np.all(np.isfinite(np.asarray(res.u)))
