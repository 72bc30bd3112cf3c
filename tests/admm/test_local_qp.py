"""ampc_jax.admm.local_qp: the inner ADMM of Formulations 1 and 2 against Clarabel."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.local_qp import InnerState, factor, inner_rho, iterate
from ampc_jax.problem.condensed import CondensedQP
from ampc_jax.reference import clarabel_solve

pytestmark = pytest.mark.timeout(120)


def _qp(seed, J=2, N=3, U=2, C=5):
    rng = np.random.default_rng(seed)
    n = N * U
    L = rng.standard_normal((J, n, n))
    P = L @ np.swapaxes(L, 1, 2) + 0.1 * np.eye(n)
    q = 3.0 * rng.standard_normal((J, n))
    A = rng.standard_normal((J, C, U))
    b = rng.uniform(0.1, 1.0, (J, N, C))
    return P, q, A, b


def test_inner_admm_reaches_the_local_qp_optimum():
    P, q, A, b = _qp(0)
    J, N, C = b.shape
    ev = np.linalg.eigvalsh(P)
    sigma = inner_rho(jnp.asarray(ev[:, 0]), jnp.asarray(ev[:, -1]), jnp.asarray(A))
    qp = factor(jnp.asarray(P), jnp.asarray(A), sigma, N)
    zero = jnp.zeros((J, N, C))
    u, _, primal, dual = jax.jit(iterate, static_argnums=4)(
        qp, jnp.asarray(q), jnp.asarray(b), InnerState(zero, zero), 3000
    )
    active = 0
    for j in range(J):
        G = np.kron(np.eye(N), A[j])
        sol = clarabel_solve(CondensedQP(P[j], q[j], G, b[j].ravel()), 1e-10)
        x = np.asarray(sol.x)
        np.testing.assert_allclose(u[j], x, rtol=1e-5, atol=1e-6)
        active += int(np.sum(G @ x > b[j].ravel() - 1e-6))
        assert float(primal[j]) < 1e-14 and float(dual[j]) < 1e-14
    assert active > 0  # the rows bind: the test is not an unconstrained solve


def test_inner_state_carries_the_iteration_on():
    """Two calls of k iterations from the carried state equal one call of 2k."""
    P, q, A, b = _qp(1)
    J, N, C = b.shape
    qp = factor(jnp.asarray(P), jnp.asarray(A), jnp.ones(J), N)
    zero = InnerState(jnp.zeros((J, N, C)), jnp.zeros((J, N, C)))
    q, b = jnp.asarray(q), jnp.asarray(b)
    u1, st, _, _ = iterate(qp, q, b, zero, 7)
    u2, _, _, _ = iterate(qp, q, b, st, 7)
    u3, _, _, _ = iterate(qp, q, b, zero, 14)
    np.testing.assert_allclose(u2, u3, rtol=1e-12, atol=1e-12)
    assert not np.allclose(u1, u3)
