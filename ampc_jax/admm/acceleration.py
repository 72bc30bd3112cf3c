"""Anderson acceleration (type II, Walker and Ni 2011) of an ADMM map, memory <= 3.

The accelerated runner evaluates the ADMM map (Z, gamma) -> (Z+, gamma+) once
per iteration, as the plain one does; the next point is the combination of
the last m + 1 images that minimises the linearised fixed-point residual
(:func:`anderson_step`), with a safeguard that falls back to the plain step
when the residual grows. The fixed points, and so the solution, are ADMM's.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "ANDERSON_MAX",
    "ANDERSON_REG",
    "ANDERSON_SAFEGUARD",
    "AndersonState",
    "anderson_init",
    "anderson_memory",
    "anderson_step",
]

ANDERSON_MAX = 3
"""Largest Anderson memory (its m x m least-squares system is solved in closed form)."""
ANDERSON_REG = 1e-8
"""Tikhonov weight of the Anderson least squares, relative to trace(dF dF')
(at least 1e3 machine epsilons, so float32 stays well conditioned)."""
ANDERSON_SAFEGUARD = 2.0
"""An extrapolated point whose fixed-point residual exceeds this factor times
the previous one is dropped: the history restarts from the last accepted image."""


def anderson_memory(value: Any) -> int:
    """``value`` as an Anderson memory (an integer in 0..``ANDERSON_MAX``), or a
    ValueError naming ``anderson``."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not 0 <= int(value) <= ANDERSON_MAX
    ):
        raise ValueError(
            f"anderson: expected an integer memory in 0..{ANDERSON_MAX} "
            f"(0 = plain ADMM), got {value!r}"
        )
    return int(value)


class AndersonState(NamedTuple):
    """Anderson acceleration's carry (x: the iterate (Z, gamma) flattened).

    The m past points and their images sit in a ring of separate vectors, not
    stacked, and are overwritten in place. Rule: no buffer over 512 bytes in
    the carry, because XLA:CPU runs a program inline only when every buffer is
    that small (or its thunks form a chain); a stacked (m + 1, n) history on
    the cruise example (40 iterate entries) moved the whole step onto the
    thread pool, 113 instead of 76 us (``bench/bench_thunk_graph.py``).
    """

    x: Any  # (n,) where the ADMM map is evaluated next
    X: tuple  # m past points (n,), a ring
    G: tuple  # their images under the ADMM map
    valid: Any  # (m,) which ring slots hold a point
    pos: Any  # () the slot the next accepted point overwrites
    fprev: Any  # () ||g - x|| at the last accepted point (inf after a restart)


def _solve_small(A: Any, b: Any) -> Any:
    """x with A x = b for one (m, m) A, m <= 3, by Cramer's rule.

    Elementwise formulas, which XLA fuses into one kernel (an unrolled
    factorisation was a dozen kernels per iteration on XLA:CPU). A is the
    regularised Gram matrix of :func:`anderson_step`, so det(A) > 0.
    """
    m = A.shape[-1]
    if m == 1:
        return b / A[0]
    if m == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        return jnp.stack([A[1, 1] * b[0] - A[0, 1] * b[1], A[0, 0] * b[1] - A[1, 0] * b[0]]) / det
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    adj = jnp.stack(
        [
            jnp.stack(
                [c00, A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2], A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]]
            ),
            jnp.stack(
                [c01, A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0], A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]]
            ),
            jnp.stack(
                [c02, A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1], A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]]
            ),
        ]
    )
    return jnp.sum(adj * b[None, :], axis=1) / det


def anderson_init(x: Any, m: int) -> AndersonState:
    z = tuple(x for _ in range(m))  # empty slots (valid = 0); masked out until written
    return AndersonState(
        x, z, z, jnp.zeros((m,), x.dtype), jnp.zeros((), jnp.int32), jnp.asarray(jnp.inf, x.dtype)
    )


def anderson_step(a: AndersonState, g: Any) -> AndersonState:
    """Next point of type-II Anderson acceleration, given g = T(a.x).

    With f = g - x and the differences to the m last accepted points and
    images, dF_i = f - (g_i - x_i), dG_i = g - g_i::

        theta = argmin ||f - sum_i theta_i dF_i||^2 + lambda ||theta||^2,
        x_next = g - sum_i theta_i dG_i

    (Walker and Ni 2011; lambda = ``ANDERSON_REG`` trace(dF dF')). Safeguard:
    when ||f|| > ``ANDERSON_SAFEGUARD`` times the last accepted residual, the
    point is dropped and the iteration restarts, plainly, from the last
    accepted image. All inner products come from one Gram matrix of (dF, f).
    """
    m = len(a.X)
    dt = g.dtype
    f = g - a.x
    dF = [(f - a.G[i] + a.X[i]) * a.valid[i] for i in range(m)]
    dG = [(g - a.G[i]) * a.valid[i] for i in range(m)]
    V = dF + [f]
    pairs = [(i, j) for i in range(m + 1) for j in range(i, m + 1)]
    # one variadic reduction over all the products, which XLA fuses with them
    # into one kernel (a stacked V or stacked products would be buffers of
    # their own, and separate sums a kernel each)
    dots = jax.lax.reduce(
        tuple(V[i] * V[j] for i, j in pairs),
        tuple(jnp.zeros((), dt) for _ in pairs),
        lambda u, w: tuple(p + q for p, q in zip(u, w, strict=True)),
        (0,),
    )
    at = {p: k for k, p in enumerate(pairs)}
    gram = jnp.stack(
        [jnp.stack([dots[at[min(i, j), max(i, j)]] for j in range(m + 1)]) for i in range(m + 1)]
    )  # (m + 1, m + 1)
    A, b = gram[:m, :m], gram[:m, m]
    fn = jnp.sqrt(jnp.maximum(gram[m, m], jnp.finfo(dt).tiny))  # finite gradient at f = 0
    reject = jnp.any(a.valid > 0) & (fn > ANDERSON_SAFEGUARD * a.fprev)
    reg = max(ANDERSON_REG, 1e3 * float(jnp.finfo(dt).eps))
    A = A + jnp.diag(1.0 - a.valid + reg * jnp.trace(A) + jnp.finfo(dt).tiny)
    theta = _solve_small(A, b)
    theta = jnp.where(jnp.all(jnp.isfinite(theta)), theta, 0.0)
    x_aa = g - sum(theta[i] * dG[i] for i in range(m))
    slot = jnp.arange(m) == a.pos
    last = jnp.arange(m) == (a.pos - 1) % m
    write = slot & ~reject
    return AndersonState(
        x=jnp.where(reject, sum(a.G[i] * last[i] for i in range(m)), x_aa),
        X=tuple(jnp.where(write[i], a.x, a.X[i]) for i in range(m)),
        G=tuple(jnp.where(write[i], g, a.G[i]) for i in range(m)),
        valid=jnp.where(reject, last, slot | (a.valid > 0)).astype(dt),
        pos=jnp.where(reject, a.pos, (a.pos + 1) % m).astype(jnp.int32),
        fprev=jnp.where(reject, jnp.inf, fn).astype(dt),
    )
