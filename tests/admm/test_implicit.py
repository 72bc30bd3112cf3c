"""Implicit differentiation at the ADMM fixed point (ampc_jax.admm.implicit).

Reference: central differences of the ordinary solve (``solver.solve``, its while
loop) at a tight tolerance, in float64. The parameters: the rho scale of each
objective, the relaxation alpha, a factor on objective 0's output weight Q_0 and
one on the input weights R. The loss is a fixed random weighting of the inputs u.
The converged inputs are the problem's solution, which does not depend on rho or
alpha: their derivative is zero, checked against the differences on the scale of
the whole gradient; Q and R's derivatives are checked entry by entry.
"""

from functools import cache

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from ampc_jax.admm.implicit import run_implicit, solve_implicit
from ampc_jax.formulations import FullyDistributed, LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(300)

TOL = 1e-24  # eq.Convergence on squared norms: residual norms ~1e-12
STEP = 1e-5  # central-difference step on every parameter
RTOL = 1e-5  # the implicit gradient's accuracy target (docs/tuning.md)

# (log rho scale per objective, relaxation, factor on Q_0, factor on R); alpha 1.3
THETA = (jnp.zeros(2), jnp.asarray(1.3), jnp.asarray(1.0), jnp.asarray(1.0))


@cache
def case(kind: str, anderson: int):
    """The problem, the solver and its loss of theta (implicit and ordinary)."""
    p = random_problem(1, 2, shared="all", horizon=4)
    d = p.data()
    cls = {"local_explicit": LocalExplicit, "fully_distributed": FullyDistributed}[kind]
    # the ordinary solve without Local Explicit's exact finish: the program
    # solve_implicit runs forward (the finish is forward only)
    plain = {"finish": "none"} if kind == "local_explicit" else {}
    solver = cls(p.topology, max_iter=20000, anderson=anderson, **plain)
    w = jnp.asarray(np.random.default_rng(0).standard_normal(d.lb.shape))

    def inputs(theta):
        log_rho, alpha, q, r = theta
        data = d._replace(Q=(d.Q[0] * q, *d.Q[1:]), R=d.R * r)
        params = solver.params(tol_primal=TOL, tol_dual=TOL)._replace(
            rho=jnp.exp(log_rho), relaxation=alpha
        )
        return data, params

    def implicit_loss(theta):
        res = solve_implicit(solver, *inputs(theta))
        return jnp.sum(w * res.u), res

    def loss(theta):
        res = solver.solve(*inputs(theta))
        return jnp.sum(w * res.u), res

    flat, unravel = ravel_pytree(THETA)
    grad = jax.jit(jax.value_and_grad(implicit_loss, has_aux=True))
    batch = jax.jit(jax.vmap(lambda x: loss(unravel(x))))
    return solver, inputs, grad, batch, flat, w


@cache
def central_differences(kind: str, anderson: int):
    """The ordinary solve at theta and at theta +- STEP e_i (one batched program)."""
    *_, batch, flat, _ = case(kind, anderson)
    E = np.eye(flat.size) * STEP
    points = jnp.concatenate([flat[None], flat + E, flat - E])
    values, results = batch(points)
    v = np.asarray(values)
    n = flat.size
    return (v[1 : n + 1] - v[n + 1 :]) / (2 * STEP), results


def check_gradient(kind: str, anderson: int):
    _, _, grad, _, flat, _ = case(kind, anderson)
    (_, res), g = grad(THETA)
    assert int(res.status) == Status.SOLVED and bool(res.converged), res.status
    gi = np.asarray(ravel_pytree(g)[0])
    fd, _ = central_differences(kind, anderson)
    scale = np.max(np.abs(fd))
    assert scale > 1e-2, fd  # the loss does move with the weights
    # rho scales and alpha (entries 0..2): the solution does not depend on them
    np.testing.assert_array_less(np.abs(gi[:3]), 1e-8 * scale)
    np.testing.assert_array_less(np.abs(gi[:3] - fd[:3]), RTOL * scale)
    # Q_0 and R factors (entries 3, 4): each within RTOL of its own difference
    np.testing.assert_allclose(gi[3:], fd[3:], rtol=RTOL, atol=0)
    return gi, fd


@pytest.mark.parametrize("anderson", [0, 3])
def test_local_explicit_gradient_matches_central_differences(anderson):
    check_gradient("local_explicit", anderson)


@pytest.mark.slow  # the consensus formulations share the adjoint code; Local Explicit's run by default
def test_fully_distributed_gradient_matches_central_differences():
    check_gradient("fully_distributed", 0)


@pytest.mark.parametrize("anderson", [pytest.param(0, marks=pytest.mark.slow), 3])
def test_forward_value_is_the_ordinary_solve(anderson):
    solver, inputs, grad, _, _, w = case("local_explicit", anderson)
    data, params = inputs(THETA)
    params = params._replace(
        tol_primal=params.tol_primal * 0 + 1e-14, tol_dual=params.tol_dual * 0 + 1e-14
    )
    imp = jax.jit(lambda d, p: solve_implicit(solver, d, p))(data, params)
    plain = jax.jit(solver.solve)(data, params)
    assert int(imp.status) == int(plain.status) == Status.SOLVED
    assert int(imp.iterations) == int(plain.iterations) > 10
    np.testing.assert_array_equal(imp.u, plain.u)
    np.testing.assert_array_equal(imp.stats.gap, plain.stats.gap)
    # and the value of the gradient program, at the round-off tolerance TOL, where
    # the last iteration may fall either side of the stopping test between programs
    (value, res), _ = grad(THETA)
    _, ref = central_differences("local_explicit", anderson)
    assert abs(int(res.iterations) - int(ref.iterations[0])) <= 1
    np.testing.assert_allclose(res.u, ref.u[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(value, jnp.sum(w * ref.u[0]), rtol=1e-12)


def test_the_finish_is_forward_only():
    """A solver with the exact finish (the default) differentiates as its plain
    iteration: solve_implicit runs no finish, so its result and gradient are those
    of finish="none", and the finished solve reaches the same inputs."""
    solver, inputs, grad, _, _, _ = case("local_explicit", 0)
    data, params = inputs(THETA)
    fin = LocalExplicit(solver.topology, max_iter=20000)
    assert fin.finish == "active_set"
    imp = jax.jit(lambda d, p: solve_implicit(fin, d, p))(data, params)
    ref = jax.jit(lambda d, p: solve_implicit(solver, d, p))(data, params)
    np.testing.assert_array_equal(imp.u, ref.u)
    assert int(imp.iterations) == int(ref.iterations)
    done = jax.jit(fin.solve)(data, params)
    np.testing.assert_allclose(done.u, ref.u, rtol=0, atol=1e-8)
    w = jnp.asarray(np.random.default_rng(1).standard_normal(data.lb.shape))

    def loss(s, R):
        return jnp.sum(w * solve_implicit(s, data._replace(R=R), params).u)

    g_fin = jax.jit(jax.grad(lambda R: loss(fin, R)))(data.R)
    g_ref = jax.jit(jax.grad(lambda R: loss(solver, R)))(data.R)
    np.testing.assert_array_equal(np.asarray(g_fin), np.asarray(g_ref))


@pytest.mark.slow  # depends on Anderson's behaviour at round-off: a demonstration, not a rule
def test_unrolled_through_converged_anderson_is_off_where_implicit_is_not():
    """The defect the implicit derivative fixes: reverse mode through 300 unrolled
    Anderson iterations (converged to round-off after ~150) differs from central
    differences of the converged solve by percents; the implicit one by < RTOL."""
    solver, inputs, _, _, flat, w = case("local_explicit", 3)

    def unrolled(theta):
        data, params = inputs(theta)
        return jnp.sum(w * solver.solve_fixed(data, 300, params).u)

    gu = np.asarray(ravel_pytree(jax.jit(jax.grad(unrolled))(THETA))[0])
    gi, fd = check_gradient("local_explicit", 3)
    scale = np.max(np.abs(fd))
    assert np.max(np.abs(gu - fd)) > 1e-3 * scale, (gu, fd)
    assert np.max(np.abs(gi - fd)) < RTOL * scale, (gi, fd)


def test_run_implicit_gives_the_start_no_gradient():
    solver, inputs, *_ = case("local_explicit", 0)
    data, params = inputs(THETA)
    setup = solver.setup(data, params)

    def f(start_Z):
        start = solver.init(setup)._replace(Z=start_Z)
        return jnp.sum(run_implicit(solver, setup, start).Z)

    g = jax.jit(jax.grad(f))(jnp.ones_like(solver.init(setup).Z))
    assert np.all(np.asarray(g) == 0.0)


def test_bad_input_is_named():
    solver, inputs, *_ = case("local_explicit", 0)
    data, params = inputs(THETA)
    with pytest.raises(TypeError, match="solver: expected an ADMMSolver"):
        solve_implicit("local_explicit", data, params)
    with pytest.raises(TypeError, match="data: expected a ProblemData"):
        solve_implicit(solver, {"A": data.A}, params)
    for bad in (0.0, -1e-6, float("nan"), float("inf"), "tight", True):
        with pytest.raises(ValueError, match="adjoint_tol: expected a positive finite number"):
            solve_implicit(solver, data, params, adjoint_tol=bad)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="adjoint_max_iter: expected an integer >= 1"):
            solve_implicit(solver, data, params, adjoint_max_iter=bad)
