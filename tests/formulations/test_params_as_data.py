"""Solver parameters as data (issue "One house for the next jobs"): one compiled
step serves every rho scale, relaxation and tolerance (absolute and relative); it vmaps over parameter
points and scenarios together; and jax.grad with respect to the SolverParams
pytree through the fixed-iteration runner matches central finite differences,
for Local Explicit and IntegratedADMM alike."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm import SolverParams
from ampc_jax.formulations import FORMULATIONS, PAPER_ITERATION, IntegratedADMM, LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(240)

# five points that differ in every tunable: rho scale per objective, relaxation,
# absolute and relative tolerances
POINTS = [
    ((1.0, 1.0), 1.0, 1e-8, 0.0),
    ((0.3, 2.0), 1.5, 1e-8, 1e-4),
    ((2.0, 0.5), 1.2, 1e-6, 0.0),
    ((1.0, 0.1), 1.7, 1e-9, 1e-6),
    ((5.0, 5.0), 0.8, 1e-7, 0.0),
]


def _params(solver, rho, relaxation, tol, rel=0.0):
    r = rho if solver.n_rho == 2 else rho[0]
    return solver.params(rho=r, relaxation=relaxation, tol_primal=tol, tol_dual=tol, tol_rel=rel)


# the integrated MPC runs the same runners (admm/core.py), written once; its variant
# compiles three more programs and runs under -m slow
@pytest.mark.parametrize(
    "kind", [LocalExplicit, pytest.param(IntegratedADMM, marks=pytest.mark.slow)]
)
def test_one_compiled_step_serves_five_parameter_points(kind):
    p = random_problem(2, 2, shared="all")
    d = p.data()
    # the paper's iteration: its iteration count moves with rho and relaxation,
    # which shows the points differ (an exact finish stops them all alike)
    solver = kind(p.topology, max_iter=5000, **PAPER_ITERATION)
    traces = []

    def step(data, params):
        traces.append(1)  # runs once per trace (compilation), not per call
        return solver.solve(data, params)

    shared = jax.jit(step)
    results = [shared(d, _params(solver, *pt)) for pt in POINTS]
    assert len(traces) == 1 and shared._cache_size() == 1
    its = [int(r.iterations) for r in results]
    assert len(set(its)) >= 3, its  # the points really differ: this is no constant
    # two points compiled on their own, their numbers as constants: each such
    # program is a compile of its own, and two already show the shared program's
    # results are not its constants' (the other three add compiles, not a check)
    alone_points = POINTS[1:3]
    for pt, r in zip(POINTS, results, strict=True):
        if pt not in alone_points:
            continue
        q = _params(solver, *pt)
        alone = jax.jit(lambda data, q=q: solver.solve(data, q))(d)  # q a compile-time constant
        assert int(alone.iterations) == int(r.iterations), pt
        assert int(alone.status) == int(r.status) == Status.SOLVED, pt
        np.testing.assert_allclose(alone.u, r.u, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(alone.rho, r.rho, rtol=1e-14)


def test_vmap_over_parameter_points_and_scenarios_together():
    problems = [random_problem(s, 2, shared="all") for s in range(3)]
    solver = LocalExplicit(problems[0].topology, max_iter=5000)
    data = jax.tree.map(lambda *x: jnp.stack(x), *[p.data() for p in problems])
    points = [_params(solver, *pt) for pt in POINTS]
    grid = jax.tree.map(lambda *x: jnp.stack(x), *points)
    # cases x points in one program: vmap over points inside vmap over cases
    f = jax.jit(jax.vmap(jax.vmap(solver.solve, in_axes=(None, 0)), in_axes=(0, None)))
    out = f(data, grid)
    assert out.u.shape == (3, len(POINTS), *problems[0].data().lb.shape)
    for c in (0, 2):
        for k in (1, 3):
            one = jax.jit(solver.solve)(problems[c].data(), _params(solver, *POINTS[k]))
            assert int(out.iterations[c, k]) == int(one.iterations)
            np.testing.assert_allclose(out.u[c, k], one.u, rtol=1e-9, atol=1e-9)


def _loss(solver, d, iterations):
    target = 0.3 * jnp.ones_like(d.lb[0])

    def loss(params):
        r = solver.solve_fixed(d, iterations, params)
        return jnp.sum((r.u0 - target) ** 2)

    return loss


@pytest.mark.parametrize("kind", sorted(FORMULATIONS))
def test_grad_wrt_parameters_matches_central_differences(kind):
    """d loss / d (rho, relaxation) through solve_fixed's scan, reverse mode,
    against central differences, 1e-5 relative (float64). The tolerances only
    decide convergence, which the fixed runner ignores: their gradient is zero."""
    p = random_problem(7, 2, shared="all", reference_scale=0.5)
    d = p.data()
    solver = FORMULATIONS[kind](p.topology)
    params = _params(solver, (1.5, 0.7), 1.3, 1e-6)
    loss = jax.jit(_loss(solver, d, 40))
    g = jax.jit(jax.grad(_loss(solver, d, 40)))(params)
    assert isinstance(g, SolverParams)
    h = 1e-6
    for field in ("rho", "relaxation"):
        value = getattr(params, field)
        for k in range(value.size):
            e = jnp.zeros_like(value).reshape(-1).at[k].set(1.0).reshape(value.shape)
            up = loss(params._replace(**{field: value + h * e}))
            down = loss(params._replace(**{field: value - h * e}))
            fd = (up - down) / (2 * h)
            got = jnp.reshape(getattr(g, field), (-1,))[k]
            assert abs(float(fd)) > 1e-8, (field, k)  # a derivative worth checking
            np.testing.assert_allclose(got, fd, rtol=1e-5, atol=0)
    assert float(g.tol_primal) == 0.0 and float(g.tol_dual) == 0.0


def test_float32_parameters_keep_their_dtype():
    p = random_problem(1, 2, shared="all")
    solver = LocalExplicit(p.topology, max_iter=3000)
    q = solver.params(tol_primal=1e-6, tol_dual=1e-6, dtype=jnp.float32)
    r = jax.jit(solver.solve)(p.data(jnp.float32), q)
    assert r.u.dtype == jnp.float32 and r.rho.dtype == jnp.float32
    g = jax.jit(jax.grad(_loss(solver, p.data(jnp.float32), 20)))(q)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(g))
