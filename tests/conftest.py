"""Shared test configuration: float64 by default (float32 is tested explicitly).

``ampc_jax`` is imported before JAX runs anything so that its XLA:CPU
deadlock workaround (README, "Known issues") is in force for every test.
"""

import os

# Under pytest-xdist (`.ci/run` runs `-n 2`) each worker is pinned to one core
# of its own before JAX starts its thread pools, so that the two workers do
# not compete for a core and timing-window tests see a steady core, as under
# the former `taskset -c 0` run of the whole suite.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
if _WORKER.startswith("gw") and hasattr(os, "sched_setaffinity"):
    _cpus = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {_cpus[int(_WORKER[2:]) % len(_cpus)]})

import jax  # noqa: E402

import ampc_jax  # noqa: F401, E402  (sets XLA_FLAGS before the CPU backend starts)

jax.config.update("jax_enable_x64", True)
