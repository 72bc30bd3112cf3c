"""Prediction matrices (eq.F3_primal_1) against a direct simulation of the model."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.prediction import matrix_powers, prediction_matrices, quadratic_cost

pytestmark = pytest.mark.timeout(60)


def simulate(A, B, x0, U, W):
    xs, x = [], x0
    for k in range(U.shape[0]):
        x = A @ x + B @ U[k] + W[k]
        xs.append(x)
    return np.array(xs)  # X^(1)..X^(N)


@pytest.mark.parametrize("horizon", [1, 4, 9])
def test_outputs_match_simulation(horizon):
    rng = np.random.default_rng(horizon)
    nx, nb, ny = 4, 3, 2
    A = rng.standard_normal((nx, nx)) * 0.4
    B = rng.standard_normal((nx, nb))
    C = rng.standard_normal((ny, nx))
    x0 = rng.standard_normal(nx)
    U = rng.standard_normal((horizon, nb))
    W = rng.standard_normal((horizon, nx))
    pred = jax.jit(prediction_matrices, static_argnums=3)(A, B, C, horizon)
    Y = pred.Y_x @ x0 + pred.Y_u @ U.reshape(-1) + pred.Y_w @ W.reshape(-1)
    expected = simulate(A, B, x0, U, W) @ C.T
    np.testing.assert_allclose(np.asarray(Y).reshape(horizon, ny), expected, rtol=1e-10, atol=1e-10)


def test_matrix_powers():
    A = np.array([[0.5, 1.0], [0.0, 0.7]])
    P = matrix_powers(jnp.asarray(A), 3)
    for k in range(4):
        np.testing.assert_allclose(P[k], np.linalg.matrix_power(A, k), rtol=1e-12)


def test_quadratic_cost_matches_direct_cost():
    rng = np.random.default_rng(1)
    nx, nb, ny, N = 3, 2, 2, 6
    A = rng.standard_normal((nx, nx)) * 0.5
    B = rng.standard_normal((nx, nb))
    C = rng.standard_normal((ny, nx))
    Q = np.diag([2.0, 0.5])
    R = np.diag([0.3, 0.1])
    x0, W = rng.standard_normal(nx), rng.standard_normal((N, nx))
    ref = rng.standard_normal((N, ny))
    H, E = quadratic_cost(prediction_matrices(A, B, C, N), Q, R, x0, W, ref)

    def J(U):
        X = simulate(A, B, x0, U, W)
        e = X @ C.T - ref  # reference of C X^(k+1), paper-notes item 19
        return np.sum(np.einsum("ki,ij,kj->k", e, Q, e)) + np.sum(np.einsum("ki,ij,kj->k", U, R, U))

    U = rng.standard_normal((N, nb))
    lhs = J(U) - J(np.zeros_like(U))
    u = U.reshape(-1)
    rhs = 0.5 * u @ np.asarray(H) @ u + np.asarray(E) @ u
    np.testing.assert_allclose(lhs, rhs, rtol=1e-10)
    np.testing.assert_allclose(H, np.asarray(H).T)
