"""ampc_jax.admm.params: SolverParams, validated where concrete, batched by broadcasting."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.params import SolverParams, as_params, solver_params

pytestmark = pytest.mark.timeout(60)


def test_defaults_and_dtype():
    p = solver_params(3)
    assert p.rho.shape == (3,) and p.relaxation.shape == ()
    np.testing.assert_array_equal(p.rho, 1.0)
    assert float(p.relaxation) == 1.0 and float(p.tol_primal) == float(p.tol_dual) == 1e-6
    assert float(p.tol_rel) == 0.0  # the absolute rule alone, by default
    p32 = solver_params(2, rho=[0.5, 2.0], dtype=jnp.float32)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(p32))


def test_batch_axes_broadcast_to_one_shape():
    p = solver_params(2, rho=np.ones((5, 2)), relaxation=np.linspace(1.0, 1.8, 5))
    assert jax.tree.map(jnp.shape, p) == SolverParams((5, 2), (5,), (5,), (5,), (5,))
    q = solver_params(2, rho=0.5, relaxation=np.linspace(1.0, 1.8, 4))
    assert q.rho.shape == (4, 2)  # a scalar rho under a batched relaxation
    with pytest.raises(ValueError, match="params: batch shapes do not broadcast"):
        solver_params(2, rho=np.ones((5, 2)), relaxation=np.ones(4))


@pytest.mark.parametrize(
    "kw,field",
    [
        ({"rho": -1.0}, "rho"),
        ({"rho": 0.0}, "rho"),
        ({"rho": float("nan")}, "rho"),
        ({"rho": [1.0, 2.0, 3.0]}, "rho"),
        ({"rho": True}, "rho"),
        ({"relaxation": 2.0}, "relaxation"),
        ({"relaxation": 0.0}, "relaxation"),
        ({"tol_primal": -1e-3}, "tol_primal"),
        ({"tol_dual": float("inf")}, "tol_dual"),
        ({"tol_dual": "a"}, "tol_dual"),
        ({"tol_rel": -1e-6}, "tol_rel"),
        ({"tol_rel": float("nan")}, "tol_rel"),
    ],
)
def test_bad_values_name_the_field(kw, field):
    with pytest.raises(ValueError, match=f"^{field}: expected"):
        solver_params(2, **kw)


def test_traced_values_are_not_checked_and_as_params_casts():
    out = jax.jit(lambda r: solver_params(2, rho=r).rho)(jnp.asarray(-1.0))
    np.testing.assert_array_equal(out, [-1.0, -1.0])  # inside jit: no check (no error)
    p = as_params(SolverParams(0.5, 1.5, 1e-3, 1e-3, 0.0), 3, jnp.float32)
    assert p.rho.shape == (3,) and p.rho.dtype == jnp.float32
    with pytest.raises(TypeError, match="params: expected a SolverParams"):
        as_params((1.0, 1.0, 1e-6, 1e-6), 2, jnp.float64)
    with pytest.raises(ValueError, match=r"params.rho: expected \(\) or \(2,\)"):
        as_params(solver_params(2, rho=np.ones((4, 2))), 2, jnp.float64)
