"""ampc_jax.admm.kkt: the KKT solve strategies agree, and "auto" picks by size."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.kkt import DenseKKT, WoodburyKKT, select_kkt
from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.problem import Agent, Constraint, Objective, Problem
from ampc_jax.reference import solve_reference
from ampc_jax.results import Status

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("horizon", [pytest.param(3, marks=pytest.mark.slow), 10])
@pytest.mark.parametrize("kkt", ["woodbury", "woodbury_factored"])
def test_woodbury_and_dense_setups_agree(horizon, kkt):
    """Woodbury setup (rho's power iteration matrix-free; K^-1 formed or kept
    factored) against the dense one (formed operators, Cholesky of H)."""
    p = random_problem(7, 3, shared="both", horizon=horizon)
    T, d = p.topology, p.data()
    lo_solver = LocalExplicit(T, kkt=kkt)
    assert lo_solver.kkt_solve == WoodburyKKT(factored=kkt == "woodbury_factored")
    lo = lo_solver.setup(d)
    de = LocalExplicit(T, kkt="dense").setup(d)
    n = de.Kinv.shape[-1]
    eye = jnp.broadcast_to(jnp.eye(n), (T.n_objectives, n, n))
    apply = lo_solver.kkt_solve.apply
    lo_K = jax.vmap(lambda x: apply(lo.Kinv, x), in_axes=2, out_axes=2)(eye)
    np.testing.assert_allclose(lo.rho, de.rho, rtol=1e-6)
    np.testing.assert_allclose(lo_K, de.Kinv, rtol=1e-7, atol=1e-9 * np.abs(de.Kinv).max())
    np.testing.assert_allclose(lo.KE, de.KE, rtol=1e-7, atol=1e-9 * np.abs(de.KE).max())


def test_auto_picks_by_outputs_against_inputs():
    """r < n/2: Woodbury kept factored; r = n/2: formed; r > n/2: dense."""
    one = random_problem(0, 2, shared="all", private_agents=2).topology  # 1 output, 3 inputs
    assert select_kkt(one) == WoodburyKKT(factored=True)
    assert LocalExplicit(one).kkt_solve.name == "woodbury_factored"
    half = random_problem(0, 2, shared="none", private_agents=2, outputs=1).topology  # 1 of 2
    assert select_kkt(half) == WoodburyKKT(factored=False)
    two = random_problem(0, 1, outputs=2, private_agents=1).topology  # 2 outputs, 1 input
    assert select_kkt(two) == DenseKKT()
    with pytest.raises(ValueError, match="kkt: expected one of"):
        select_kkt(one, "qr")


def test_singular_r_falls_back_to_the_dense_factorisation():
    """R_(i) singular along (1, -1) and the inputs covered only by +-(u1 + u2) <= 1:
    K_j is positive definite but the Woodbury form's per-step block 2R + rho A'A
    is not. One output would pick the Woodbury form; with a singular R 'auto'
    takes the dense one and matches Clarabel, and 'woodbury' is refused."""
    p = Problem(
        horizon=4,
        A=[[0.9, 0.1], [0.0, 0.8]],
        x0=[1.0, -0.5],
        agents=[Agent("a", B=[[1.0, 0.3], [0.2, 1.0]], R=[[0.1, 0.1], [0.1, 0.1]])],
        objectives=[Objective("o", C=[[1.0, 0.0]], Q=[1.0], ref=[3.0])],
        constraints=[Constraint(A={"a": [[1.0, 1.0], [-1.0, -1.0]]}, b=[1.0, 1.0])],
    )
    T, d = p.topology, p.data()
    assert T.singular_r == (0,)
    le = LocalExplicit(T, max_iter=30000)
    assert le.kkt_solve == DenseKKT()
    r = jax.jit(le.solve)(d, le.params(tol_primal=1e-14, tol_dual=1e-14))
    ref = solve_reference(T, d)
    assert int(r.status) == Status.SOLVED
    np.testing.assert_allclose(np.asarray(r.u0), ref.u[0], rtol=1e-3, atol=1e-6)
    for kkt in ("woodbury", "woodbury_factored"):
        with pytest.raises(ValueError, match="kkt: .*singular for \\['a'\\]"):
            LocalExplicit(T, kkt=kkt)


@pytest.mark.parametrize("kkt", ["dense", "woodbury", "riccati"])
def test_each_strategy_holds_the_same_local_hessian(kkt):
    """Each KKT strategy's Hessian operator (what eq.opt_ro's power iteration and
    the duality gap use, in place of a string naming the form) applies H_j and
    inverts it, against the formed H_j and numpy's solve."""
    from ampc_jax.admm.costs import padded_costs

    p = random_problem(7, 3, shared="both", horizon=4)
    T, d = p.topology, p.data()
    strategy = select_kkt(T, kkt)
    c = padded_costs(T, d, with_H=True, condensed=True)
    h = strategy.hessian(c, T)
    x = jnp.asarray(np.random.default_rng(0).standard_normal((T.n_objectives, 2, c.H.shape[-1])))
    H = np.asarray(c.H)
    np.testing.assert_allclose(h.apply(x), np.einsum("jab,jpb->jpa", H, x), rtol=1e-10, atol=1e-10)
    want = np.stack([np.linalg.solve(H[j], np.asarray(x[j]).T).T for j in range(len(H))])
    np.testing.assert_allclose(h.solve(x), want, rtol=1e-8, atol=1e-10)
    assert strategy.forms_H == (kkt == "dense")


def test_strategies_are_chosen_by_name_at_construction():
    from ampc_jax.admm.rho import ExactRho, GivenRho, PowerRho
    from ampc_jax.admm.stopping import ChangeResidual, PaperResidual
    from ampc_jax.formulations import FullyDistributed

    T = random_problem(0, 2).topology
    le = LocalExplicit(T, rho_method="eigh", dual_residual="paper")
    assert isinstance(le.rho_rule, ExactRho) and isinstance(le.dual_rule, PaperResidual)
    assert isinstance(LocalExplicit(T, rho_method="given").rho_rule, GivenRho)
    fd = FullyDistributed(T)
    assert isinstance(fd.rho_rule, PowerRho) and fd.dual_rule == ChangeResidual("change")
    with pytest.raises(ValueError, match=r"rho_method: expected one of \('power', 'given'\)"):
        FullyDistributed(T, rho_method="eigh")
    with pytest.raises(ValueError, match="dual_residual: expected one of"):
        LocalExplicit(T, dual_residual="change")
