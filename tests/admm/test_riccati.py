"""ampc_jax.admm.riccati: the structured local solve against the condensed dense form,
and Local Explicit with it against Clarabel on the integrated QP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm import riccati
from ampc_jax.admm.costs import padded_costs
from ampc_jax.admm.feasibility import repaired_inputs, violation
from ampc_jax.admm.kkt import RiccatiKKT, select_kkt
from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(180)


def stack(datas):
    return jax.tree.map(lambda *x: jnp.stack(x), *datas)


def test_unrolled_inverse_matches_numpy():
    rng = np.random.default_rng(0)
    X = rng.standard_normal((5, 4, 4))
    M = X @ np.swapaxes(X, 1, 2) + 0.1 * np.eye(4)
    np.testing.assert_allclose(
        riccati.unrolled_spd_inverse(jnp.asarray(M)), np.linalg.inv(M), rtol=1e-9
    )


@pytest.mark.parametrize("horizon", [1, 3, 12])
@pytest.mark.parametrize("shared", ["both", "all"])
def test_factor_solve_and_sweeps_match_the_condensed_form(horizon, shared):
    """K^-1 (every column), E_j, H_j x and trace(Y_u' 2Qbar Y_u) from sweeps of the
    model equal the condensed matrices' (built independently by padded_costs)."""
    p = random_problem(5, 3, shared=shared, horizon=horizon, outputs=2, disturbance=0.3)
    T, d = p.topology, p.data()
    c = padded_costs(T, d)
    s = padded_costs(T, d, with_H=False, condensed=False)
    assert s.Yu is None and s.H is None
    np.testing.assert_allclose(s.E, c.E, rtol=1e-10, atol=1e-12 * np.abs(c.E).max())
    J, n = c.E.shape
    rng = np.random.default_rng(1)
    Bk = c.BH + jnp.asarray(rng.uniform(0.5, 2.0, (J, 1, 1))) * jnp.eye(c.BH.shape[-1])
    U = c.BH.shape[-1]
    K = c.H - jnp.einsum("kl,jab->jkalb", jnp.eye(horizon), c.BH).reshape(J, n, n)
    K = K + jnp.einsum("kl,jab->jkalb", jnp.eye(horizon), Bk).reshape(J, n, n)
    f = riccati.factor(s.A, s.Bu, s.Qx, Bk, horizon)
    eye = jnp.broadcast_to(jnp.eye(n), (J, n, n))
    Kinv = riccati.solve(f, eye)  # rows: K^-1 e_i (K symmetric)
    np.testing.assert_allclose(Kinv, np.linalg.inv(np.asarray(K)), rtol=1e-8, atol=1e-10)
    x = jnp.asarray(rng.standard_normal((J, 2, n)))
    np.testing.assert_allclose(
        riccati.hessian_apply(s.A, s.Bu, s.Qx, c.BH, x),
        jnp.einsum("jab,jpb->jpa", c.H, x),
        rtol=1e-10,
        atol=1e-10,
    )
    np.testing.assert_allclose(
        riccati.trace_gram(s.A, s.Bu, s.Qx, horizon),
        jnp.einsum("jaa->j", c.H) - horizon * jnp.einsum("jaa->j", c.BH),
        rtol=1e-10,
    )
    assert U == s.Bu.shape[-1]


@pytest.mark.parametrize("seed", [pytest.param(0, marks=pytest.mark.slow), 3])
def test_riccati_setup_matches_dense(seed):
    """rho* (power iteration on the pencil by sweeps), K^-1 E and the whole solve."""
    p = random_problem(seed, 3, shared="both", horizon=10)
    T, d = p.topology, p.data()
    ric = LocalExplicit(T, kkt="riccati")
    assert ric.kkt_solve == RiccatiKKT() and select_kkt(T, "riccati") == RiccatiKKT()
    de = LocalExplicit(T, kkt="dense")
    a, b = ric.setup(d), de.setup(d)
    np.testing.assert_allclose(a.rho, b.rho, rtol=1e-8)
    np.testing.assert_allclose(a.KE, b.KE, rtol=1e-8, atol=1e-10 * np.abs(b.KE).max())
    ra, rb = jax.jit(ric.solve)(d), jax.jit(de.solve)(d)
    assert int(ra.iterations) == int(rb.iterations)
    np.testing.assert_allclose(ra.u, rb.u, atol=1e-9)


def test_riccati_solve_matches_clarabel_with_general_rows():
    """Local Explicit with the structured solve against Clarabel on the integrated QP
    (a reference no one here wrote), batched, with an active general row."""
    from ampc_jax.problem import Agent, Constraint, Objective, Problem

    A = [[1.0, 0.1, 0.0], [0.0, 0.95, 0.1], [0.0, 0.0, 0.9]]
    agents = [
        Agent("a", [[0.0], [0.1], [0.0]], [0.1], [-1.0], [1.0]),
        Agent("b", [[0.0], [0.05], [0.1]], [0.2], [-1.0], [1.0]),
        Agent("c", [[0.0], [0.0], [0.1]], [0.3], [-2.0], [2.0]),
    ]
    objectives = [
        Objective("pos", [[1.0, 0.0, 0.0]], [1.0], [3.0]),
        Objective("z", [[0, 0, 1.0]], [2.0], [1.5]),
    ]
    rows = Constraint({"a": [[1.0]], "b": [[1.0]]}, [0.6])
    probs = [
        Problem(12, A, [0.0, 0.0, 0.0], agents, objectives, constraints=[rows]),
        Problem(12, A, [0.2, -0.1, 0.3], agents, objectives, constraints=[rows]),
    ]
    T = probs[0].topology
    solver = LocalExplicit(T, kkt="riccati", max_iter=20000)
    q = solver.params(tol_primal=1e-12, tol_dual=1e-12)
    datas = [pr.data() for pr in probs]
    res = jax.jit(jax.vmap(solver.solve, in_axes=(0, None)))(stack(datas), q)
    assert np.all(np.asarray(res.status) == Status.SOLVED)
    for k, dk in enumerate(datas):
        ref = solve_reference(T, dk)
        assert np.any(np.isclose(ref.u[:, 0] + ref.u[:, 1], 0.6, atol=1e-6)), "row inactive"
        np.testing.assert_allclose(res.u[k], ref.u, atol=2e-5)


def _crossed(problem, step=2, k=0):
    """Problem data with input k's bounds crossed at one step (an empty set)."""
    T, d = problem.topology, problem.data()
    lo, hi = d.lb.at[step, k].set(1.0), d.ub.at[step, k].set(-1.0)
    up = [i for i, s in T.box_rows if s > 0]
    down = [i for i, s in T.box_rows if s < 0]
    return d._replace(lb=lo, ub=hi, bin=jnp.concatenate([hi[:, up], -lo[:, down]], axis=1))


def test_batched_certificate_only_where_needed():
    """Under vmap the infeasibility search runs for the batch once and reports
    only the case whose set is empty; its feasible neighbour stays solved."""
    p = random_problem(1, 2, shared="chain")
    T = p.topology
    good, bad = p.data(), _crossed(p)
    solver = LocalExplicit(T, kkt="riccati", max_iter=300)
    q = solver.params(tol_primal=1e-10, tol_dual=1e-10)
    alone = jax.jit(solver.solve)(bad, q)
    assert int(alone.status) == Status.INFEASIBLE
    batched = jax.jit(jax.vmap(solver.solve, in_axes=(0, None)))
    res = batched(stack([good, bad]), q)
    st = np.asarray(res.status)
    assert st[1] == 3 and st[0] in (0, 1)
    inf = np.asarray(res.certificate.infeasible)
    assert not inf[0] and inf[1] and int(res.certificate.step[1]) == 2
    np.testing.assert_allclose(res.certificate.y[1], alone.certificate.y, atol=1e-9)
    # the batched program decides once: a cond on the batch, not a select of both branches
    txt = str(jax.make_jaxpr(jax.vmap(solver.solve, in_axes=(0, None)))(stack([good, good]), q))
    assert "cond[" in txt


def test_repair_proves_slightly_violating_inputs_feasible():
    """A converged solve violates a general row by about sqrt(eps_r); the repair
    gives a point that satisfies every row exactly, so no search is needed."""
    p = random_problem(2, 2, shared="all")
    d = p.data()
    u = jnp.zeros((p.topology.horizon, p.topology.n_u))
    # a row violated by 1e-4 at every step: u just outside the upper bound of input 0
    u = u.at[:, 0].set(d.ub[:, 0] + 1e-4)
    assert float(violation(d, u)) > 0
    assert float(violation(d, repaired_inputs(d, u))) <= 0


def test_batched_structured_step_has_no_custom_calls():
    """The batched step with the structured solve is plain XLA (no LAPACK kernel,
    no host callback: custom calls on CPU), so it runs unchanged on a GPU."""
    p = random_problem(2, 2, shared="all")
    solver = LocalExplicit(p.topology, kkt="riccati")
    q = solver.params()
    batch = stack([p.data()] * 3)
    hlo = jax.jit(jax.vmap(solver.solve, in_axes=(0, None))).lower(batch, q).compile().as_text()
    assert "custom-call" not in hlo and "callback" not in hlo
