"""ampc_jax.admm.stopping: the duality gap of a result bounds its distance to the
optimum (against Clarabel), and the relative tolerance reads the same whatever
the problem's units."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import FORMULATIONS, PAPER_ITERATION, formulation
from ampc_jax.generate import random_problem
from ampc_jax.problem import condensed_qp
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(240)


def _iteration(name):
    """The paper's iteration where the formulation has other defaults: these tests are
    about the iteration's stopping rule (Local Explicit's finish would stop it sooner)."""
    return PAPER_ITERATION if name in ("local_explicit", "integrated") else {}


# Local Explicit in the default run: the gap is computed by the one core for every
# formulation; the others under -m slow
@pytest.mark.parametrize(
    "name",
    [
        n if n == "local_explicit" else pytest.param(n, marks=pytest.mark.slow)
        for n in sorted(FORMULATIONS)
    ],
)
def test_the_gap_bounds_the_distance_to_the_optimum(name):
    """1/2 ||u - U*||_H^2 <= J(u) - J* <= gap for box-only problems (u feasible),
    the gap shrinking with the tolerance, the same under vmap."""
    problems = [random_problem(s, 2, shared="chain") for s in (7, 3)]
    T = problems[0].topology
    f = formulation(name, T, max_iter=20000, **_iteration(name))
    gaps = []
    for tol in (1e-6, 1e-10):
        q = f.params(tol_primal=tol, tol_dual=tol)
        data = jax.tree.map(lambda *x: jnp.stack(x), *[p.data() for p in problems])
        batch = jax.jit(jax.vmap(f.solve, in_axes=(0, None)))(data, q)
        for b, p in enumerate(problems):
            d = p.data()
            res = jax.jit(f.solve)(d, q)
            assert int(res.status) == Status.SOLVED
            gap = float(res.stats.gap)
            np.testing.assert_allclose(batch.stats.gap[b], gap, rtol=1e-6, atol=1e-12)
            ref = solve_reference(T, d, eps=1e-12)
            H = np.asarray(condensed_qp(T, d).H)
            e = (np.asarray(res.u) - ref.u).ravel()
            assert 0.0 <= 0.5 * e @ H @ e <= gap * (1 + 1e-6) + 1e-12, (tol, b)
            # the bound in the inputs' units, what `ampc solve` prints
            low = np.linalg.eigvalsh(H)[0]
            assert np.linalg.norm(e) <= np.sqrt(2 * gap / low) * (1 + 1e-6) + 1e-9
            gaps.append(gap)
    assert gaps[2] < 0.05 * gaps[0] and gaps[3] < 0.05 * gaps[1], gaps  # ~ the residuals


def test_the_references_report_their_gap_too():
    p = random_problem(7, 2, shared="chain")
    for solver in ("clarabel", "osqp"):
        res = solve_reference(p.topology, p.data(), solver, eps=1e-9)
        assert -1e-9 <= res.stats.gap <= 1e-5, (solver, res.stats.gap)


def _scaled(data, k):
    """The same problem in units k times smaller: every input, bound, reference
    and state k times larger, so U* scales by k (H is unchanged)."""
    return data._replace(
        x0=k * data.x0,
        w=k * data.w,
        ref=tuple(k * r for r in data.ref),
        bin=k * data.bin,
        lb=k * data.lb,
        ub=k * data.ub,
    )


@pytest.mark.parametrize("name", ["local_explicit", "fully_distributed"])
def test_the_relative_tolerance_reads_the_same_in_any_units(name):
    """With eps_rel alone the iteration count does not depend on the units (the
    ADMM iterates scale with the problem, and so do the scales); with eps_abs
    alone the larger units need many more iterations for the same accuracy."""
    p = random_problem(7, 2, shared="chain")
    d = p.data()
    f = formulation(name, p.topology, max_iter=20000, **_iteration(name))
    solve = jax.jit(f.solve)
    rel = f.params(tol_primal=0.0, tol_dual=0.0, tol_rel=1e-5)
    absolute = f.params(tol_primal=1e-8, tol_dual=1e-8)
    k = 1e3
    one, big = solve(d, rel), solve(_scaled(d, k), rel)
    assert int(one.status) == int(big.status) == Status.SOLVED
    assert abs(int(one.iterations) - int(big.iterations)) <= 2, (one.iterations, big.iterations)
    np.testing.assert_allclose(np.asarray(big.u) / k, one.u, rtol=1e-6, atol=1e-6)
    a1, ak = solve(d, absolute), solve(_scaled(d, k), absolute)
    assert int(ak.iterations) > int(a1.iterations) + 50, (a1.iterations, ak.iterations)


def test_a_zero_relative_tolerance_is_the_absolute_rule():
    """tol_rel = 0 (the default) stops at the same iteration as the absolute rule
    with any scale: the threshold is eps + 0 * scale^2, exactly eps."""
    p = random_problem(3, 3, shared="both")
    f = formulation("local_explicit", p.topology, max_iter=5000, **PAPER_ITERATION)
    solve = jax.jit(f.solve)
    base = solve(p.data(), f.params(tol_primal=1e-9, tol_dual=1e-9))
    tiny = solve(p.data(), f.params(tol_primal=1e-9, tol_dual=1e-9, tol_rel=1e-30))
    assert int(base.iterations) == int(tiny.iterations)
    looser = solve(p.data(), f.params(tol_primal=1e-9, tol_dual=1e-9, tol_rel=1e-3))
    assert int(looser.iterations) < int(base.iterations)
