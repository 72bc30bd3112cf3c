"""ampc_jax.admm.feasibility: Farkas certificates of an empty constraint set, and the
infeasible status every formulation reports with them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.feasibility import certify
from ampc_jax.formulations import FORMULATIONS, formulation
from ampc_jax.generate import random_problem
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(240)


def _with_bounds(problem, step, k, lb, ub):
    """The problem's data with input k's bounds at one step replaced (data, so no
    ProblemError: a moving bound such as the TCR agent's can cross at run time)."""
    T, d = problem.topology, problem.data()
    lo, hi = d.lb.at[step, k].set(lb), d.ub.at[step, k].set(ub)
    up = [i for i, s in T.box_rows if s > 0]
    down = [i for i, s in T.box_rows if s < 0]
    return d._replace(lb=lo, ub=hi, bin=jnp.concatenate([hi[:, up], -lo[:, down]], axis=1))


def _check(cert, d):
    """The certificate's two conditions, from the data (independent of the search)."""
    y, k = np.asarray(cert.y), int(cert.step)
    A, b = np.asarray(d.Ain), np.asarray(d.bin[k])
    assert np.all(y >= 0) and np.max(y) == pytest.approx(1.0)
    assert np.max(np.abs(A.T @ y)) < 1e-6
    assert float(b @ y) < -1e-3
    assert float(cert.bty) == pytest.approx(float(b @ y), rel=1e-6)


def test_certificates_of_crossed_bounds_and_none_for_a_feasible_set():
    p = random_problem(0, 2, shared="chain")
    d = _with_bounds(p, 4, 1, 0.6, 0.5)
    cert = jax.jit(certify)(d)
    assert bool(cert.infeasible) and int(cert.step) == 4
    _check(cert, d)
    # b' y is the bounds' gap: 0.5 - 0.6
    assert float(cert.bty) == pytest.approx(-0.1, rel=1e-6)
    for seed in range(5):  # feasible sets, bounds touching included, are never certified
        q = random_problem(seed, 3, shared="both")
        assert not bool(certify(q.data()).infeasible)
        assert not bool(certify(_with_bounds(q, 2, 0, 0.3, 0.3)).infeasible)


@pytest.mark.parametrize("name", sorted(FORMULATIONS))
def test_every_formulation_reports_infeasible_with_its_evidence(name):
    p = random_problem(1, 2, shared="chain")
    f = formulation(name, p.topology, max_iter=300)
    q = f.params(tol_primal=1e-10, tol_dual=1e-10)
    bad = _with_bounds(p, 2, 0, 1.0, -1.0)
    res = jax.jit(f.solve)(bad, q)
    assert int(res.status) == Status.INFEASIBLE and not bool(res.converged)
    assert bool(res.certificate.infeasible) and int(res.certificate.step) == 2
    _check(res.certificate, bad)
    assert np.all(np.isfinite(np.asarray(res.u)))  # never a NaN, even with no solution
    # the same compiled step on feasible data: solved, no certificate
    ok = jax.jit(f.solve)(p.data(), f.params(tol_primal=1e-8, tol_dual=1e-8))
    assert int(ok.status) in (0, 1) and not bool(ok.certificate.infeasible)


def _three_agents(agents_bounds, rows, b):
    from ampc_jax.problem import Agent, Constraint, Objective, Problem

    A = [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.9]]
    B = {"a": [[0.0], [1.0], [0.0]], "b": [[0.0], [0.5], [1.0]], "c": [[0.0], [0.0], [1.0]]}
    R = {"a": [0.1], "b": [0.2], "c": [0.3]}
    agents = [
        Agent(n, B[n], R[n], *agents_bounds[n]) if n in agents_bounds else Agent(n, B[n], R[n])
        for n in "abc"
    ]
    objectives = [
        Objective("pos", [[1.0, 0.0, 0.0]], [1.0], [1.0]),
        Objective("z", [[0, 0, 1.0]], [2.0], [0.5]),
    ]
    return Problem(4, A, [0.0, 0.0, 0.0], agents, objectives, constraints=[Constraint(rows, b)])


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_a_feasible_slab_of_badly_scaled_rows_is_never_certified(dtype):
    """1e-3 a <= -1 and -1e-3 a <= 2 (a in [-2000, -1000]): feasible, whatever the
    rows' scale. Before the rows were equilibrated, a single row passed as a
    'certificate' in float32 (||A'y|| = 1e-3 looked small)."""
    for scale in (1e-3, 1e-6, 1.0, 1e3):
        p = _three_agents({}, {"a": [[scale], [-scale]]}, [-1000.0 * scale, 2000.0 * scale])
        assert not bool(jax.jit(certify)(p.data(dtype)).infeasible), scale


@pytest.mark.parametrize("name", ["local_explicit", "fully_distributed", "virtual_center"])
def test_a_set_empty_by_less_than_the_tolerance_is_not_called_solved(name):
    """b on [-1, 1] with -b <= -1.001: empty by 1e-3, about sqrt(eps_r) at the
    default tolerance, so the stopping rule alone would accept the violation."""
    p = _three_agents(
        {"a": ([-1.0], [1.0]), "b": ([-1.0], [1.0]), "c": ([-2.0], [2.0])},
        {"b": [[-1.0]]},
        [-1.001],
    )
    f = formulation(name, p.topology, max_iter=1000)
    res = jax.jit(f.solve)(p.data(), f.params())
    assert int(res.status) == Status.INFEASIBLE
    _check_scaled(res.certificate, p.data(), margin=1e-3)


def _check_scaled(cert, d, margin):
    y, k = np.asarray(cert.y), int(cert.step)
    A, b = np.asarray(d.Ain), np.asarray(d.bin[k])
    assert np.all(y >= 0) and np.max(np.abs(A.T @ y)) < 1e-6
    assert float(b @ y) == pytest.approx(-margin, rel=1e-3)
