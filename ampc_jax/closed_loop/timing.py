"""eq.t_ratio, measured by replaying a closed loop's logged control steps.

The time ratio r_time = t_distributed / t_integrated cannot be timed inside a
compiled scan, so :func:`replay_timing` replays the logged
:class:`~ampc_jax.problem.ProblemData` through both solvers' compiled steps.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from ..formulations import PAPER_ITERATION, IntegratedADMM
from ..results import usable
from .config import SimConfig
from .controller import controller_for
from .log import SimLog

__all__ = ["replay_timing"]


def replay_timing(
    config: SimConfig,
    log: SimLog,
    repeats: int = 3,
    progress: Callable[[int], Any] | None = None,
) -> dict[str, np.ndarray]:
    """Time eq.t_ratio per step by replaying the logged ProblemData.

    What is timed, for both Local Explicit and IntegratedADMM: one call of an
    ahead-of-time compiled full control step on the logged
    :class:`ProblemData`, its :class:`~ampc_jax.admm.SolverParams` an argument -- local costs (H_j, E_j), rho (eq.opt_ro), Cholesky
    factorisation, the ADMM ``while_loop`` to the *controller's* tolerance
    ``config.tol_primal``, ``config.tol_dual`` and the result -- with ``block_until_ready``; the median of
    ``repeats`` calls per step. Building the model and ``make_data`` are not
    timed (identical for both). Both use ``config.relaxation`` and ``config.finish``; Local Explicit
    scales eq.opt_ro's rho* by ``config.rho_scale`` (enabled objectives),
    IntegratedADMM by its own ``config.integrated_rho_scale``, each tuned by
    the same sweep (``docs/results.md``). Warm start: Local Explicit gets the warm state
    it had in the loop; IntegratedADMM is replayed sequentially from its own
    shifted previous solution at the same tolerance (cold at every step when
    ``config.warm_start`` is False).

    ``progress``, if given, is called with 1 after every replayed step (a
    progress bar's ``update``).

    Returns
    -------
    dict with (K,) arrays ``t_distributed``, ``t_integrated`` (s), ``r_time``
    and ``integrated_iterations``, ``distributed_iterations``.
    """
    if not config.mpc or not config.formulation_info.decomposed:
        raise ValueError(
            "replay_timing compares a decomposed formulation with IntegratedADMM; "
            f"got formulation {config.formulation!r}"
        )
    ctrl = controller_for(config)
    T = ctrl.topology
    data, warm = log.data, log.warm
    dtype = data.A.dtype
    le = ctrl.solver
    p_le = config.loop_params(dtype).controller.solver
    ia = IntegratedADMM(
        T,
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
    K = int(np.shape(log.t)[0])
    cold_i = ia.cold_state(dtype)
    d0 = jax.tree.map(lambda x: x[0], data)
    w0 = jax.tree.map(lambda x: x[0], warm)
    f_le = jax.jit(le.solve).lower(d0, p_le, w0).compile()
    f_ia = jax.jit(ia.solve).lower(d0, p_ia, cold_i).compile()
    datas = [jax.device_put(jax.tree.map(lambda x, k=k: np.asarray(x[k]), data)) for k in range(K)]
    warms = [jax.device_put(jax.tree.map(lambda x, k=k: np.asarray(x[k]), warm)) for k in range(K)]
    t_d = np.zeros(K)
    t_i = np.zeros(K)
    it_d = np.zeros(K, int)
    it_i = np.zeros(K, int)
    w_i = cold_i
    for k in range(K):
        jax.block_until_ready(f_le(datas[k], p_le, warms[k]))  # warm caches
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = jax.block_until_ready(f_le(datas[k], p_le, warms[k]))
            ts.append(time.perf_counter() - t0)
        t_d[k] = np.median(ts)
        it_d[k] = int(r.iterations)
        jax.block_until_ready(f_ia(datas[k], p_ia, w_i))
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = jax.block_until_ready(f_ia(datas[k], p_ia, w_i))
            ts.append(time.perf_counter() - t0)
        t_i[k] = np.median(ts)
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
    }
