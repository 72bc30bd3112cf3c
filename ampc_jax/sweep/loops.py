"""Closed-loop sweeps: whole manoeuvres of a loop family against a grid of rho scales.

Every (case, point) pair is one closed loop of K control steps (plant, driver,
controller, the integrated shadow for e_sub) under ``lax.scan``; the pairs are
vmapped in one compiled program (:func:`~ampc_jax.batch.map_scenarios`:
chunks, sharded over the devices of this process). Each pair is reduced in
the program to the numbers a table row keeps (:class:`LoopRow`), so a sweep
never holds the per-step logs of more than one chunk.

Within a closed loop the solves are ``while_loop`` s inside a ``scan``: every
step of every pair in a chunk waits for the chunk's slowest solve of that
step, and compaction across pairs does not apply (the pairs' steps are
coupled through the plant). Sweeps of single steps
(:mod:`~ampc_jax.sweep.engine`) are where compaction pays.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..batch import map_scenarios
from ..results import Status

__all__ = ["LoopRow", "loop_pairs"]


class LoopRow(NamedTuple):
    """One closed-loop pair, reduced (shapes for one pair).

    iterations : mean controller iterations per step; iterations_max, iterations_p95.
    converged : every step's solve met eq.Convergence (status 0).
    fallbacks : steps whose command the guard replaced.
    e_sub_max : the largest |U^(0) - U*^(0)| over steps and inputs (Nm), the
        integrated shadow as U*.
    yaw_rms : RMS of yaw rate - eq.CC_objective's reference over the run (rad/s).
    slip_max : the largest |longitudinal slip| of a wheel.
    torque_max : the largest |wheel torque| sent (Nm).
    """

    iterations: Any
    iterations_max: Any
    iterations_p95: Any
    converged: Any
    fallbacks: Any
    e_sub_max: Any
    yaw_rms: Any
    slip_max: Any
    torque_max: Any


def _reduce(log: Any) -> LoopRow:
    it = log.iterations.astype(jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    k = it.shape[0]
    srt = jnp.sort(it)
    e = jnp.where(jnp.isfinite(log.e_sub), log.e_sub, -jnp.inf)
    return LoopRow(
        iterations=jnp.mean(it),
        iterations_max=jnp.max(log.iterations),
        iterations_p95=srt[min(k - 1, int(np.ceil(0.95 * k)) - 1)],
        converged=jnp.all(log.status == Status.SOLVED),
        fallbacks=jnp.sum(log.fallback),
        e_sub_max=jnp.max(e),
        yaw_rms=jnp.sqrt(jnp.mean((log.yaw_rate - log.yaw_ref) ** 2)),
        slip_max=jnp.max(jnp.abs(log.slip)),
        torque_max=jnp.max(jnp.abs(log.torques)),
    )


def loop_pairs(
    config: Any,
    scenarios: Any,
    rho: Any,
    n_steps: int,
    *,
    dtype: Any = None,
    chunk: int = 8,
) -> LoopRow:
    """Closed loops of ``config`` for every case of ``scenarios`` (leading axis C)
    and every rho scale of ``rho`` (P,): rho_j = scale * eq.opt_ro's rho_j* for
    every objective (as a single-step sweep; not relative to the config's own
    ``rho_scale``). Pairs case-major; returns a :class:`LoopRow` with a leading
    axis of C * P. One program per (simulator, steps, chunk), reused across calls."""
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    base = config.loop_params(dt)
    rho = jnp.asarray(rho, dt)
    P = int(rho.shape[0])
    C = int(np.shape(scenarios.mu)[0])
    sc = jax.tree.map(
        lambda x: jnp.repeat(
            jnp.asarray(x, dt) if np.issubdtype(np.asarray(x).dtype, np.floating) else x,
            P,
            axis=0,
        ),
        scenarios,
    )
    n_rho = base.controller.solver.rho.shape[-1]
    pts = jnp.broadcast_to(jnp.tile(rho, C)[:, None], (C * P, n_rho))
    from ..closed_loop.loop import simulator_for

    return _program(simulator_for(config), int(n_steps), int(chunk))(sc, pts, base)


@functools.lru_cache(maxsize=8)
def _program(sim: Any, n_steps: int, chunk: int) -> Any:
    from ..closed_loop.loop import run_closed_loop

    def run(sc: Any, pts: Any, base: Any) -> LoopRow:
        def one(x: tuple) -> LoopRow:
            s, r = x
            solver = base.controller.solver._replace(rho=r)
            p = base._replace(controller=base.controller._replace(solver=solver))
            return _reduce(run_closed_loop(sim, s, p, n_steps))

        return map_scenarios(one, (sc, pts), chunk=chunk)

    # a closed loop's options (no LLVM optimisation passes): on 2 cores the
    # 20-case sweep's program compiled in minutes with XLA's defaults and its run
    # is shorter than that compile (bench/bench_compile.py, "sweep closed loops")
    from ..closed_loop.compile import loop_compiler_options

    return jax.jit(run, compiler_options=loop_compiler_options() or None)
