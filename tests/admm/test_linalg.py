"""ampc_jax.admm.linalg: the SPD inverses (sweeps and LAPACK) and the small Cholesky."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.linalg import small_cholesky, spd_inverse

pytestmark = pytest.mark.timeout(120)


@pytest.mark.parametrize("n", [1, 4, 12, 20])
def testspd_inverse_matches_numpy_batched_and_unbatched(n):
    rng = np.random.default_rng(n)
    X = rng.normal(size=(3, n, n))
    A = X @ X.transpose(0, 2, 1) + 0.1 * np.eye(n)  # condition number up to ~1e3
    ref = np.linalg.inv(A)
    tol = 1e-9 * np.abs(ref).max()
    np.testing.assert_allclose(jax.jit(spd_inverse)(jnp.asarray(A)), ref, atol=tol)
    batched = jax.jit(jax.vmap(spd_inverse))(jnp.asarray(A[:, None]))[:, 0]  # the sweeps
    np.testing.assert_allclose(batched, ref, atol=tol)


def testspd_inverse_gradient_against_finite_differences():
    rng = np.random.default_rng(7)
    for n in (3, 16):
        X = rng.normal(size=(2, n, n))
        A = jnp.asarray(X @ X.transpose(0, 2, 1) + n * np.eye(n))
        W = jnp.asarray(rng.normal(size=(2, n, n)))
        D = rng.normal(size=(2, n, n))
        D = jnp.asarray(D + D.transpose(0, 2, 1))  # symmetric perturbation

        def f(a, W=W):
            return jnp.sum(W * spd_inverse(a))

        h = 1e-6
        fd = (f(A + h * D) - f(A - h * D)) / (2 * h)
        g = jax.grad(f)(A)
        np.testing.assert_allclose(float(jnp.sum(g * D)), float(fd), rtol=1e-6)
        _, t = jax.jvp(f, (A,), (D,))  # forward mode
        np.testing.assert_allclose(float(t), float(fd), rtol=1e-6)
        # second derivatives (the rule differentiates itself): d/dh of the
        # directional derivative, against finite differences of the gradient
        hvp = jax.jvp(jax.grad(f), (A,), (D,))[1]
        fd2 = (jax.grad(f)(A + h * D) - jax.grad(f)(A - h * D)) / (2 * h)
        np.testing.assert_allclose(hvp, fd2, rtol=1e-5, atol=1e-8)

        # the same derivative through the batched (sweep) path
        def fb(a, w):
            return jnp.sum(w * spd_inverse(a[None])[0])

        gv = jax.vmap(jax.grad(fb))(A, W)
        np.testing.assert_allclose(gv, g, rtol=1e-9, atol=1e-12)


def testsmall_cholesky_semidefinite():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(4, 3, 2))
    A = X @ X.transpose(0, 2, 1)  # rank 2 of 3
    A[1] = np.diag([2.0, 0.0, 0.0])  # a padded output with zero weight
    L = np.asarray(small_cholesky(jnp.asarray(A)))
    assert np.all(np.isfinite(L))
    assert np.allclose(np.triu(L, 1), 0.0)
    np.testing.assert_allclose(L @ L.transpose(0, 2, 1), A, atol=1e-10)
