"""An exact finish of an ADMM solve: the equality-constrained QP of the iterate's active set.

ADMM identifies which constraint rows are active long before its iterate is
accurate. Once the active set W of the slack (rows with Z_c = 0, so
lambda_c = sum_j gamma_jc >= 0 may be positive) stops changing, the finish
solves the problem the formulation converges to with the rows of W as
equalities, exactly, and checks the KKT conditions:

    min  1/2 U'H U + E'U   s.t.  a_c' u_k = b_k,c  for (k, c) in W

with H = sum_j P_j' H_j P_j, E = sum_j P_j' E_j (the integrated cost the
local costs sum to; eq.integMPC). Its solution is accepted when

* every row holds: a_c' u_k - b_k,c <= eps_f max(1, max |b|)  (primal feasibility),
* every multiplier of W has the right sign: nu_k,c >= -eps_f max |nu|,
* every pivot of the solve was positive (the rows of W independent),

and the ADMM iterate is then replaced by it (OSQP's polish, Stellato et al.
2020, sec. 4.3, used as the stopping rule). A rejected finish leaves the
iterate as it was: ADMM goes on and tries again later.

The equality-constrained QP is solved without a condensed matrix, as an LQ
problem over the horizon (:mod:`~.riccati`'s recursion with each step's rows
of W as equalities on u_k). Objective j's cost tracks its own model
x^j_(k+1) = A x^j_k + B_j P_j u_k (its group's inputs; the free response is
in E_j), so the state of the LQ problem stacks the J objectives' states
(J n_x), and the stage cost is 1/2 x'blockdiag(Qx_j) x + 1/2 u'R u + Ebar_k'u_k
with R = sum_j P_j' BH_j P_j. The backward recursion at step k, with
G = R + B'P B, F = B'P A, e = B'p + Ebar_k and D = M_k A_in the rows of W
(M_k the 0/1 mask; masked rows are zero)::

    S  = D G^-1 D' + (I - M_k)          (unit pivots on masked rows)
    Gt = G^-1 - G^-1 D' S^-1 D G^-1     (G^-1 on the null space of D)
    c  = G^-1 D' S^-1 d                 (d = M_k b_k)
    u_k = -Gt (F x_k + e) + c,    nu_k = -S^-1 (d + D G^-1 (F x_k + e))
    P  <- Qx + A'P A - F'Gt F,    p <- A'p - F'(Gt e - c)

O(N_p ((J n_x)^3 + n_c^3)) per finish: for the cruise benchmark (J n_x = 6,
n_c = 10, N_p = 10) about as many flops as a few ADMM iterations.

How a formulation finishes is a strategy chosen by name (``finish``;
:func:`select_finish`): :class:`NoFinish` (``"none"``, the paper's iteration)
or :class:`ActiveSetFinish` (``"active_set"``), tried on the start's own
active set (a warm start's) and then every ``every`` iterations where the
active set did not change in the last iteration, each attempt with up to
``corrections`` primal-dual active-set steps (:func:`finish_solve`). Under ``vmap`` the attempt is decided once for the batch (a custom
batching rule): the finish runs when some case asks for it, not, as a batched
``lax.cond`` would, at every iteration.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .linalg import bmm as _mm
from .linalg import bmtm as _mtm
from .linalg import bmtv as _mtv
from .linalg import bmv as _mv

__all__ = [
    "FINISHES",
    "FINISH_CORRECTIONS",
    "FINISH_EVERY",
    "ActiveSetFinish",
    "FinishData",
    "NoFinish",
    "attempt",
    "default_tol",
    "finish_data",
    "finish_solve",
    "select_finish",
    "solve_eqp",
    "verify",
]

FINISH_EVERY = 8
"""Default iterations between finish attempts. Rule: 8; reason: on
bench/bench_peers.py's drives (N_p = 10, 100 drives x 10 steps, warm, 2
corrections) a finish costs about as much as 8 to 10 iterations, and the
cold first steps need 12 to 24 iterations; every 4 to 12 gave the same
warm iterations (the warm start's set, corrected, is final)."""

FINISH_CORRECTIONS = 2
"""Default primal-dual active-set steps of a finish. Rule: 2; reason: on
bench/bench_peers.py's drives (N_p = 10) the warm start's set was final
after 2 steps in every warm step (mean ADMM iterations 0.0 against 7.6
without steps and 1.1 with one; 0.66x the time of the plain iteration)."""


class FinishData(NamedTuple):
    """The integrated LQ problem the finish solves (stacked objective states, m = J n_x).

    A : (m, m) blockdiag(A); B : (m, n_u) the rows B_j P_j; Q : (m, m)
    blockdiag(Qx_j); R : (n_u, n_u) sum_j P_j' BH_j P_j; E : (N_p, n_u) the
    linear cost sum_j P_j' E_j per step; Ain : (n_c, n_u) the rows; b : (N_p, n_c)
    their right-hand sides; tol : () eps_f of the checks.
    """

    A: Any
    B: Any
    Q: Any
    R: Any
    E: Any
    Ain: Any
    b: Any
    tol: Any


def finish_data(
    A: Any, Bu: Any, Qx: Any, BH: Any, E: Any, P: Any, Ain: Any, b: Any, tol: Any
) -> FinishData:
    """:class:`FinishData` from the padded costs of a formulation.

    A : (n_x, n_x); Bu : (J, n_x, U) each objective's input columns (zero on
    padding); Qx : (J, n_x, n_x); BH : (J, U, U); E : (J, N_p U) the linear
    costs E_j; P : (J, U, n_u) the 0/1 column selection (zero rows on padding);
    Ain : (n_c, n_u), b : (N_p, n_c) the rows; tol : eps_f.
    """
    J, nx, U = Bu.shape
    N = b.shape[0]
    m = J * nx
    eyeJ = jnp.eye(J, dtype=A.dtype)
    Aa = jnp.einsum("ij,ab->iajb", eyeJ, A).reshape(m, m)
    Qa = jnp.einsum("ij,jab->iajb", eyeJ, Qx).reshape(m, m)
    Ba = jnp.einsum("jxu,jun->jxn", Bu, P).reshape(m, -1)
    R = jnp.einsum("jua,juv,jvb->ab", P, BH, P)
    Eb = jnp.einsum("jku,jun->kn", E.reshape(J, N, U), P)
    return FinishData(Aa, Ba, Qa, 0.5 * (R + R.T), Eb, Ain, b, jnp.asarray(tol, A.dtype))


def _guarded_inverse(M: Any) -> tuple[Any, Any]:
    """(M^-1, smallest pivot / its diagonal entry) of symmetric M (..., m, m) by m
    unrolled symmetric sweeps (:func:`~.riccati.unrolled_spd_inverse`); a pivot
    <= 0 is replaced by 1 (the inverse is then meaningless, and the ratio says so)."""
    m = M.shape[-1]
    A = M
    diag = jnp.diagonal(M, axis1=-2, axis2=-1)
    ratio = jnp.ones(M.shape[:-2], M.dtype)
    tiny = jnp.finfo(M.dtype).tiny
    for k in range(m):
        d = A[..., k, k]
        ratio = jnp.minimum(ratio, d / jnp.maximum(jnp.abs(diag[..., k]), tiny))
        d = jnp.where(d > 0, d, 1.0)[..., None, None]
        v = A[..., :, k : k + 1] / d
        e = jnp.zeros((m, 1), M.dtype).at[k, 0].set(1.0)
        new = v - e * (1.0 + 1.0 / d)
        B = A - d * v * jnp.swapaxes(v, -1, -2)
        sel_r = jnp.zeros((m, 1), bool).at[k, 0].set(True)
        sel_c = jnp.zeros((1, m), bool).at[0, k].set(True)
        B = jnp.where(sel_r, jnp.swapaxes(new, -1, -2), B)
        A = jnp.where(sel_c, new, B)
    return -A, ratio


def solve_eqp(fd: FinishData, active: Any, n_box: int) -> tuple[Any, Any, Any]:
    """The equality-constrained QP of the active set ``active`` (N_p, n_c) bool:
    (u (N_p, n_u), nu (N_p, n_c) its multipliers, zero off the set, and the
    smallest pivot ratio of the solve: positive when the rows of the set are
    independent and the reduced Hessian definite).

    The first ``n_box`` rows are box rows (one input each, +-1): an active box
    row fixes its input, which is eliminated from the step's problem (masked),
    so only the general rows of the set need a Schur complement (n_g x n_g).
    """
    dt = fd.A.dtype
    M = active.astype(dt)
    A, B = fd.A, fd.B
    Sel, Ag = fd.Ain[:n_box], fd.Ain[n_box:]  # (n_b, n_u) +-1 entries; (n_g, n_u)
    ng = Ag.shape[0]

    def back(carry: tuple, xs: tuple) -> tuple:
        P, p, piv = carry
        Mk, bk, Ek = xs
        Mb, Mg = Mk[:n_box], Mk[n_box:]
        fixed = jnp.minimum(_mtv(jnp.abs(Sel), Mb), 1.0)  # (n_u,) inputs at a bound
        v = _mtv(Sel, Mb * bk[:n_box]) / jnp.maximum(_mtv(jnp.abs(Sel), Mb), 1.0)
        free = 1.0 - fixed
        PB = _mm(P, B)  # (m, n_u)
        G = fd.R + _mtm(B, PB)
        G = 0.5 * (G + G.T)
        F = _mtm(PB, A)  # B'P A (n_u, m)
        e = _mtv(B, p) + Ek
        Gh = G * free[:, None] * free[None, :] + jnp.diag(fixed)
        Gi, rg = _guarded_inverse(Gh)
        h0 = free * (e + _mv(G, v))
        Ff = free[:, None] * F
        if ng:
            D = Mg[:, None] * Ag * free[None, :]  # (n_g, n_u)
            d = Mg * (bk[n_box:] - _mv(Ag, v))
            GiDt = _mm(Gi, D.T)
            S = _mm(D, GiDt) + jnp.diag(1.0 - Mg)
            Si, rs = _guarded_inverse(0.5 * (S + S.T))
            Wg = _mm(Si, GiDt.T)  # S^-1 D G^-1 (n_g, n_u)
            Gt = Gi - _mm(GiDt, Wg)
            c = _mv(GiDt, _mv(Si, d))
            sd = _mv(Si, d)
            rg = jnp.minimum(rg, rs)
        else:
            Wg = jnp.zeros((0, G.shape[0]), dt)
            Gt, c, sd = Gi, jnp.zeros_like(v), jnp.zeros((0,), dt)
        L = _mm(Gt, Ff)  # (n_u, m)
        ell = _mv(Gt, h0) - c - v
        P = fd.Q + _mtm(A, _mm(P, A)) - _mtm(F, L)
        p = _mtv(A, p) - _mtv(F, ell)
        out = (L, ell, F, e, G, v, free, Wg, sd)
        return (0.5 * (P + P.T), p, jnp.minimum(piv, rg)), out

    m = A.shape[0]
    init = (fd.Q, jnp.zeros((m,), dt), jnp.ones((), dt))
    (_, _, piv), stages = jax.lax.scan(back, init, (M, fd.b, fd.E), reverse=True)

    def fwd(x: Any, xs: tuple) -> tuple:
        L, ell, F, e, G, v, free, Wg, sd = xs
        u = -(_mv(L, x) + ell)
        h = _mv(F, x) + e
        nug = -(_mv(Wg, free * (h + _mv(G, v))) + sd)
        g = _mv(G, u) + h + _mtv(Ag, nug)  # stationarity before the box rows' multipliers
        nub = -_mv(Sel, g)  # row r (s u_i <= b): s nu_r = -g_i
        return _mv(A, x) + _mv(B, u), (u, jnp.concatenate([nub, nug]))

    _, (u, nu) = jax.lax.scan(fwd, jnp.zeros((m,), dt), stages)
    return u, nu * M, piv


def verify(fd: FinishData, u: Any, nu: Any, active: Any, pivot: Any) -> tuple[Any, Any, Any]:
    """(accepted, rows to add, rows to drop) of a finish: accepted when every row
    is within eps_f max(1, max |b|) of feasible and every row of the set within
    it of tight (complementarity: a set holding both rows of a box whose bounds
    differ fixes the input between them), every multiplier of the set is
    >= -eps_f max |nu|, the solve's pivots are positive and everything finite;
    the violated rows, and the rows of the set with a negative multiplier or a
    slack, are what a primal-dual active-set step changes (each (N_p, n_c) bool).
    Stationarity holds by construction (:func:`solve_eqp`), so these are the
    KKT conditions of the convex QP: an accepted point is its optimum."""
    viol = u @ fd.Ain.T - fd.b  # (N_p, n_c), <= 0 where a row holds
    scale_b = jnp.maximum(1.0, jnp.max(jnp.abs(jnp.where(jnp.isfinite(fd.b), fd.b, 0.0))))
    scale_nu = jnp.maximum(jnp.max(jnp.abs(nu)), jnp.finfo(nu.dtype).tiny)
    add = viol > fd.tol * scale_b
    drop = active & ((nu < -fd.tol * scale_nu) | (viol < -fd.tol * scale_b))
    pivots = pivot > jnp.sqrt(jnp.finfo(u.dtype).eps) * 1e-4
    finite = jnp.all(jnp.isfinite(u)) & jnp.all(jnp.isfinite(nu))
    return ~jnp.any(add) & ~jnp.any(drop) & pivots & finite, add, drop


def finish_solve(fd: FinishData, active: Any, n_box: int, corrections: int) -> tuple:
    """(u, nu, active set, accepted): the equality-constrained QP of ``active``
    (:func:`solve_eqp`) and, while it is not accepted (:func:`verify`), up to
    ``corrections`` primal-dual active-set steps (Hintermueller, Ito and Kunisch
    2002): the violated rows join the set and the rows with a negative
    multiplier leave it, and the new set's QP is solved. A warm start's set
    usually differs from the final one by a row or two (bench/bench_peers.py's
    drives), which one such step repairs."""

    def attempt_set(act: Any) -> tuple:
        u, nu, piv = solve_eqp(fd, act, n_box)
        ok, add, drop = verify(fd, u, nu, act, piv)
        return u, nu, act, ok, (act | add) & ~drop

    u, nu, act, ok, nxt = attempt_set(active)
    if corrections < 1:
        return u, nu, act, ok

    def cond(c: tuple) -> Any:
        return ~c[3] & (c[5] < corrections)

    def body(c: tuple) -> tuple:
        u, nu, act, ok, nxt, k = attempt_set(c[4]) + (c[5] + 1,)
        return u, nu, act, ok, nxt, k

    u, nu, act, ok, _, _ = jax.lax.while_loop(cond, body, (u, nu, act, ok, nxt, 0))
    return u, nu, act, ok


# -- the batch-level decision ------------------------------------------------------------
def attempt(try_: Any, args: Any, finish_fn: Any, skip_fn: Any) -> Any:
    """``finish_fn(args)`` where ``try_``, else ``skip_fn(args)`` (same pytree). One
    ``lax.cond``; under ``vmap`` one decision for the batch: the finish runs
    (vmapped) when any case tries, and its result is kept where it was tried."""

    @jax.custom_batching.custom_vmap
    def run(t: Any, a: Any) -> Any:
        return jax.lax.cond(t, finish_fn, skip_fn, a)

    @run.def_vmap
    def rule(axis_size: int, in_batched: Any, t: Any, a: Any) -> tuple:
        t_b, a_b = in_batched

        def full(x: Any, b: bool) -> Any:
            return x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        t = full(t, t_b)
        a = jax.tree.map(full, a, a_b)
        skipped = jax.vmap(skip_fn)(a)
        out = jax.lax.cond(jnp.any(t), lambda x: jax.vmap(finish_fn)(x), lambda x: skipped, a)
        out = jax.tree.map(
            lambda f, s: jnp.where(t.reshape((axis_size,) + (1,) * (f.ndim - 1)), f, s),
            out,
            skipped,
        )
        return out, jax.tree.map(lambda _: True, out)

    return run(try_, args)


# -- strategies --------------------------------------------------------------------------
@dataclass(frozen=True)
class NoFinish:
    """The paper's iteration: no finish, ADMM alone to eq.Convergence."""

    name: str = "none"
    every: int = 0
    corrections: int = 0


@dataclass(frozen=True)
class ActiveSetFinish:
    """Solve the active set's equality-constrained QP exactly every ``every``
    iterations where the active set did not change in the last iteration, with
    up to ``corrections`` primal-dual active-set steps (:func:`finish_solve`)."""

    name: str = "active_set"
    every: int = FINISH_EVERY
    corrections: int = FINISH_CORRECTIONS


FINISHES = ("none", "active_set")
"""Names :func:`select_finish` accepts."""


def select_finish(
    name: str, every: int = FINISH_EVERY, corrections: int = FINISH_CORRECTIONS
) -> Any:
    """The finish strategy ``name`` (one of :data:`FINISHES`), or a ValueError naming ``finish``."""
    if name not in FINISHES:
        raise ValueError(f"finish: expected one of {FINISHES}, got {name!r}")
    if name == "none":
        return NoFinish()
    return ActiveSetFinish(every=int(every), corrections=int(corrections))


def default_tol(dtype: Any) -> float:
    """eps_f for ``dtype``: 1e-9 in float64, 1e-4 in float32 (round-off of the solve)."""
    return 1e-9 if np.dtype(dtype).itemsize >= 8 else 1e-4
