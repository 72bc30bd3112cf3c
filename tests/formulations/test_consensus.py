"""ampc_jax.formulations.consensus (Formulations 1 and 2: fully_distributed.py,
virtual_center.py): the integrated optimum on generated problems with two to four
objectives, the fixed point of a row coupling groups, parameters as data, gradients."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import FullyDistributed, VirtualCenter
from ampc_jax.generate import random_problem
from ampc_jax.problem import Constraint, ProblemError, Topology
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(300)

KINDS = [FullyDistributed, VirtualCenter]
TIGHT = dict(tol_primal=1e-14, tol_dual=1e-14)
ATOL = 1e-6  # absolute floor of the "1e-3 relative" comparison (inputs near zero)


def stack(datas):
    return jax.tree.map(lambda *x: jnp.stack(x), *datas)


def relative_error(u0, ref):
    return float(np.max(np.abs(np.asarray(u0) - ref) / (np.abs(ref) + ATOL / 1e-3)))


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
@pytest.mark.parametrize(
    ("J", "shared"),
    [
        (2, "chain"),
        pytest.param(3, "chain", marks=pytest.mark.slow),
        (3, "both"),
        pytest.param(4, "both", marks=pytest.mark.slow),
    ],
)
def test_reaches_the_integrated_optimum(kind, J, shared):
    """First-step inputs within 1e-3 relative of Clarabel's, with unequal rho_j
    (``rho_spread``: weights 1x, 10x, 100x apart; paper-notes item 14) and active bounds.
    ``-m slow`` adds 3 objectives on a chain and 4 objectives (more groups, the same
    check; 4 objectives take 2 to 4 times the 3-objective run)."""
    problems = [random_problem(s, J, shared=shared) for s in range(3)]
    T = problems[0].topology
    f = kind(T, max_iter=40000, inner_iterations=5)
    datas = [p.data() for p in problems]
    res = jax.jit(jax.vmap(f.solve, in_axes=(0, None)))(stack(datas), f.params(**TIGHT))
    active = 0
    for b, (p, d) in enumerate(zip(problems, datas, strict=True)):
        ref = solve_reference(p.topology, d)
        assert int(res.status[b]) == Status.SOLVED, f"problem {b} did not converge"
        assert relative_error(res.u0[b], ref.u[0]) < 1e-3
        lb, ub = np.asarray(d.lb), np.asarray(d.ub)
        active += int(np.sum(np.isclose(ref.u, lb, atol=1e-6) | np.isclose(ref.u, ub, atol=1e-6)))
    assert active > 0
    rho = np.asarray(res.rho)
    assert np.max(rho.max(axis=1) / rho.min(axis=1)) > 5  # unequal rho_j really tested


def _with_row(A, c, seed=3):
    base = random_problem(seed, 2, shared="chain")  # agents p0_0, p1_0, s01
    return dataclasses.replace(base, constraints=[Constraint(A, [c])])


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_a_row_inside_every_group_it_touches_keeps_the_optimum(kind):
    p = _with_row({"s01": [[1.0]]}, -0.2)
    f = kind(p.topology, max_iter=30000, inner_iterations=5)
    res = jax.jit(f.solve)(p.data(), f.params(**TIGHT))
    ref = solve_reference(p.topology, p.data())
    G, h = np.asarray(p.data().Ain[-1]), np.asarray(p.data().bin[:, -1])
    assert np.max(ref.u @ G - h) > -1e-6  # the row binds at the optimum
    assert int(res.status) == Status.SOLVED and relative_error(res.u0, ref.u[0]) < 1e-3


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_a_row_coupling_two_groups_has_a_pinned_gap(kind):
    """p0_0 + p1_0 <= 0.2 couples agents of different groups, each seen by the
    other objective as U-tilde (eq.F1_1). The iteration converges to a feasible
    fixed point that is not the optimum (docs/formulations.md, "The fixed point"):
    pinned at the measured first-step gap of 1.03 (inputs in about [-1, 1]), and at
    the point reached with two settings of rho."""
    p = _with_row({"p0_0": [[1.0]], "p1_0": [[1.0]]}, 0.2)
    T, d = p.topology, p.data()
    with pytest.raises(ProblemError, match="share no objective"):
        from ampc_jax.formulations import LocalExplicit

        LocalExplicit(T)
    f = kind(T, max_iter=30000, inner_iterations=5)
    res = jax.jit(f.solve)(d, f.params(**TIGHT))
    ref = solve_reference(T, d)
    u = np.asarray(res.u)
    G, h = np.asarray(d.Ain[-1]), np.asarray(d.bin[:, -1])
    assert int(res.status) == Status.SOLVED
    assert np.max(u @ G - h) < 1e-6  # feasible
    gap = float(np.max(np.abs(np.asarray(res.u0) - ref.u[0])))
    assert gap == pytest.approx(1.03, abs=0.02)
    # the equilibrium is not unique: which one is reached depends on rho. The row
    # binds at every one (p0 + p1 = 0.2); the shared agent s01 stays at -0.509
    u0 = np.asarray(res.u0)
    np.testing.assert_allclose(u0, [-0.2989, 0.4989, -0.5089], atol=2e-4)
    other = jax.jit(f.solve)(d, f.params(rho=(0.1, 10.0), **TIGHT))
    v0 = np.asarray(other.u0)
    assert int(other.status) == Status.SOLVED and v0[0] + v0[1] == pytest.approx(0.2, abs=1e-6)
    assert v0[0] == pytest.approx(0.047, abs=2e-3) and v0[2] == pytest.approx(-0.5089, abs=2e-4)


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.__name__)
def test_one_compiled_step_serves_every_parameter_point(kind):
    p = random_problem(2, 2, shared="chain")
    f = kind(p.topology, max_iter=5000)
    d = p.data()
    traces = []

    def solve(data, q):
        traces.append(1)
        return f.solve(data, q)

    fn = jax.jit(solve)
    points = [(1.0, 1.0), (0.3, 1.5), (3.0, 0.8), ((0.5, 2.0), 1.2), (0.1, 1.9)]
    out = [fn(d, f.params(rho=r, relaxation=a, **TIGHT)) for r, a in points]
    assert len(traces) == 1
    # the first and the last point compiled on their own (each a compile of its
    # own; the three between add compiles, not a check)
    for (r, a), res in [*zip(points, out, strict=True)][:: len(points) - 1]:
        alone = jax.jit(kind(p.topology, max_iter=5000).solve)(
            d, f.params(rho=r, relaxation=a, **TIGHT)
        )
        np.testing.assert_array_equal(res.u, alone.u)
        assert int(res.iterations) == int(alone.iterations)
    # and vmapped over parameter points and scenarios together
    datas = stack([random_problem(s, 2, shared="chain").data() for s in range(3)])
    rho = jnp.asarray([[1.0, 1.0], [0.3, 0.3], [3.0, 1.0]])
    q = f.params(rho=rho, relaxation=jnp.asarray([1.0, 1.5, 1.2]), tol_primal=1e-8, tol_dual=1e-8)
    batched = jax.jit(jax.vmap(f.solve))(datas, q)
    assert batched.u.shape == (3, p.topology.horizon, p.topology.n_u)
    assert np.all(np.asarray(batched.status) == Status.SOLVED)


@pytest.mark.parametrize(
    "kind",
    [FullyDistributed, pytest.param(VirtualCenter, marks=pytest.mark.slow)],
    ids=lambda k: k.__name__,
)
def test_gradient_through_the_fixed_iteration_runner_matches_finite_differences(kind):
    """d/d(rho, alpha) of a smooth function of the inputs after K iterations (inputs
    inside their bounds, so the projection is the identity), central differences.
    ``-m slow`` adds Virtual Center (its gradient's finiteness under grad is
    tests/formulations/test_formulation_protocol.py's in the default run)."""
    p = random_problem(7, 2, shared="chain", reference_scale=0.5)
    d = p.data()
    f = kind(p.topology)

    def loss(rho, alpha):
        res = f.solve_fixed(d, 15, f.params(rho=rho, relaxation=alpha))
        return jnp.sum(res.u[:3] ** 2) + jnp.sum(res.u)

    rho0, a0 = jnp.asarray([0.7, 1.3]), jnp.asarray(1.2)
    g_rho, g_a = jax.jit(jax.grad(loss, argnums=(0, 1)))(rho0, a0)
    h = 1e-6
    fd_rho = [
        (loss(rho0.at[j].add(h), a0) - loss(rho0.at[j].add(-h), a0)) / (2 * h) for j in range(2)
    ]
    fd_a = (loss(rho0, a0 + h) - loss(rho0, a0 - h)) / (2 * h)
    np.testing.assert_allclose(g_rho, fd_rho, rtol=1e-5)
    np.testing.assert_allclose(g_a, fd_a, rtol=1e-5)
    assert float(jnp.min(jnp.abs(g_rho))) > 1e-6


def test_warm_start_from_a_shifted_state_and_clear_errors():
    p = random_problem(0, 2, shared="chain")
    f = FullyDistributed(p.topology, max_iter=5000)
    q = f.params(tol_primal=1e-10, tol_dual=1e-10)
    cold = jax.jit(f.solve)(p.data(), q)
    warm = jax.jit(f.solve)(p.data(), q, f.shift(cold.state, 0))
    assert int(warm.iterations) < int(cold.iterations) / 2
    np.testing.assert_allclose(warm.u0, cold.u0, atol=1e-4)
    with pytest.raises(TypeError, match="warm: expected a ConsensusState"):
        f.solve(p.data(), q, object())
    with pytest.raises(ValueError, match="rho_method: expected one of"):
        FullyDistributed(p.topology, rho_method="eigh")
    with pytest.raises(ValueError, match="dual_residual: expected one of"):
        VirtualCenter(p.topology, dual_residual="slack")
    # an agent in no group cannot be given a consensus copy
    T = p.topology
    lonely = Topology.build(
        n_x=T.n_x,
        horizon=T.horizon,
        agent_names=(*T.agent_names, "idle"),
        agent_sizes=(*T.agent_sizes, 1),
        objective_names=T.objective_names,
        output_sizes=T.output_sizes,
        groups=T.groups,
    )
    with pytest.raises(ProblemError, match=r"agents\[3\] \(idle\): in no objective's group"):
        FullyDistributed(lonely)
