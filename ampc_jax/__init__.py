"""ampc-jax: multi-objective agent-based MPC (consensus ADMM, Local Explicit) in pure JAX.

Importing the package appends ``--xla_cpu_multi_thread_eigen=false`` and
``--xla_cpu_enable_concurrency_optimized_scheduler=false`` to ``XLA_FLAGS``
(unless ``AMPC_KEEP_XLA_FLAGS=1`` is set): an early mitigation of a deadlock
of batched XLA:CPU programs on small (2-core) machines. The deadlock's cause
was later found in XLA:CPU's batched LAPACK kernels, which the solvers no
longer call under ``vmap`` (README, "Known issues"). The flags only take effect
if JAX's CPU backend has not started yet, so import ``ampc_jax`` first.
"""

import os as _os

__version__ = "0.1.0"

XLA_WORKAROUND_FLAGS = (
    "--xla_cpu_multi_thread_eigen=false",
    "--xla_cpu_enable_concurrency_optimized_scheduler=false",
)


def _apply_xla_workaround() -> None:
    if _os.environ.get("AMPC_KEEP_XLA_FLAGS") == "1":
        return
    flags = _os.environ.get("XLA_FLAGS", "")
    missing = [f for f in XLA_WORKAROUND_FLAGS if f.split("=")[0] not in flags]
    if missing:
        _os.environ["XLA_FLAGS"] = " ".join([flags, *missing]).strip()


_apply_xla_workaround()
