"""Primal infeasibility: a certificate that the constraint set is empty, for every formulation.

The MPC's constraints act step by step (eq.eq_linear: A_in U^(k) <= b_in^(k)),
so the problem is infeasible exactly when some step's polyhedron is empty.
By Farkas' lemma that is certified by a y >= 0 with ::

    A_in' y = 0   and   b_in^(k)' y < 0

(a non-negative combination of the rows that reads 0 <= negative). After
OSQP (Stellato et al. 2020, sec. 3.4): ADMM on a problem over an empty set
does not converge, and the change of its multiplier between iterations tends
to such a y. :func:`certify` runs a small ADMM on the projection problem
``min 1/2 ||U||^2 s.t. A_in U <= b^(k)`` of every step at once (n_u inputs;
the same slack splitting as Local Explicit) for a fixed number of iterations
and tests the multiplier's last change dy::

    ||A_in' dy||_inf <= eps ||dy||_inf     and     b^(k)' dy < -eps ||dy||_inf

with eps = :data:`EPS_INFEASIBLE` (1e-3 in float32). A y that passes is
evidence: anyone can check the two conditions. A step whose set is not empty
never passes (then b' y >= 0 for every y >= 0 with A' y = 0), so the test
cannot call a feasible problem infeasible; a nearly empty set may need more
than :data:`CERTIFY_ITERATIONS` iterations to be certified, and is then
reported as not converged.

The formulations call :func:`with_certificate` on every result that did not
converge: it is a ``lax.cond``, so a converged control step pays nothing (under
``vmap`` both branches run, a few microseconds per case).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ..problem.data import ProblemData
from ..results import SolveResult
from .linalg import spd_inverse

__all__ = ["CERTIFY_ITERATIONS", "EPS_INFEASIBLE", "Certificate", "certify", "with_certificate"]

CERTIFY_ITERATIONS = 200
"""ADMM iterations of :func:`certify` (a lb > ub box is certified within a few)."""

EPS_INFEASIBLE = 1e-6
"""Relative tolerance of the certificate test in float64 (1e-3 in float32)."""


class Certificate(NamedTuple):
    """Evidence of primal infeasibility (:func:`certify`).

    infeasible : () bool, a certificate was found.
    step : () int32, the first prediction step k whose constraint set is empty
        (-1 when none).
    y : (n_c,) the Farkas vector of that step, y >= 0 scaled to max(y) = 1, on
        the rows of ``ProblemData.Ain`` (box rows, then general rows).
    Aty : () ||A_in' y||_inf (near 0).   bty : () b_in^(k)' y (negative).
    """

    infeasible: Any
    step: Any
    y: Any
    Aty: Any
    bty: Any


def certify(data: ProblemData, iterations: int = CERTIFY_ITERATIONS) -> Certificate:
    """Look for a Farkas certificate of an empty constraint set at any step."""
    A, b = data.Ain, data.bin  # (n_c, n_u), (N, n_c)
    dt = A.dtype
    n_c = A.shape[0]
    if n_c == 0:
        return no_certificate(data)
    # scale each step's rows to unit right-hand-side magnitude, so that one rho fits
    # problems in Nm and in unit bounds alike (a positive row scaling keeps the set)
    scale = jnp.maximum(jnp.max(jnp.abs(b), axis=1, keepdims=True), 1.0)  # (N, 1)
    bs = b / scale
    rho = jnp.asarray(1.0, dt)
    M = spd_inverse((jnp.eye(A.shape[1], dtype=dt) + rho * A.T @ A)[None])[0]

    def body(_: Any, carry: tuple) -> tuple:
        s, y, _ = carry
        u = -(rho * (s - bs) + y) @ A @ M  # (N, n_u)
        Au = u @ A.T
        s = jnp.maximum(bs - Au - y / rho, 0.0)
        y_new = y + rho * (Au - bs + s)
        return s, y_new, y_new - y

    zeros = jnp.zeros_like(bs)
    _, _, dy = jax.lax.fori_loop(0, iterations, body, (zeros, zeros, zeros))
    dy = jnp.maximum(dy, 0.0)  # y >= 0 in this splitting; rounding below 0 is dropped
    norm = jnp.max(dy, axis=1)  # (N,)
    y = dy / jnp.where(norm > 0, norm, 1.0)[:, None]
    Aty = jnp.max(jnp.abs(y @ A), axis=1)
    bty = jnp.sum(y * bs, axis=1)
    eps = jnp.asarray(1e-3 if dt == jnp.float32 else EPS_INFEASIBLE, dt)
    ok = (norm > 0) & (Aty <= eps) & (bty < -eps)
    k = jnp.argmax(ok)
    found = jnp.any(ok)
    # report b'y in the problem's units (the row scaling undone)
    return Certificate(
        infeasible=found,
        step=jnp.where(found, k, -1).astype(jnp.int32),
        y=y[k],
        Aty=Aty[k],
        bty=bty[k] * scale[k, 0],
    )


def no_certificate(data: ProblemData) -> Certificate:
    """The :class:`Certificate` of a result that was not checked (the shape of one)."""
    dt = data.Ain.dtype
    z = jnp.zeros((), dt)
    return Certificate(
        jnp.zeros((), bool), jnp.asarray(-1, jnp.int32), jnp.zeros(data.Ain.shape[:1], dt), z, z
    )


def with_certificate(result: SolveResult, data: ProblemData) -> SolveResult:
    """``result`` with status ``infeasible`` (3) and its :class:`Certificate` when a
    solve that did not converge faced an empty constraint set. Converged
    results are not checked (``lax.cond``); their certificate says not infeasible."""
    cert = jax.lax.cond(result.status == 0, lambda d: no_certificate(d), lambda d: certify(d), data)
    status = jnp.where(cert.infeasible, 3, result.status).astype(jnp.int32)
    return result._replace(
        status=status, converged=result.converged & ~cert.infeasible, certificate=cert
    )
