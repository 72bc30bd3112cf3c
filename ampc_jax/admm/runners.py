"""The two runners of an ADMM formulation: to tolerance, and a fixed number of iterations.

After jaxopt's loop module: a ``lax.while_loop`` stops early but has no
reverse-mode derivative (deployment); a ``lax.scan`` of fixed length
differentiates (tuning). Both run a formulation's one-iteration map, plainly
or Anderson-accelerated (:mod:`~ampc_jax.admm.acceleration`); with
acceleration the loop carries the iterate and the history.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from ..validation import check_count
from .acceleration import anderson_init, anderson_step

__all__ = [
    "check_iterations",
    "loop_parts",
    "replace_iterate",
    "run_fixed",
    "run_segment",
    "run_while",
    "still_running",
]


def check_iterations(iterations: Any, name: str = "iterations", low: int = 1) -> int:
    """A static count (iterations, cases, steps): an integer >= ``low``, or a
    ValueError naming ``name`` (:func:`ampc_jax.validation.check_count`)."""
    return check_count(iterations, name, low)


def loop_parts(
    step: Callable[[Any], Any],
    state: Any,
    anderson: int,
    point: Callable[[Any], Any],
    at: Callable[[Any, Any], Any],
) -> tuple[Any, Callable[[Any], Any], Callable[[Any], Any]]:
    """The loop's initial carry, one iteration, and the iterate inside the carry
    (the pieces :func:`run_while`, :func:`run_fixed` and the sweep's segmented
    runner, :mod:`ampc_jax.sweep.engine`, are built from)."""
    if not anderson:
        return state, step, lambda st: st

    def accelerated(carry: tuple) -> tuple:
        st, a = carry
        out = step(at(a.x, st))
        return out, anderson_step(a, point(out))

    return (state, anderson_init(point(state), anderson)), accelerated, lambda c: c[0]


def replace_iterate(carry: Any, state: Any, anderson: int) -> Any:
    """``carry`` (:func:`loop_parts`' form) with its iterate replaced by ``state``."""
    return (state, carry[1]) if anderson else state


def _freeze(go: Any, new: Any, old: Any) -> Any:
    return jax.tree.map(lambda a, b: jnp.where(go, a, b), new, old)


def run_segment(
    body: Callable[[Any], Any],
    iterate_of: Callable[[Any], Any],
    running: Callable[[Any], Any],
    carry: Any,
    length: int,
    *,
    finish: Callable[[Any, Any, Any], Any] | None = None,
    anderson: int = 0,
) -> Any:
    """``length`` iterations of ``body`` on ``carry``, each one only where ``running``
    (a stopped iterate keeps its state and count), then ``finish(before, after,
    ran)`` of the last iteration (None: no finish): the formulation's exact
    finish (:mod:`~.finish`), which returns ``after`` or its verified finish.
    The pieces come from :func:`loop_parts`."""

    def one(c: Any, _: Any) -> tuple[Any, None]:
        return _freeze(running(c), body(c), c), None

    if finish is None:
        return jax.lax.scan(one, carry, None, length=length)[0]
    if length > 1:
        carry = jax.lax.scan(one, carry, None, length=length - 1)[0]
    before = iterate_of(carry)
    go = running(carry)
    if length > 0:
        carry = _freeze(go, body(carry), carry)
    return replace_iterate(carry, finish(before, iterate_of(carry), go), anderson)


def still_running(st: Any, converged: Callable[[Any], Any], max_iter: int) -> Any:
    """Whether :func:`run_while` iterates again from ``st``: under the cap, not
    converged (eq.Convergence) and every residual finite (or none computed yet)."""
    finite = jnp.all(jnp.isfinite(st.primal) | (st.iteration == 0))
    return (st.iteration < max_iter) & ~converged(st) & finite


def run_while(
    step: Callable[[Any], Any],
    converged: Callable[[Any], Any],
    state: Any,
    max_iter: int,
    *,
    anderson: int = 0,
    point: Callable[[Any], Any] | None = None,
    at: Callable[[Any, Any], Any] | None = None,
    finish: Callable[[Any, Any, Any], Any] | None = None,
    every: int = 1,
    first: int = 1,
) -> Any:
    """Iterate ``step`` until ``converged`` (eq.Convergence), ``max_iter`` or a
    non-finite residual. ``state`` needs ``iteration`` and ``primal`` fields;
    ``point`` / ``at`` map it to and from the accelerated vector (``anderson`` > 0).

    With ``finish`` (a formulation's exact finish, ``finish(before, after, ran)``
    -> state): ``first`` iterations (0: none), then segments of ``every`` iterations
    (:func:`run_segment`), each ended by a finish attempt; a verified finish passes ``converged``, so the
    loop stops there. Iteration counts are those of the plain loop."""

    def cond(st: Any) -> Any:
        return still_running(st, converged, max_iter)

    carry, body, iterate_of = loop_parts(step, state, anderson, point, at)
    if finish is None:
        return iterate_of(jax.lax.while_loop(lambda c: cond(iterate_of(c)), body, carry))

    def running(c: Any) -> Any:
        return cond(iterate_of(c))

    def segment(c: Any, length: int) -> Any:
        return run_segment(body, iterate_of, running, c, length, finish=finish, anderson=anderson)

    # the first attempt after ``first`` iterations (0: the start's own active set; a
    # warm start's is often final)
    carry = segment(carry, int(first))
    return iterate_of(jax.lax.while_loop(running, lambda c: segment(c, int(every)), carry))


def run_fixed(
    step: Callable[[Any], Any],
    state: Any,
    iterations: int,
    *,
    anderson: int = 0,
    point: Callable[[Any], Any] | None = None,
    at: Callable[[Any, Any], Any] | None = None,
) -> Any:
    """Exactly ``iterations`` steps under ``lax.scan`` (differentiable)."""
    iterations = check_iterations(iterations)
    carry, body, iterate_of = loop_parts(step, state, anderson, point, at)
    out, _ = jax.lax.scan(lambda c, _: (body(c), None), carry, None, length=iterations)
    return iterate_of(out)
