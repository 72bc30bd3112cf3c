"""Many scenarios at once: chunked ``vmap`` with early exit, sharded over devices.

``jax.vmap`` of a solver's ``while_loop`` runs every case until the slowest
converges, and a large batch's factorised matrices no longer fit in cache.
:func:`map_scenarios` instead vmaps ``chunk`` cases at a time and scans over
the chunks (``jax.lax.map(..., batch_size=chunk)``), so each chunk stops at its
own slowest case and iterates on cache-resident data; with several devices the
leading axis is split across them with ``jax.shard_map`` (each device maps over
its own share). On CPU, ``XLA_FLAGS=--xla_force_host_platform_device_count=N``
(set before JAX starts) gives N devices, one per core.

Rule: chunks (16 to 64 cases) rather than one ``vmap`` of the whole batch;
reason: each chunk stops at its own slowest case and stays in cache, several
times the throughput of one ``vmap`` of 1,024 drives on one core
(``bench/bench_local_explicit.py --only throughput``, docs/benchmarks.md
"Batched throughput").

Deadlock (docs/known-issues.md): XLA:CPU's batched LAPACK kernels
(Cholesky, triangular solve, LU, eigh) split their batch into tasks on the
intra-op thread pool they themselves run on and block until those finish.
With two CPU devices on two cores both pool threads can be such a kernel, and
nothing is left to run the tasks. The solvers' batched factorisations are
therefore pure JAX (:mod:`ampc_jax.admm.linalg`), and a vmapped solve contains
no LAPACK call (``tests/batch/test_batch.py`` checks both). The exact ``rho_method="eigh"`` and
rank-deficient constraint rows still use LAPACK eigensolvers: shard those
with one device per process, or under a timeout.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec

__all__ = ["map_scenarios", "pad_cases"]


def _leading(xs: Any) -> int:
    sizes = {int(np.shape(x)[0]) for x in jax.tree.leaves(xs)}
    if len(sizes) != 1:
        raise ValueError(f"xs: every leaf needs the same leading (batch) size, got {sorted(sizes)}")
    return sizes.pop()


def pad_cases(xs: Any, n: int) -> Any:
    """The pytree ``xs`` with its leading (batch) axis padded to ``n`` by copies of
    its last case (a batch that splits evenly over devices or chunks)."""
    have = _leading(xs)
    if have == n:
        return xs
    return jax.tree.map(
        lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], n - have, axis=0)], axis=0), xs
    )


def map_scenarios(
    fn: Callable[[Any], Any],
    xs: Any,
    *,
    chunk: int = 32,
    devices: Sequence[Any] | None = None,
) -> Any:
    """``fn`` applied to every case along the leading axis of the pytree ``xs``.

    Parameters
    ----------
    fn : a function of one case (a pytree without the batch axis), jittable.
    xs : pytree whose leaves share a leading batch axis of size B.
    chunk : cases vmapped together; chunks run one after another (per device).
    devices : devices to shard the batch over (default: all of
        ``jax.devices()``). The batch is padded with copies of its last case
        to a multiple of the device count; the padding is dropped from the result.

    Returns the stacked outputs, leading axis B. Call it inside ``jax.jit`` (or
    wrap it) to compile once.
    """
    if int(chunk) < 1:
        raise ValueError(f"chunk: expected a positive integer, got {chunk}")
    B = _leading(xs)
    devs = list(jax.devices() if devices is None else devices)
    if len(devs) <= 1:
        return jax.lax.map(fn, xs, batch_size=min(int(chunk), B))
    n = len(devs)
    pad = (-B) % n
    xs = pad_cases(xs, B + pad)
    mesh = jax.sharding.Mesh(np.asarray(devs), ("scenarios",))
    per = (B + pad) // n
    spec = PartitionSpec("scenarios")

    def local(x: Any) -> Any:
        return jax.lax.map(fn, x, batch_size=min(int(chunk), per))

    out = jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)(xs)
    return jax.tree.map(lambda y: y[:B], out) if pad else out
