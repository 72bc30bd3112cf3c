"""The one training loop every tuner runs: Adam (optax) on a loss of a pytree of variables.

:func:`fit` minimises ``loss(theta[, batch])`` by ``spec.steps`` Adam steps
(:class:`FitSpec`: learning rate, optional cosine decay, optional treatment of
non-finite gradients and updates, the progress bar), one jitted program per
run (``jax.value_and_grad`` and the optimiser's update), and keeps the
variables it is asked to keep:

* ``select="loss"`` -- the lowest finite loss seen; each step records the loss of
  the variables *before* it, and with ``final`` the variables after the last
  step are evaluated too (the solver's rho scales, the weights);
* a :class:`Validation` -- the lowest validation score, taken before the first
  step and every ``every`` steps (a learned start's iterations to tolerance on
  a held-back split: the loss is only a proxy);
* ``select="last"`` -- the variables after the last step (pretraining).

Every step appends a record to the history (``record``: by default
``{"step": k, "loss": value}``). The tuners (:mod:`.solver`, :mod:`.weights`,
:mod:`.warm_start`) differ in their loss and what they record, not in the loop.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..validation import check_count, check_positive

__all__ = ["FitResult", "FitSpec", "Validation", "fit"]

SELECT = ("loss", "last")
"""Which variables :func:`fit` returns without a :class:`Validation`."""


@dataclass(frozen=True)
class FitSpec:
    """How :func:`fit` trains (validated on construction, ValueError naming the field).

    steps : Adam steps (>= 0).
    lr : the learning rate (positive, finite).
    decay : None (default: a constant rate) or alpha of a cosine decay of the
        rate to ``alpha lr`` over the steps (optax ``cosine_decay_schedule``).
    finite_grads : replace a non-finite gradient entry by 0 (default False), so
        that one case's overflow moves nothing.
    finite_updates : keep the variables where a step makes any of them
        non-finite (default False).
    final : with ``select="loss"``, also evaluate (and record) the variables
        after the last step (default True).
    desc : the progress bar's label; ``progress``: tqdm's ``disable`` negated
        (None: on a terminal only).
    compiler_options : XLA options of the compiled step (None: XLA's defaults;
        e.g. :func:`~ampc_jax.closed_loop.compile.loop_compiler_options` where the
        compile outweighs the steps' run, ``bench/bench_compile.py``).
    """

    steps: int
    lr: float
    decay: float | None = None
    finite_grads: bool = False
    finite_updates: bool = False
    final: bool = True
    desc: str = "tune"
    progress: bool | None = None
    compiler_options: Any = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "steps", check_count(self.steps, "steps", 0))
        object.__setattr__(self, "lr", check_positive(self.lr, "lr"))
        if self.decay is not None and not 0.0 < float(self.decay) <= 1.0:
            raise ValueError(f"decay: expected None or a fraction in (0, 1], got {self.decay!r}")

    def optimizer(self) -> Any:
        """``optax.adam`` at this spec's (decaying) rate."""
        import optax

        if self.decay is None:
            return optax.adam(self.lr)
        rate = optax.cosine_decay_schedule(self.lr, max(self.steps, 1), alpha=self.decay)
        return optax.adam(rate)


class Validation(NamedTuple):
    """Selection by a validation score instead of the loss.

    score : variables -> a comparable score (lower is better; tuples compare in order).
    every : steps between two scores (the last step is always scored).
    record : (step, score) -> the history entry of a score.
    """

    score: Callable[[Any], Any]
    every: int
    record: Callable[[int, Any], dict[str, Any]]


class FitResult(NamedTuple):
    """What :func:`fit` returns.

    theta : the variables selected (lowest loss, best validation score, or last).
    value : their loss or score (inf where no finite loss was seen).
    last : the variables after the last step.
    history : the records appended during the run (also appended to the list
        given as ``history``).
    """

    theta: Any
    value: Any
    last: Any
    history: list[dict[str, Any]]


def _default_record(step: int, theta: Any, value: Any, aux: Any) -> dict[str, Any]:
    return {"step": step, "loss": float(value)}


def _default_postfix(value: Any, aux: Any) -> dict[str, str]:
    return {"loss": f"{float(value):.3e}"}


def _finite(tree: Any) -> bool:
    return all(bool(np.all(np.isfinite(x))) for x in jax.tree.leaves(tree))


def fit(
    loss: Callable[..., Any],
    theta: Any,
    spec: FitSpec,
    *,
    has_aux: bool = False,
    batches: Callable[[int], Any] | None = None,
    select: str = "loss",
    validation: Validation | None = None,
    record: Callable[[int, Any, Any, Any], dict[str, Any]] = _default_record,
    postfix: Callable[[Any, Any], dict[str, str]] = _default_postfix,
    history: list[dict[str, Any]] | None = None,
) -> FitResult:
    """Minimise ``loss`` from ``theta`` by ``spec.steps`` Adam steps (module docstring).

    ``loss(theta)`` (``loss(theta, batch)`` with ``batches``: ``batches(k)`` gives
    step k's batch, e.g. minibatch indices) returns the loss, or (loss, aux)
    with ``has_aux``; it must be jittable and differentiable in ``theta`` (a
    pytree). ``record(k, theta, value, aux)`` makes step k's history entry,
    ``postfix(value, aux)`` the progress bar's figures.
    """
    from tqdm import tqdm

    if select not in SELECT:
        raise ValueError(f"select: expected one of {SELECT}, got {select!r}")
    history = [] if history is None else history
    start = len(history)
    if spec.steps == 0:
        return FitResult(theta, np.inf, theta, history[start:])
    opt = spec.optimizer()
    value_and_grad = jax.value_and_grad(
        loss if has_aux else lambda *a: (loss(*a), None), has_aux=True
    )

    options = dict(spec.compiler_options) if spec.compiler_options else None

    @functools.partial(jax.jit, compiler_options=options)
    def update(th: Any, state: Any, *batch: Any) -> tuple[Any, Any, Any, Any]:
        import optax

        (value, aux), g = value_and_grad(th, *batch)
        if spec.finite_grads:  # a non-finite gradient moves nothing
            g = jax.tree.map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)
        upd, state = opt.update(g, state, th)
        return optax.apply_updates(th, upd), state, value, aux

    def args(k: int) -> tuple:
        return () if batches is None else (batches(k),)

    state = opt.init(theta)
    if validation is not None:
        best = (validation.score(theta), theta)
        history.append(validation.record(0, best[0]))
    else:
        best = (np.inf, theta)
    bar = tqdm(
        range(spec.steps),
        desc=spec.desc,
        disable=None if spec.progress is None else not spec.progress,
    )
    for k in bar:
        new, state, value, aux = update(theta, state, *args(k))
        history.append(record(k, theta, value, aux))  # the loss of theta before the step
        v = float(value)
        if validation is None and select == "loss" and np.isfinite(v) and v < best[0]:
            best = (v, theta)
        bar.set_postfix(**postfix(value, aux))
        theta = new if not spec.finite_updates or _finite(new) else theta
        if validation is not None and ((k + 1) % validation.every == 0 or k + 1 == spec.steps):
            score = validation.score(theta)
            history.append(validation.record(k + 1, score))
            if score < best[0]:
                best = (score, theta)
    if validation is None and select == "loss" and spec.final:
        _, _, value, aux = update(theta, state, *args(spec.steps))  # the final point's loss
        history.append(record(spec.steps, theta, value, aux))
        if np.isfinite(float(value)) and float(value) < best[0]:
            best = (float(value), theta)
    if validation is None and select == "last":
        best = (np.inf, theta)
    return FitResult(best[1], best[0], theta, history[start:])
