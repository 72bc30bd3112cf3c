"""ampc_jax.batch.map_scenarios against a plain vmap, on one and on several (forced CPU)
devices; no LAPACK kernel in a batched solve (the deadlock, docs/known-issues.md)."""

import os
import re
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.batch import map_scenarios
from ampc_jax.formulations import LocalExplicit
from ampc_jax.generate import random_problem
from ampc_jax.testing.budget import budget

pytestmark = pytest.mark.timeout(300)


def stack(datas):
    return jax.tree.map(lambda *x: jnp.stack(x), *datas)


@pytest.mark.slow  # on one device; test_sharded_over_two_cpu_devices checks the same
def test_matches_vmap_with_remainder_chunk():
    """One device, 7 cases in chunks of 3. The default run's check is
    test_sharded_over_two_cpu_devices (5 cases in chunks of 2 on two devices: a
    remainder chunk too, the same comparison with vmap, each case's iterations)."""
    problems = [random_problem(seed, 2, shared="all") for seed in range(7)]
    solver = LocalExplicit(problems[0].topology, max_iter=5000)
    q = solver.params(tol_primal=1e-10, tol_dual=1e-10)
    data = stack([p.data() for p in problems])
    ref = jax.jit(jax.vmap(lambda d: solver.solve(d, q)))(data)
    out = jax.jit(lambda d: map_scenarios(lambda x: solver.solve(x, q), d, chunk=3))(data)
    np.testing.assert_allclose(out.u, ref.u, rtol=1e-9, atol=1e-12)
    # per-chunk early exit: each case's own iteration count, as with vmap
    np.testing.assert_array_equal(out.iterations, ref.iterations)


def test_bad_arguments_name_the_field():
    with pytest.raises(ValueError, match="chunk"):
        map_scenarios(lambda x: x, jnp.zeros(3), chunk=0)
    with pytest.raises(ValueError, match="xs"):
        map_scenarios(lambda x: x, (jnp.zeros(3), jnp.zeros(4)))


SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from ampc_jax.batch import map_scenarios
    from ampc_jax.formulations import LocalExplicit
    from ampc_jax.generate import random_problem
    assert len(jax.devices()) == 2, jax.devices()
    ps = [random_problem(s, 2, shared="all") for s in range(5)]
    solver = LocalExplicit(ps[0].topology, max_iter=5000)
    q = solver.params(tol_primal=1e-10, tol_dual=1e-10)
    data = jax.tree.map(lambda *x: jnp.stack(x), *[p.data() for p in ps])
    ref = jax.jit(jax.vmap(lambda d: solver.solve(d, q)))(data)
    out = jax.jit(lambda d: map_scenarios(lambda x: solver.solve(x, q), d, chunk=2))(data)
    assert out.u.shape == ref.u.shape
    np.testing.assert_allclose(out.u, ref.u, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(out.iterations, ref.iterations)  # each case's own
    print("ok", len(out.u.sharding.device_set))
    """
)


@pytest.mark.both_cores
def test_sharded_over_two_cpu_devices():
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    ).strip()
    r = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=budget(240)
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.startswith("ok 2"), r.stdout


# The cruise-sized problem of bench/bench_local_explicit.py at N_p = 20, batch
# 100, sharded over two CPU devices on both cores: before the batched
# factorisations stopped calling LAPACK this deadlocked in every run (the
# batched LAPACK kernels wait on the intra-op thread pool they run on).
HANG_SCRIPT = textwrap.dedent(
    """
    import os
    os.sched_setaffinity(0, range(os.cpu_count()))  # undo the suite's one-core pin
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from ampc_jax.batch import map_scenarios
    from ampc_jax.formulations import LocalExplicit
    from ampc_jax.generate import random_problem
    assert len(jax.devices()) == 2, jax.devices()
    ps = [random_problem(s, 2, shared="all", horizon=20) for s in range(4)]
    solver = LocalExplicit(ps[0].topology, max_iter=300)
    data = jax.tree.map(lambda *x: jnp.stack([x[i % len(x)] for i in range(100)]),
                        *[p.data() for p in ps])
    f = jax.jit(lambda d: map_scenarios(solver.solve, d, chunk=32))
    for _ in range(3):
        out = jax.block_until_ready(f(data))
    assert bool(jnp.all(jnp.isfinite(out.u)))
    print("ok")
    """
)


@pytest.mark.both_cores
def test_sharded_batch_with_factorisations_does_not_deadlock():
    env = dict(os.environ)
    env["XLA_FLAGS"] = (
        env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    ).strip()
    try:
        r = subprocess.run(
            [sys.executable, "-c", HANG_SCRIPT],
            env=env,
            capture_output=True,
            text=True,
            timeout=budget(180),
        )
    except subprocess.TimeoutExpired:
        pytest.fail("sharded batched solve did not finish in 180 s (deadlock)")
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip().endswith("ok"), r.stdout


def test_batched_solve_calls_no_lapack_kernel():
    p = random_problem(0, 2, shared="all", horizon=20)
    solver = LocalExplicit(p.topology)
    data = stack([p.data(), p.data()])
    hlo = jax.jit(jax.vmap(solver.solve)).lower(data).compile().as_text()
    targets = set(re.findall(r'custom_call_target="(\w+)"', hlo))
    assert not any("lapack" in t for t in targets), targets
    # the unbatched solve of the same (large enough) problem does use LAPACK
    hlo1 = jax.jit(LocalExplicit(p.topology, kkt="dense").solve).lower(p.data()).compile()
    assert "lapack" in " ".join(re.findall(r'custom_call_target="(\w+)"', hlo1.as_text()))
