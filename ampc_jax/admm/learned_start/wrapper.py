"""A formulation started from a learned start: :class:`LearnedStart`, an
:class:`~ampc_jax.admm.core.ADMMSolver` wrapping one, and :func:`start_state`,
the predicted iterate."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ...problem.data import ProblemData
from ...results import SolveResult
from ..core import ADMMSolver
from ..params import SolverParams
from ..runners import still_running
from .network import (
    FEATURE_CLIP,
    KINDS,
    StartArrays,
    StartModel,
    input_of,
    mlp,
    n_features,
    problem_features,
)

__all__ = ["LearnedStart", "StartSetup", "start_state"]


def start_state(
    arrays: StartArrays,
    kind: str,
    solver: ADMMSolver,
    setup: Any,
    data: ProblemData,
    prev: Any,
) -> Any:
    """The predicted start of one solve (iteration 0, residuals inf).

    ``setup``: the formulation's (a ``"step"`` network's inputs u become a state by
    :meth:`ADMMSolver.start_from_inputs`); ``prev``: the previous iterate
    (:meth:`ADMMSolver.init`'s state; the cold start when there is none), read
    by a ``"loop"`` network and kept for its U.
    """
    feats = problem_features(data)
    if kind == "loop":
        feats = jnp.concatenate([feats, solver.point(prev)])
    x = jnp.clip((feats - arrays.input_mean) / arrays.input_scale, -FEATURE_CLIP, FEATURE_CLIP)
    y = mlp(arrays.layers, x)
    if kind == "loop":
        step = arrays.out_mean + arrays.out_scale * y
        st = solver.at(solver.point(prev) + arrays.out_mask * step, prev)
        return st._replace(Z=jnp.maximum(st.Z, 0.0))
    if kind != "step":
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    N, n_u = data.lb.shape
    out = arrays.out_mask * (arrays.out_mean + arrays.out_scale * y)
    u = input_of(out.reshape(N, n_u), data)
    return solver.start_from_inputs(setup, data, u, prev)


class StartSetup(NamedTuple):
    """:class:`LearnedStart`'s setup: the formulation's own, the schedule's k setups
    (stacked on a leading axis; None without a schedule), the step's data and the
    model's arrays (what :meth:`LearnedStart.init` predicts from)."""

    main: Any
    schedule: Any
    data: ProblemData
    arrays: StartArrays


@dataclass(frozen=True)
class LearnedStart(ADMMSolver):
    """``inner`` started from a :class:`StartModel`'s prediction and schedule.

    The core protocol delegates to ``inner`` except ``setup`` (also the
    schedule's factorisations) and ``init`` (the prediction, then the k
    scheduled iterations). With a ``"step"`` model a given ``warm`` state wins
    over the prediction; a ``"loop"`` model reads it (the cold start when none).
    ``inner`` must serve a learned start (``info.learned_start``: its iterate is
    an :class:`~ampc_jax.admm.state.ADMMState` and it implements
    :meth:`~ampc_jax.admm.core.ADMMSolver.start_from_inputs`). Nothing else of
    ``inner`` is reached through the wrapper: its own views (``local_inputs``,
    ``state_of``, ...) are ``inner``'s.
    """

    inner: ADMMSolver
    model: StartModel

    def __post_init__(self) -> None:
        info = self.inner.info
        if info is None or not info.learned_start:
            raise ValueError(
                f"warm_start: {type(self.inner).__name__} serves no learned start "
                f"(its info.learned_start is not set)"
            )
        why = self.model.mismatch(self.inner)
        if why is not None:
            raise ValueError(f"warm_start: the start network does not fit this problem: {why}")

    @property
    def topology(self) -> Any:  # type: ignore[override]
        return self.inner.topology

    @property
    def max_iter(self) -> int:  # type: ignore[override]
        return self.inner.max_iter

    @property
    def anderson(self) -> int:  # type: ignore[override]
        return self.inner.anderson

    @property
    def n_rho(self) -> int:
        return self.inner.n_rho

    @property
    def finish_every(self) -> int:  # type: ignore[override]
        return int(getattr(self.inner, "finish_every", 1))

    @property
    def finish_first(self) -> int:  # type: ignore[override]
        return int(getattr(self.inner, "finish_first", 1))

    def finisher(self, setup: StartSetup) -> Any:
        """``inner``'s exact finish on its own setup (None where it has none)."""
        return self.inner.finisher(setup.main)

    def setup_from(self, data: ProblemData, params: SolverParams | None, warm: Any) -> StartSetup:
        """:meth:`setup` reusing what ``warm`` carries (``inner``'s
        :meth:`~ampc_jax.admm.core.ADMMSolver.setup_from`: a carried rho_j*)."""
        return self.setup_with(data, params, self.model.arrays(data.A.dtype), warm=warm)

    def setup_with(
        self,
        data: ProblemData,
        params: SolverParams | None,
        arrays: StartArrays,
        warm: Any = None,
    ) -> Any:
        """:meth:`setup` with the model's numbers given as ``arrays`` (for training);
        ``warm``: the state the solve starts from (what ``inner``'s setup may reuse)."""
        n_in = n_features(data) + (self.model.n_point if self.model.kind == "loop" else 0)
        if self.model.input_mean.shape[0] != n_in:
            raise ValueError(
                f"warm_start: the start network reads {self.model.input_mean.shape[0]} "
                f"inputs, this problem's step gives {n_in} (trained for another problem)"
            )
        dt = data.A.dtype
        p = self.inner.params(dtype=dt) if params is None else params
        main = self.inner.setup_from(data, p, warm)
        sched = None
        if arrays.schedule_rho.shape[0]:
            rho = jnp.asarray(p.rho, dt)

            def one(r: Any, a: Any) -> Any:
                return self.inner.setup_from(data, p._replace(rho=rho * r, relaxation=a), warm)

            sched = jax.vmap(one)(arrays.schedule_rho, arrays.schedule_relaxation)
        return StartSetup(main, sched, data, arrays)

    def setup(self, data: ProblemData, params: SolverParams | None = None) -> StartSetup:
        """The formulation's setup, the schedule's k setups and the model's arrays."""
        return self.setup_with(data, params, self.model.arrays(data.A.dtype))

    def init(self, setup: StartSetup, warm: Any = None) -> Any:
        """The predicted start, then the scheduled iterations (counted)."""
        prev = self.inner.init(setup.main, warm)
        if self.model.kind == "step" and warm is not None:
            start = prev
        else:
            start = start_state(
                setup.arrays, self.model.kind, self.inner, setup.main, setup.data, prev
            )
        if setup.schedule is None:
            return start

        def body(st: Any, s_k: Any) -> tuple[Any, None]:
            go = still_running(
                st, lambda x: self.inner.converged(setup.main, x), self.inner.max_iter
            )
            new = self.inner.step(s_k, st)
            return jax.tree.map(lambda a, b: jnp.where(go, a, b), new, st), None

        return jax.lax.scan(body, start, setup.schedule)[0]

    def step(self, setup: StartSetup, state: Any) -> Any:
        return self.inner.step(setup.main, state)

    def converged(self, setup: StartSetup, state: Any) -> Any:
        return self.inner.converged(setup.main, state)

    def result(self, setup: StartSetup, state: Any) -> SolveResult:
        return self.inner.result(setup.main, state)

    def point(self, state: Any) -> Any:
        return self.inner.point(state)

    def at(self, x: Any, state: Any) -> Any:
        return self.inner.at(x, state)

    def cold_state(self, dtype: Any = None) -> Any:
        return self.inner.cold_state(dtype)

    def shift(self, state: Any, steps: int = 1) -> Any:
        return self.inner.shift(state, steps)
