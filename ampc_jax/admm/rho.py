"""eq.opt_ro: the penalty rho_j* of each objective, exactly or by power iteration.

rho_j* = 1 / sqrt(lambda_1 lambda_n) of Abar_j H_j^-1 Abar_j' (lambda_1, lambda_n
the smallest non-zero and the largest eigenvalue). :func:`eq_opt_ro` gives it
for every objective of the padded layout: by default estimated by power
iteration on the pencil (H_j, Abar_j'Abar_j) (:func:`power_rho`,
:func:`power_rho_woodbury`), or exactly (:func:`optimal_rho`, an
eigendecomposition, several times slower on XLA:CPU). Objectives whose rows
A_in,j are column-rank deficient always use the exact form with the known rank.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..problem.topology import Topology
from . import riccati
from .costs import PaddedCosts, unpad_matrix
from .layout import padded_layout
from .linalg import apply_blocks, eye_like, spd_inverse, spd_inverse_dense, woodbury_parts

__all__ = [
    "RHO_METHODS",
    "eq_opt_ro",
    "extreme_eigenvalues",
    "optimal_rho",
    "power_rho",
    "power_rho_riccati",
    "power_rho_woodbury",
    "scaled_hessian",
]

RHO_METHODS = ("power", "eigh")
"""How eq.opt_ro's extreme eigenvalues are found: power iteration or exactly."""


def eq_opt_ro(
    topology: Topology,
    c: PaddedCosts,
    Ain: Any,
    AtA: Any,
    own_rows: tuple,
    *,
    method: str = "power",
    iterations: int = 8,
    hinv: str = "dense",
) -> Any:
    """(J,) eq.opt_ro's rho_j* for every objective of the padded layout.

    Parameters
    ----------
    c : the padded costs (``c.H`` formed unless ``hinv`` is not "dense" and the power method).
    Ain : (J, R, U) per-step rows A_in,j in the layout; AtA : (J, U, U) A_in,j'A_in,j.
    own_rows : per objective, the positions of its own rows among the R (for the
        exact rank-deficient form).
    method : ``"power"`` or ``"eigh"`` (:data:`RHO_METHODS`).
    iterations : power-iteration steps.
    hinv : how the power iteration applies H_j^-1: ``"dense"`` (formed),
        ``"woodbury"`` (the Woodbury identity, no n x n matrix formed) or
        ``"riccati"`` (the Riccati recursion over the model, :func:`power_rho_riccati`;
        ``c`` then needs no condensed form).
    """
    T = topology
    lay = padded_layout(T)
    J, U = lay.cols.shape
    N = T.horizon
    H = c.H
    dt = c.E.dtype
    full = np.asarray(lay.full)
    out = [None] * J
    if full.any():
        # Padded inputs: identity in A_in'A_in and in H, decoupled from the real
        # entries. Rank-deficient objectives get an identity here and the exact
        # form below.
        eyeU = jnp.asarray(np.eye(U)[None] * (1.0 - lay.umask)[:, :, None], dt)
        fixed = jnp.asarray((~full)[:, None, None] * np.eye(U), dt)
        LamB = AtA * jnp.asarray(full[:, None, None], dt) + eyeU + fixed
        mask = jnp.asarray(np.tile(lay.umask, (1, N)), dt)
        if method == "power":
            # H may be singular (R_j = 0): a shift of eps * mean(diag H) keeps
            # its inverse finite and mu_min at about the eps * mu_max floor
            nj = jnp.asarray([N * u for u in lay.u_sizes], dt)
            um = jnp.asarray(lay.umask, dt)
            if hinv == "riccati":
                gram = riccati.trace_gram(c.A, c.Bu, c.Qx, N)
            else:
                gram = jnp.sum(c.Yu * (c.Q2 @ c.Yu), axis=(1, 2))
            tr = gram + N * jnp.einsum("jaa,ja->j", c.BH, um)
            delta = (jnp.finfo(dt).eps * tr / nj)[:, None, None]
            if hinv == "riccati":
                BHd = c.BH + delta * jnp.eye(U, dtype=dt)
                rho_full = power_rho_riccati(c, BHd, LamB, mask, iterations, N)
            elif hinv == "woodbury":
                BHd = c.BH + delta * jnp.eye(U, dtype=dt)
                rho_full = power_rho_woodbury(c, BHd, LamB, mask, iterations, N)
            else:
                Hinv = spd_inverse_dense(H + delta * jnp.eye(N * U, dtype=dt))
                rho_full = power_rho(H, Hinv, LamB, mask, iterations)
        else:
            # exact: G = L^-1 H L^-T padded with the mean real eigenvalue
            # (trace / n_j), which lies between the extreme ones and so leaves
            # mu_min, mu_max unchanged
            G = scaled_hessian(H, LamB, N)
            G = 0.5 * (G + jnp.swapaxes(G, 1, 2))
            nj = jnp.asarray([N * u for u in lay.u_sizes], dt)
            mean = jnp.einsum("jaa->j", G * mask[:, :, None]) / nj
            G = G * (mask[:, :, None] * mask[:, None, :]) + (1 - mask)[:, :, None] * (
                mean[:, None, None] * jnp.eye(N * U, dtype=dt)
            )
            mu = jnp.linalg.eigvalsh(G)
            eps = jnp.finfo(dt).eps
            rho_full = jnp.sqrt(jnp.maximum(mu[:, 0], eps * mu[:, -1]) * mu[:, -1])
        for j in range(J):
            if full[j]:
                out[j] = rho_full[j]
    for j in range(J):
        if not full[j]:
            u = lay.u_sizes[j]
            Hj = unpad_matrix(H[j], u, U, N)
            Aj = Ain[j][own_rows[j], :u]
            out[j] = optimal_rho(Hj, Aj, N, T.group_rank[j])
    return jnp.stack(out)


def optimal_rho(H: Any, Ain: Any, horizon: int, rank: int | None = None) -> Any:
    """eq.opt_ro, exactly: rho* = 1 / sqrt(lambda_1 lambda_n) of M = Abar H^-1 Abar'.

    lambda_1 and lambda_n are the smallest non-zero and the largest eigenvalue
    of M. The non-zero eigenvalues of M are those of H^-1 Abar'Abar (same
    non-zero spectrum of XY and YX).

    * Full column rank A_in,j (every bounded input; ``rank is None``): all of
      H^-1 Abar'Abar's eigenvalues are non-zero. With Abar'Abar = L L' (block
      diagonal, L = I (x) chol(A_in,j' A_in,j)) they are 1/mu for mu the
      eigenvalues of G = L^-1 H L^-T, so rho* = sqrt(mu_min mu_max): no
      threshold, so float32 does not pick rounding noise (jax-facts). For
      two-sided boxes this is sqrt(lambda_min(H) lambda_max(H)) / 2 (NOTES 16).
    * Otherwise ``rank`` = rank(A_in,j) per step gives the number of non-zero
      eigenvalues, N_p * rank, of L_H^-1 Abar'Abar L_H^-T (L_H = chol(H)):
      the known rank replaces a numerical threshold.

    This is the exact (eigendecomposition) form, ``rho_method="eigh"`` of
    the formulations; the default estimates mu_min and mu_max by power
    iteration (:func:`power_rho`), which is much cheaper on XLA:CPU.
    """
    n = H.shape[0]
    AtA = Ain.T @ Ain
    if rank is None:
        G = scaled_hessian(H, AtA, horizon)
        mu = jnp.linalg.eigvalsh(0.5 * (G + G.T))
        mu_min = jnp.maximum(mu[0], jnp.finfo(H.dtype).eps * mu[-1])
        return jnp.sqrt(mu_min * mu[-1])
    LH = jnp.linalg.cholesky(H)
    M = jnp.kron(jnp.eye(horizon, dtype=H.dtype), AtA)
    X = jsl.solve_triangular(LH, M, lower=True)
    G = jsl.solve_triangular(LH, X.T, lower=True)
    lam = jnp.linalg.eigvalsh(0.5 * (G + G.T))
    nonzero = horizon * rank
    return 1.0 / jnp.sqrt(lam[n - nonzero] * lam[-1])


def scaled_hessian(H: Any, AtA: Any, horizon: int) -> Any:
    """L^-1 H L^-T with L = I (x) chol(A_in' A_in) (see :func:`optimal_rho`).

    Works on one (n, n) H with (U, U) A_in'A_in, or a batch (J, n, n), (J, U, U).
    """
    batched = H.ndim == 3
    Hb = H if batched else H[None]
    Ab = AtA if batched else AtA[None]
    J, n = Hb.shape[0], Hb.shape[1]
    nu = n // horizon
    La = jnp.linalg.cholesky(Ab)
    Li = jsl.solve_triangular(La, eye_like(nu, H.dtype, J), lower=True)
    G = jnp.einsum("jab,jkblc,jdc->jkald", Li, Hb.reshape(J, horizon, nu, horizon, nu), Li)
    G = G.reshape(J, n, n)
    return G if batched else G[0]


def rho_from_quotients(rq: Any) -> Any:
    """sqrt(mu_min mu_max) from the two chains' Rayleigh quotients (J, 2), mu_min
    floored at eps mu_max (a singular H_j)."""
    mu_max = jnp.maximum(rq[:, 0], rq[:, 1])
    mu_min = jnp.maximum(jnp.minimum(rq[:, 0], rq[:, 1]), jnp.finfo(rq.dtype).eps * mu_max)
    return jnp.sqrt(mu_min * mu_max)


def power_start(mask: Any, dtype: Any) -> Any:
    """The two chains' fixed start (J, 2, n): positive entries on real inputs."""
    J, n = mask.shape
    v0 = np.random.default_rng(12345).uniform(0.5, 1.5, n)
    return jnp.broadcast_to((jnp.asarray(v0, dtype) * mask)[:, None, :], (J, 2, n))


def power_rho(H: Any, Hinv: Any, LamB: Any, mask: Any, iterations: int) -> Any:
    """eq.opt_ro with mu_min, mu_max estimated by power iteration.

    mu are the eigenvalues of the pencil H x = mu Lambda x, Lambda = Abar'Abar
    (= I (x) A_in,j'A_in,j, positive definite for full column rank rows): the
    same as those of G = L^-1 H L^-T of :func:`optimal_rho`, without forming
    L. mu_max comes from iterating x <- Lambda^-1 H x, mu_min from
    x <- H^-1 Lambda x; each estimate is the Rayleigh quotient
    x'Hx / x'Lambda x, which lies inside [mu_min, mu_max], so mu_max is under-
    and mu_min over-estimated. rho only sets the convergence rate (the
    solution does not depend on it): ``rho_iterations`` = 8 gave rho within
    10 % of the exact eigendecomposition on the generated problems (worst
    8.7 %, ``test_power_rho_close_to_exact``) and within 1 % on the shipped
    cruise example (``examples/cruise_control.json``: 0.95 % and 0.06 %).

    H, Hinv : (J, n, n); LamB : (J, U, U) the per-step block of Lambda;
    mask : (J, n) 1 on real entries. The two operators are formed (for one
    problem at the stability example's n = 9 that was 4 us faster than
    applying H and H^-1 in every iteration).
    """
    # the two operators, formed once (n^2 U work: block-diagonal factors); with H,
    # H^-1 and Lambda symmetric, (I (x) B) applied to the rows of M is M (I (x) B)
    LiH = jnp.swapaxes(apply_blocks(spd_inverse(LamB), H), 1, 2)  # Lambda^-1 H
    HiL = apply_blocks(LamB, Hinv)  # H^-1 Lambda
    ops = jnp.stack([LiH, HiL], axis=1)  # (J, 2, n, n): one chain each
    v = power_start(mask, H.dtype)

    def body(_: Any, v: Any) -> Any:
        v = jnp.einsum("jpab,jpb->jpa", ops, v)
        return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))

    v = jax.lax.fori_loop(0, iterations, body, v)
    num = jnp.einsum("jpa,jab,jpb->jp", v, H, v)
    return rho_from_quotients(num / jnp.sum(v * apply_blocks(LamB, v), -1))


def power_rho_woodbury(
    c: PaddedCosts, BH: Any, LamB: Any, mask: Any, iterations: int, horizon: int
) -> Any:
    """:func:`power_rho` with H = Y_u' Q2 Y_u + I (x) BH and H^-1 from the Woodbury form.

    No n x n matrix is formed or factorised: each iteration applies
    (:func:`woodbury_parts`)::

        Lambda^-1 H x = (I (x) Lambda_B^-1) [(I (x) BH) x + Y_u'(Q2 (Y_u x))]
        H^-1 Lambda x = (I (x) BH^-1) Lambda x - W'(P (W Lambda x))

    which is O(n r) per product against the O(n^2 r) of forming the two
    operators: on the cruise example at N_p = 10 (n = 40) the setup took 26
    against 42 us per case batched over 32 cases, and 56 against 62 us for
    one problem (``bench/bench_local_explicit.py``).
    """
    Binv, W, P = woodbury_parts(c.Yu, c.Qh, BH, horizon)
    Laminv = spd_inverse(LamB)

    def lowrank(L: Any, Mid: Any, R: Any, x: Any) -> Any:
        y = jnp.einsum("jsn,jpn->jps", R, x)
        y = jnp.einsum("jst,jpt->jps", Mid, y)
        return jnp.einsum("jsn,jps->jpn", L, y)

    def Hx(x: Any) -> Any:
        return apply_blocks(BH, x) + lowrank(c.Yu, c.Q2, c.Yu, x)

    def body(_: Any, v: Any) -> Any:
        up = apply_blocks(Laminv, Hx(v[:, :1]))  # Lambda^-1 H v
        lx = apply_blocks(LamB, v[:, 1:])
        down = apply_blocks(Binv, lx) - lowrank(W, P, W, lx)  # H^-1 Lambda v
        v = jnp.concatenate([up, down], axis=1)
        return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))

    v = power_start(mask, c.Yu.dtype)
    v = jax.lax.fori_loop(0, iterations, body, v)
    rq = jnp.sum(v * Hx(v), -1) / jnp.sum(v * apply_blocks(LamB, v), -1)
    return rho_from_quotients(rq)


def power_rho_riccati(
    c: PaddedCosts, BH: Any, LamB: Any, mask: Any, iterations: int, horizon: int
) -> Any:
    """:func:`power_rho` with H_j and H_j^-1 applied by sweeps of the model (:mod:`~.riccati`).

    H x is a forward sweep from x_0 = 0 and an adjoint sweep back
    (:func:`~.riccati.hessian_apply`); H^-1 y the Riccati solve with the
    per-step block BH (no rho term). Neither Y_u,j nor any n x n matrix is
    formed: O(N_p (n_x^2 + n_x U)) per product.
    """
    f = riccati.factor(c.A, c.Bu, c.Qx, BH, horizon)
    Laminv = spd_inverse(LamB)

    def Hx(x: Any) -> Any:
        return riccati.hessian_apply(c.A, c.Bu, c.Qx, BH, x)

    def body(_: Any, v: Any) -> Any:
        up = apply_blocks(Laminv, Hx(v[:, :1]))  # Lambda^-1 H v
        down = riccati.solve(f, apply_blocks(LamB, v[:, 1:]))  # H^-1 Lambda v
        v = jnp.concatenate([up, down], axis=1)
        return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))

    v = power_start(mask, c.E.dtype)
    v = jax.lax.fori_loop(0, iterations, body, v)
    rq = jnp.sum(v * Hx(v), -1) / jnp.sum(v * apply_blocks(LamB, v), -1)
    return rho_from_quotients(rq)


def extreme_eigenvalues(H: Any, Hinv: Any, mask: Any, iterations: int) -> tuple[Any, Any]:
    """(lambda_min, lambda_max) of each H_j (J, n, n) on its real entries
    (``mask`` (J, n)) by ``iterations`` steps of power iteration on H_j and
    H_j^-1; both Rayleigh quotients lie inside [lambda_min, lambda_max]."""
    ops = jnp.stack([H, Hinv], axis=1)
    v = power_start(mask, H.dtype)

    def body(_: Any, v: Any) -> Any:
        v = jnp.einsum("jpab,jpb->jpa", ops, v)
        return v / jnp.sqrt(jnp.sum(v * v, axis=-1, keepdims=True))

    v = jax.lax.fori_loop(0, iterations, body, v)
    rq = jnp.einsum("jpa,jab,jpb->jp", v, H, v) / jnp.sum(v * v, axis=-1)
    lam_max = jnp.maximum(rq[:, 0], rq[:, 1])
    lam_min = jnp.maximum(jnp.minimum(rq[:, 0], rq[:, 1]), jnp.finfo(H.dtype).eps * lam_max)
    return lam_min, lam_max
