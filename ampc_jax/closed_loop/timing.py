"""eq.t_ratio, measured by replaying a closed loop's logged control steps.

The time ratio r_time = t_distributed / t_integrated cannot be timed inside a
compiled scan, so :func:`replay_timing` replays the logged
:class:`~ampc_jax.problem.ProblemData` through both solvers' compiled steps.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

from ..formulations import PAPER_ITERATION, IntegratedADMM
from ..results import usable
from .compile import cores
from .config import SimConfig
from .controller import controller_for
from .log import SimLog

__all__ = ["ReplayPrograms", "lower_replay", "replay_programs", "replay_timing"]


class ReplayPrograms(NamedTuple):
    """The two single-step programs the replay times, and what they are called with."""

    local: Any  # the controller's formulation: solve(data, params, warm)
    integrated: Any  # IntegratedADMM: solve(data, params, warm)
    local_params: Any
    integrated_params: Any
    integrated_solver: IntegratedADMM


def _solvers(config: SimConfig, dtype: Any) -> tuple[Any, Any, IntegratedADMM, Any]:
    ctrl = controller_for(config)
    le = ctrl.solver
    p_le = config.loop_params(dtype).controller.solver
    ia = IntegratedADMM(
        ctrl.topology,
        max_iter=max(config.max_iter, 2000),
        anderson=config.anderson,
        **{**PAPER_ITERATION, "finish": config.finish},
    )
    p_ia = ia.params(
        rho=config.integrated_rho_scale,
        relaxation=config.relaxation,
        tol_primal=config.tol_primal,
        tol_dual=config.tol_dual,
        dtype=dtype,
    )
    return le, p_le, ia, p_ia


def _check(config: SimConfig) -> None:
    if not config.mpc or not config.formulation_info.decomposed:
        raise ValueError(
            "replay_timing compares a decomposed formulation with IntegratedADMM; "
            f"got formulation {config.formulation!r}"
        )


def lower_replay(config: SimConfig, log_shapes: SimLog) -> tuple[Any, Any]:
    """Trace and lower the replay's two programs from the log's shapes alone
    (:meth:`~ampc_jax.closed_loop.loop.PreparedRun.log_shapes`), so that they
    compile while the closed loop still compiles or runs; compile them with
    XLA's defaults (they are timed) and pass them to :func:`replay_timing`
    through :func:`replay_programs`."""
    _check(config)
    step = jax.tree.map(
        lambda s: jax.ShapeDtypeStruct(s.shape[1:], s.dtype), (log_shapes.data, log_shapes.warm)
    )
    dtype = step[0].A.dtype
    le, p_le, ia, p_ia = _solvers(config, dtype)
    return (
        jax.jit(le.solve).lower(step[0], p_le, step[1]),
        jax.jit(ia.solve).lower(step[0], p_ia, ia.cold_state(dtype)),
    )


def replay_programs(config: SimConfig, local: Any, integrated: Any, dtype: Any) -> ReplayPrograms:
    """The compiled programs of :func:`lower_replay` with their parameters."""
    _, p_le, ia, p_ia = _solvers(config, dtype)
    return ReplayPrograms(local, integrated, p_le, p_ia, ia)


def replay_timing(
    config: SimConfig,
    log: SimLog,
    repeats: int = 3,
    progress: Callable[[int], Any] | None = None,
    programs: ReplayPrograms | None = None,
) -> dict[str, Any]:
    """Time eq.t_ratio per step by replaying the logged ProblemData.

    What is timed, for both Local Explicit and IntegratedADMM: one call of an
    ahead-of-time compiled full control step on the logged
    :class:`ProblemData`, its :class:`~ampc_jax.admm.SolverParams` an argument
    -- local costs (H_j, E_j), rho (eq.opt_ro), Cholesky factorisation, the
    ADMM ``while_loop`` to the *controller's* tolerance ``config.tol_primal``,
    ``config.tol_dual`` and the result -- with ``block_until_ready``; per step
    the fastest of ``repeats`` calls after one untimed call, the two solvers'
    calls of a step one after the other. Rule: the fastest, not the median;
    reason: every call repeats the same work, so a slower one was held up by
    something else on the machine (the timeit module's advice); on a machine
    busy with other processes the times still rise (``load`` records the load
    average at the start and the end, and the cores this process may use).
    Building the model and ``make_data`` are not timed (identical for both).
    Both use ``config.relaxation`` and ``config.finish`` (the paper's iteration
    otherwise); Local Explicit scales eq.opt_ro's rho* by
    ``config.rho_scale`` (enabled objectives), IntegratedADMM by its own
    ``config.integrated_rho_scale``, each tuned by the same sweep
    (``docs/results.md``). Warm start: Local Explicit gets the warm state it
    had in the loop; IntegratedADMM is replayed sequentially from its own
    shifted previous solution at the same tolerance (cold at every step when
    ``config.warm_start`` is False).

    ``progress``, if given, is called with 1 after every replayed step (a
    progress bar's ``update``). ``programs``: compiled by the caller
    (:func:`lower_replay`, :func:`replay_programs`); compiled here otherwise.

    Returns
    -------
    dict with (K,) arrays ``t_distributed``, ``t_integrated`` (s), ``r_time``
    and ``integrated_iterations``, ``distributed_iterations``; ``load``: the
    1-minute load average at the start and the end and the cores
    (:func:`~ampc_jax.closed_loop.compile.cores`).
    """
    _check(config)
    log = jax.tree.map(np.asarray, log)  # slices of host arrays: no program per slice
    data, warm = log.data, log.warm
    dtype = data.A.dtype
    if programs is None:
        lo_le, lo_ia = lower_replay(config, jax.tree.map(_shape, log))
        programs = replay_programs(config, lo_le.compile(), lo_ia.compile(), dtype)
    f_le, f_ia = programs.local, programs.integrated
    p_le, p_ia, ia = programs.local_params, programs.integrated_params, programs.integrated_solver
    K = int(np.shape(log.t)[0])
    cold_i = ia.cold_state(dtype)
    load0 = _load()
    t_d = np.zeros(K)
    t_i = np.zeros(K)
    it_d = np.zeros(K, int)
    it_i = np.zeros(K, int)
    w_i = cold_i
    for k in range(K):
        d_k = jax.device_put(jax.tree.map(lambda x, k=k: x[k], data))
        w_k = jax.device_put(jax.tree.map(lambda x, k=k: x[k], warm))
        t_d[k], r = _fastest(lambda d_k=d_k, w_k=w_k: f_le(d_k, p_le, w_k), repeats)
        it_d[k] = int(r.iterations)
        t_i[k], r = _fastest(lambda d_k=d_k, w_i=w_i: f_ia(d_k, p_ia, w_i), repeats)
        it_i[k] = int(r.iterations)
        ok = bool(usable(int(r.status))) and bool(np.all(np.isfinite(np.asarray(r.u))))
        w_i = ia.shift(r.state, config.warm_shift) if (config.warm_start and ok) else cold_i
        if progress is not None:
            progress(1)
    return {
        "t_distributed": t_d,
        "t_integrated": t_i,
        "r_time": t_d / t_i,
        "distributed_iterations": it_d,
        "integrated_iterations": it_i,
        "load": {"start": load0, "end": _load(), "cores": cores()},
    }


def _shape(x: Any) -> jax.ShapeDtypeStruct:
    return jax.ShapeDtypeStruct(np.shape(x), np.asarray(x).dtype)


def _load() -> float | None:
    try:
        return float(os.getloadavg()[0])
    except OSError:  # no load average on this platform
        return None


def _fastest(call: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """(the fastest of ``repeats`` timed calls after one untimed call, the last result)."""
    r = jax.block_until_ready(call())
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        r = jax.block_until_ready(call())
        best = min(best, time.perf_counter() - t0)
    return best, r
