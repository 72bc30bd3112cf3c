"""ampc_jax.admm.acceleration: type-II Anderson acceleration."""

import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.acceleration import anderson_init, anderson_step

pytestmark = pytest.mark.timeout(60)


def testanderson_step_solves_a_linear_fixed_point_like_gmres():
    """Type-II Anderson with memory m >= n on x -> M x + c is GMRES in disguise
    (Walker and Ni 2011): it reaches the fixed point after about n + 1 maps,
    where the plain iteration (spectral radius 0.95) needs hundreds."""
    rng = np.random.default_rng(0)
    n = 3
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    M = jnp.asarray(Q @ np.diag([0.95, -0.5, 0.3]) @ Q.T)
    c = jnp.asarray(rng.normal(size=n))
    x_star = np.linalg.solve(np.eye(n) - np.asarray(M), np.asarray(c))
    a = anderson_init(jnp.zeros(n), 3)
    for _ in range(n + 2):
        a = anderson_step(a, M @ a.x + c)
    np.testing.assert_allclose(a.x, x_star, atol=1e-8)
    x = jnp.zeros(n)
    for _ in range(n + 2):
        x = M @ x + c
    assert np.max(np.abs(x - x_star)) > 1e-2  # the plain iteration is far from it
