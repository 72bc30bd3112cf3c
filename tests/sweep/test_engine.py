"""The sweep engine: per-pair freezing and compaction give each pair the
iteration count and solution it gets alone; the work counts."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import formulation
from ampc_jax.sweep import bucket_sizes, family, pair_data, pair_params, solve_pairs

pytestmark = pytest.mark.timeout(240)


def _pairs(name, n, points, solver_name="local_explicit", tol=1e-8, **opts):
    cases = family(name).sample(n, seed=3)
    solver = formulation(solver_name, cases.topology, **opts)
    rho = np.asarray(points)[:, None] * np.ones((1, solver.n_rho))
    grid = solver.params(rho=rho, tol_primal=tol, tol_dual=tol)
    return solver, pair_data(cases.data, len(points)), pair_params(grid, n)


def _one(tree, q):
    return jax.tree.map(lambda x: x[q], tree)


def test_bucket_ladder():
    assert bucket_sizes(100, 16) == (100, 50, 25)
    assert bucket_sizes(8, 16) == (8,)
    assert bucket_sizes(64, 8) == (64, 32, 16, 8)


def test_frozen_pairs_report_their_own_iterations():
    solver, d, p = _pairs("generated", 6, [0.2, 1.0, 5.0], max_iter=400)
    plain, w0 = jax.jit(lambda d, p: solve_pairs(solver, d, p, compaction=False))(d, p)
    comp, w1 = jax.jit(lambda d, p: solve_pairs(solver, d, p, segment=8, min_bucket=2))(d, p)
    solo = jax.jit(solver.solve)
    its = np.asarray(comp.iterations)
    assert its.min() < its.max()  # the batch has a spread, or the test proves nothing
    np.testing.assert_array_equal(its, plain.iterations)
    for q in range(len(its)):
        r = solo(_one(d, q), _one(p, q))
        assert int(r.iterations) == its[q], q
        np.testing.assert_allclose(comp.u0[q], r.u0, rtol=1e-9, atol=1e-9)
        assert int(r.status) == int(comp.status[q])
    # the work: vmap computes B * max, compaction less; both need the sum
    assert int(w0.needed) == int(w1.needed) == its.sum()
    assert int(w0.computed) == len(its) * its.max()
    assert its.sum() <= int(w1.computed) < int(w0.computed)


def test_chunked_iterations_give_each_pair_its_own_result():
    # 18 pairs in chunks of 4: five chunks, the last padded with two copies
    solver, d, p = _pairs("generated", 6, [0.2, 1.0, 5.0], max_iter=400)
    whole, w0 = jax.jit(lambda d, p: solve_pairs(solver, d, p, segment=8, min_bucket=2))(d, p)
    parts, w1 = jax.jit(lambda d, p: solve_pairs(solver, d, p, segment=8, min_bucket=2, chunk=4))(
        d, p
    )
    its = np.asarray(whole.iterations)
    assert its.min() < its.max()
    np.testing.assert_array_equal(parts.iterations, its)
    np.testing.assert_array_equal(parts.status, whole.status)
    np.testing.assert_allclose(parts.u0, whole.u0, rtol=1e-9, atol=1e-9)
    assert int(w1.needed) == int(w0.needed) == its.sum()  # the padding's work is not needed
    assert its.sum() <= int(w1.computed)
    with pytest.raises(ValueError, match="chunk"):
        solve_pairs(solver, d, p, chunk=0)


@pytest.mark.slow
def test_anderson_counts_agree_to_round_off():
    # Anderson's least squares amplifies last-bit differences between batch
    # sizes (vectorised code differs), so counts of slow pairs move by a few %
    solver, d, p = _pairs("generated", 4, [0.3, 3.0], max_iter=400, anderson=2)
    plain, _ = jax.jit(lambda d, p: solve_pairs(solver, d, p, compaction=False))(d, p)
    comp, _ = jax.jit(lambda d, p: solve_pairs(solver, d, p, segment=8, min_bucket=2))(d, p)
    np.testing.assert_array_equal(comp.converged, plain.converged)
    np.testing.assert_allclose(comp.iterations, plain.iterations, rtol=0.15)


def test_vehicle_family_and_violation():
    solver, d, p = _pairs("cruise_step", 16, [1.0], tol=1.0, max_iter=300)
    out, work = jax.jit(lambda d, p: solve_pairs(solver, d, p))(d, p)
    assert np.all(np.asarray(out.converged))
    assert np.all(np.asarray(out.violation) >= 0)
    # u0 is projected on the bounds, the general rows of cruise are boxes: no violation
    assert float(np.max(out.violation)) < 1e-6
    assert work.waste >= 1.0


@pytest.mark.parametrize("name", ["fully_distributed", "integrated"])
def test_other_formulations(name):
    solver, d, p = _pairs("generated", 3, [1.0, 3.0], solver_name=name, max_iter=300)
    out, _ = jax.jit(lambda d, p: solve_pairs(solver, d, p, segment=4, min_bucket=2))(d, p)
    solo = jax.jit(solver.solve)
    for q in range(6):
        r = solo(_one(d, q), _one(p, q))
        assert int(r.iterations) == int(out.iterations[q])
        np.testing.assert_allclose(out.u0[q], r.u0, rtol=1e-8, atol=1e-8)


def test_float32_runs():
    cases = family("cruise_step").sample(8, seed=0, dtype=jnp.float32)
    solver = formulation("local_explicit", cases.topology, max_iter=300)
    grid = solver.params(rho=[[1.0, 1.0]], tol_primal=1.0, tol_dual=1.0, dtype=jnp.float32)
    out, _ = jax.jit(lambda d, p: solve_pairs(solver, d, p))(
        pair_data(cases.data, 1), pair_params(grid, 8)
    )
    assert out.u0.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(out.u0)))
    assert np.mean(np.asarray(out.converged)) > 0.8


def test_the_engine_takes_the_core_protocol_only():
    """Any ADMMSolver runs, through its public protocol methods (no duck typing,
    no private attribute); anything else is refused naming the formulation."""
    import ast
    import pathlib

    import ampc_jax.sweep.engine as engine

    tree = ast.parse(pathlib.Path(engine.__file__).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            assert node.func.id not in ("hasattr", "getattr"), ast.unparse(node)
        if isinstance(node, ast.Attribute) and node.attr.startswith("_"):
            assert node.attr.startswith("__"), ast.unparse(node)
    cases = family("generated").sample(1, seed=0)
    with pytest.raises(TypeError, match="formulation: expected an ADMM formulation"):
        solve_pairs(object(), cases.data, None)


def test_refill_gives_each_pair_its_own_result():
    """Continuous batching (3 slots for 12 pairs): each pair's iterations and
    solution are those of the unbatched solve; no slot idles while pairs wait."""
    solver, d, p = _pairs("generated", 4, [0.2, 1.0, 5.0], max_iter=400)
    plain, w0 = jax.jit(lambda d, p: solve_pairs(solver, d, p, compaction=False))(d, p)
    refill, w1 = jax.jit(lambda d, p: solve_pairs(solver, d, p, segment=8, chunk=3, refill=True))(
        d, p
    )
    its = np.asarray(plain.iterations)
    assert its.min() < its.max()
    np.testing.assert_array_equal(refill.iterations, its)
    np.testing.assert_array_equal(refill.status, plain.status)
    np.testing.assert_allclose(refill.u0, plain.u0, rtol=1e-9, atol=1e-9)
    assert int(w1.needed) == its.sum()
    # slots x segment per segment: at most one segment's rounding per pair, plus the
    # tail once no pair waits
    assert its.sum() <= int(w1.computed) <= its.sum() + len(its) * 8 + 3 * its.max()
