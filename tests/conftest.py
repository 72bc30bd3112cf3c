"""Shared test configuration: float64 by default (float32 is tested explicitly).

``ampc_jax`` is imported before JAX runs anything so that its XLA:CPU
deadlock workaround (README, "Known issues") is in force for every test.
"""

import jax

import ampc_jax  # noqa: F401  (sets XLA_FLAGS before the CPU backend starts)

jax.config.update("jax_enable_x64", True)
