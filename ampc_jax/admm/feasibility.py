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

with eps = :data:`EPS_INFEASIBLE` (1e-3 in float32). The rows are
equilibrated first (unit row norms, each step's right-hand side scaled to
unit magnitude), so the test is relative. A y that passes is evidence: anyone
can check the two conditions on the problem's own rows. A step whose set is
not empty has b' y >= 0 for every y >= 0 with A' y = 0; the test's margin eps
keeps a feasible set from passing unless it is within about eps of empty
in the equilibrated units. A set empty by less than the margin, or one that
needs more than :data:`CERTIFY_ITERATIONS` iterations, is not certified.

The formulations call :func:`with_certificate` on every result: it searches
(a ``lax.cond``) when the solve did not converge or when its inputs violate a
row and a cheap repair of them (:func:`repaired_inputs`: a few projections on
the violated rows and the bounds, then the exact test A_in u <= b_in) finds no
point of the set either. A point that passes the exact test proves the set
non-empty, so a converged control step pays a few matrix products. Under
``vmap`` the decision is taken for the whole batch (a custom batching rule):
the search runs when some case needs it, not, as a batched ``lax.cond``
would, always (200 iterations per case: 3x the whole step of the cruise QP
with general rows, ``bench/bench_peers.py``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ..problem.data import ProblemData
from ..results import SolveResult, Status
from .linalg import spd_inverse

__all__ = [
    "CERTIFY_ITERATIONS",
    "EPS_INFEASIBLE",
    "Certificate",
    "certify",
    "repaired_inputs",
    "violation",
    "with_certificate",
]

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
    A0, b0 = data.Ain, data.bin  # (n_c, n_u), (N, n_c)
    dt = A0.dtype
    n_c = A0.shape[0]
    if n_c == 0:
        return no_certificate(data)
    # Equilibrate: every row to unit norm (a positive scaling of a row keeps its
    # half-space, and y scales back), then each step's right-hand side to unit
    # magnitude (the set scales, emptiness does not change), so that one rho and
    # one eps fit coefficients of 1e-7 and bounds in kNm alike. Zero rows are
    # left as they are (0 <= b with b < 0 is itself a certificate).
    norm_r = jnp.sqrt(jnp.sum(A0 * A0, axis=1))
    row = jnp.where(norm_r > 0, norm_r, 1.0)
    A = A0 / row[:, None]
    b = b0 / row[None, :]
    scale = jnp.maximum(jnp.max(jnp.abs(b), axis=1, keepdims=True), jnp.finfo(dt).tiny)
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
    # the test on the equilibrated rows: relative to ||y||_inf = 1 and unit rows
    Aty = jnp.max(jnp.abs(y @ A), axis=1)
    bty = jnp.sum(y * bs, axis=1)
    eps = jnp.asarray(1e-3 if dt == jnp.float32 else EPS_INFEASIBLE, dt)
    ok = (norm > 0) & (Aty <= eps) & (bty < -eps)
    k = jnp.argmax(ok)
    found = jnp.any(ok)
    # the certificate on the problem's own rows: y_c / ||A_c|| (still >= 0), scaled
    # to max 1, with its A'y and b'y
    yk = y[k] / row
    yk = yk / jnp.maximum(jnp.max(yk), jnp.finfo(dt).tiny)
    return Certificate(
        infeasible=found,
        step=jnp.where(found, k, -1).astype(jnp.int32),
        y=yk,
        Aty=jnp.max(jnp.abs(yk @ A0)),
        bty=jnp.sum(yk * b0[k]),
    )


def no_certificate(data: ProblemData) -> Certificate:
    """The :class:`Certificate` of a result that was not checked (the shape of one)."""
    dt = data.Ain.dtype
    z = jnp.zeros((), dt)
    return Certificate(
        jnp.zeros((), bool), jnp.asarray(-1, jnp.int32), jnp.zeros(data.Ain.shape[:1], dt), z, z
    )


def violation(data: ProblemData, u: Any) -> Any:
    """() the largest violation max_k,c (A_in U^(k) - b^(k))_c of inputs u (N_p, n_u)."""
    if data.Ain.shape[0] == 0:
        return jnp.zeros((), u.dtype)
    return jnp.max(u @ data.Ain.T - data.bin)


REPAIR_PASSES = 4
"""Projection passes of :func:`repaired_inputs`."""


def repaired_inputs(data: ProblemData, u: Any, passes: int = REPAIR_PASSES) -> Any:
    """u (N_p, n_u) moved toward the constraint set: ``passes`` simultaneous
    projections on the rows it violates (each row's target tightened by a
    rounding margin), each followed by the clip to the bounds.

    Only a candidate: :func:`with_certificate` tests the exact A_in u <= b_in
    on it. A converged solve violates rows by about sqrt(eps_r), which one
    such pass removes unless the set is (nearly) empty.
    """
    A, b = data.Ain, data.bin
    if A.shape[0] == 0:
        return u
    eps = jnp.finfo(A.dtype).eps
    n2 = jnp.sum(A * A, axis=1)
    inv = jnp.where(n2 > 0, 1.0 / jnp.where(n2 > 0, n2, 1.0), 0.0)
    for _ in range(passes):
        Au = u @ A.T
        margin = 64 * eps * (jnp.abs(b) + jnp.abs(u) @ jnp.abs(A).T)
        over = jnp.maximum(Au - b + margin, 0.0) * inv  # (N, n_c)
        u = jnp.clip(u - over @ A, data.lb, data.ub)
    return u


def _search(check: Any, data: ProblemData) -> Certificate:
    return jax.lax.cond(check, lambda d: certify(d), lambda d: no_certificate(d), data)


@jax.custom_batching.custom_vmap
def _batched_search(check: Any, data: ProblemData) -> Certificate:
    return _search(check, data)


@_batched_search.def_vmap
def _search_rule(axis_size: int, in_batched: Any, check: Any, data: ProblemData) -> tuple:
    """One decision for the batch: search (every case, vmapped) when any case
    needs it, keep the certificate only where it was asked for."""
    c_b, d_b = in_batched

    def full(x: Any, b: bool) -> Any:
        return x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

    check = full(check, c_b)
    data = jax.tree.map(full, data, d_b)
    none = jax.vmap(no_certificate)(data)
    cert = jax.lax.cond(jnp.any(check), lambda d: jax.vmap(certify)(d), lambda d: none, data)
    cert = jax.tree.map(
        lambda c, z: jnp.where(check.reshape((axis_size,) + (1,) * (c.ndim - 1)), c, z), cert, none
    )
    return cert, jax.tree.map(lambda _: True, cert)


def with_certificate(result: SolveResult, data: ProblemData) -> SolveResult:
    """``result`` with status ``infeasible`` (3) and its :class:`Certificate` when
    the constraint set is empty.

    The search runs (``lax.cond``; under ``vmap`` once for the batch) when the
    solve did not converge, or when it converged to inputs that violate some
    row and their repair (:func:`repaired_inputs`) does not satisfy every row
    exactly either: the stopping rule accepts violations of about
    sqrt(eps_r), so a set that is empty by less than that would otherwise come
    back solved. A point that satisfies every row proves the set non-empty;
    the result's inputs themselves are not changed."""
    fixed = repaired_inputs(data, result.u)
    check = (result.status != Status.SOLVED) | (
        (violation(data, result.u) > 0) & (violation(data, fixed) > 0)
    )
    cert = _batched_search(check, jax.lax.stop_gradient(data))
    status = jnp.where(cert.infeasible, Status.INFEASIBLE, result.status).astype(jnp.int32)
    return result._replace(
        status=status, converged=result.converged & ~cert.infeasible, certificate=cert
    )
