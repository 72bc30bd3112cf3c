"""ampc_jax.admm.finish: the exact finish of Local Explicit against Clarabel, and its
KKT check refusing a wrong active set."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.finish import finish_solve, select_finish, solve_eqp, verify
from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(300)

REF_EPS = 1e-13  # Clarabel's tolerances: its own error is then ~1e-8 on these problems


def stack(datas):
    return jax.tree.map(lambda *x: jnp.stack(x), *datas)


def reference(problem, data):
    ref = solve_reference(problem.topology, data, eps=REF_EPS)
    assert ref.status == Status.SOLVED
    return ref


@pytest.mark.parametrize("n_obj,rho", [(2, (1.0, 0.3)), (3, (1.0, 0.3, 2.0))])
def test_finish_matches_clarabel(n_obj, rho):
    """Every verified finish is the integrated optimum to 1e-5 (Nm on the vehicle
    examples), with unequal rho_j; the batch has active bounds."""
    problems = [random_problem(seed, n_obj, shared="chain") for seed in range(6)]
    T = problems[0].topology
    datas = [p.data() for p in problems]
    solver = LocalExplicit(T, max_iter=3000, finish="active_set")
    q = solver.params(rho=rho, tol_primal=1e-10, tol_dual=1e-10)
    res = jax.jit(jax.vmap(solver.solve, in_axes=(0, None)))(stack(datas), q)
    finished = np.asarray(jnp.all(res.dual_residual == 0, axis=-1))
    assert finished.sum() >= 5, f"verified finishes {finished}"
    active = 0
    for b, (p, d) in enumerate(zip(problems, datas, strict=True)):
        ref = reference(p, d)
        assert int(res.status[b]) == Status.SOLVED
        if finished[b]:
            assert np.max(np.abs(np.asarray(res.u[b]) - ref.u)) < 1e-5, b
        lb, ub = np.asarray(d.lb), np.asarray(d.ub)
        active += int(np.sum(np.isclose(ref.u, lb, atol=1e-7) | np.isclose(ref.u, ub, atol=1e-7)))
    assert active > 0


def _setup_and_sets():
    p = random_problem(0, 2, shared="chain")
    T, d = p.topology, p.data()
    solver = LocalExplicit(T, max_iter=3000, finish="active_set")
    setup = jax.jit(solver.setup)(d, solver.params(tol_primal=1e-10, tol_dual=1e-10))
    ref = reference(p, d)
    slack = np.asarray(d.bin) - ref.u @ np.asarray(d.Ain).T
    right = slack < 1e-7
    assert right.any() and (~right).any()
    return T, d, solver, setup, ref, right


def test_kkt_check_refuses_a_wrong_active_set():
    """The right set passes the check and gives Clarabel's optimum; a set missing an
    active row (violated) or holding an inactive one (negative multiplier) is
    refused, also after the solve itself succeeded (positive pivots)."""
    T, d, solver, setup, ref, right = _setup_and_sets()
    nb = len(T.box_rows)
    fd = setup.finish
    u, nu, piv = solve_eqp(fd, jnp.asarray(right), nb)
    ok, add, drop = verify(fd, u, nu, jnp.asarray(right), piv)
    assert bool(ok) and np.max(np.abs(np.asarray(u) - ref.u)) < 1e-6
    k, c = np.argwhere(right)[0]
    missing = right.copy()
    missing[k, c] = False  # an active row left out: the QP's solution violates it
    u, nu, piv = solve_eqp(fd, jnp.asarray(missing), nb)
    ok, add, _ = verify(fd, u, nu, jnp.asarray(missing), piv)
    assert not bool(ok) and bool(add[k, c]) and float(piv) > 0
    extra = right.copy()
    slack = np.asarray(d.bin) - ref.u @ np.asarray(d.Ain).T
    k2, c2 = np.unravel_index(np.argmax(np.where(right, -np.inf, slack)), slack.shape)
    extra[k2, c2] = True  # an inactive row forced active: its multiplier is negative
    u, nu, piv = solve_eqp(fd, jnp.asarray(extra), nb)
    ok, _, drop = verify(fd, u, nu, jnp.asarray(extra), piv)
    assert not bool(ok) and bool(drop[k2, c2])
    # without correction steps the wrong set is refused; with them, whatever is
    # accepted is the optimum (active-set steps may also fail to reach it)
    for wrong in (missing, extra):
        assert not bool(finish_solve(fd, jnp.asarray(wrong), nb, 0)[3])
        u, _, act, ok = finish_solve(fd, jnp.asarray(wrong), nb, 4)
        if bool(ok):
            assert np.max(np.abs(np.asarray(u) - ref.u)) < 1e-6


def test_refused_finish_leaves_the_iterate():
    """The finisher on an iterate whose set is wrong (no correction steps) returns
    the iterate unchanged; on the right set it returns the optimum, converged."""
    T, d, _, _, ref, right = _setup_and_sets()
    solver = LocalExplicit(T, max_iter=3000, finish="active_set", finish_corrections=0)
    setup = solver.setup(d, solver.params(tol_primal=1e-10, tol_dual=1e-10))
    finish = solver.finisher(setup)
    k, c = np.argwhere(right)[0]
    wrong = right.copy()
    wrong[k, c] = False
    st = solver.cold_state()
    for act, accepted in ((wrong, False), (right, True)):
        it = st._replace(Z=jnp.where(jnp.asarray(act), 0.0, 1.0), iteration=jnp.int32(3))
        out = finish(it, it, jnp.asarray(True))
        if accepted:
            assert bool(solver.converged(setup, out))
            u = np.asarray(solver.result(setup, out).u)
            assert np.max(np.abs(u - ref.u)) < 1e-6
        else:
            for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(it), strict=True):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_finish_options_are_validated():
    T = random_problem(0, 2).topology
    with pytest.raises(ValueError, match="finish"):
        LocalExplicit(T, finish="polish")
    with pytest.raises(ValueError, match="finish_every"):
        LocalExplicit(T, finish="active_set", finish_every=0)
    with pytest.raises(ValueError, match="finish_corrections"):
        LocalExplicit(T, finish="active_set", finish_corrections=-1)
    assert select_finish("none").name == "none"
