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

__all__ = ["check_iterations", "loop_parts", "run_fixed", "run_while", "still_running"]


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
) -> Any:
    """Iterate ``step`` until ``converged`` (eq.Convergence), ``max_iter`` or a
    non-finite residual. ``state`` needs ``iteration`` and ``primal`` fields;
    ``point`` / ``at`` map it to and from the accelerated vector (``anderson`` > 0)."""

    def cond(st: Any) -> Any:
        return still_running(st, converged, max_iter)

    carry, body, iterate_of = loop_parts(step, state, anderson, point, at)
    return iterate_of(jax.lax.while_loop(lambda c: cond(iterate_of(c)), body, carry))


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
