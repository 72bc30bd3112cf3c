"""eq.opt_ro: the penalty rho_j* of each objective, exactly or by Lanczos steps.

rho_j* = 1 / sqrt(lambda_1 lambda_n) of Abar_j H_j^-1 Abar_j' (lambda_1, lambda_n
the smallest non-zero and the largest eigenvalue), for every objective of the
padded layout: estimated by Lanczos steps on the pencil (H_j, Abar_j'Abar_j)
(:func:`eq_opt_ro_power`; H_j applied as the KKT strategy holds it,
:mod:`~.hessian`), or exactly (:func:`eq_opt_ro_exact`, an eigendecomposition,
several times slower on XLA:CPU). Objectives whose rows A_in,j are
column-rank deficient always use the exact form with the known rank.

How a formulation picks rho_j is a strategy chosen by name at construction
(``rho_method``; :func:`select_rho`): :class:`PowerRho`, :class:`ExactRho`,
:class:`CarriedRho` (a factor ``params.rho`` on the automatic rho_j*,
estimated, exact, or carried by the warm start from the previous step) or
:class:`GivenRho` (``params.rho`` itself). The formulation gives the automatic rho_j* as a
:class:`RhoEstimates` (eq.opt_ro for Local Explicit, Ghadimi's
sqrt(lambda_min lambda_max) of H_j for Formulations 1 and 2).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..problem.topology import Topology
from .costs import PaddedCosts, unpad_matrix
from .layout import padded_layout
from .linalg import apply_blocks, eye_like, spd_inverse

__all__ = [
    "RHO_RULES",
    "RHO_STEPS",
    "CarriedRho",
    "ExactRho",
    "GivenRho",
    "PowerRho",
    "RhoEstimates",
    "carried_or_estimate",
    "eq_opt_ro_exact",
    "eq_opt_ro_power",
    "extreme_eigenvalues",
    "lanczos_extremes",
    "optimal_rho",
    "power_rho",
    "power_rho_riccati",
    "power_rho_woodbury",
    "rho_from_ritz",
    "scaled_hessian",
    "select_rho",
    "tridiagonal_max",
]


# -- how rho_j is chosen: strategies behind one interface, chosen by name ------------
class RhoEstimates(NamedTuple):
    """A formulation's automatic rho_j*, two ways: ``estimate()`` (an iterative estimate)
    and ``exact()`` (an eigendecomposition; None where the formulation has none);
    ``carried``: (J,) the rho_j* a warm start carries (0 where none), with
    ``estimate_of(args)`` / ``args``, the estimate as a function of its array inputs
    (for :class:`CarriedRho`'s batch-level decision)."""

    estimate: Callable[[], Any]
    exact: Callable[[], Any] | None = None
    carried: Any = None
    estimate_of: Callable[[Any], Any] | None = None
    args: Any = None


@dataclass(frozen=True)
class PowerRho:
    """rho_j = ``params.rho[j]`` times the automatic rho_j*, estimated iteratively (Lanczos
    steps for eq.opt_ro, power iteration for Formulations 1 and 2's rho)."""

    name: str = "power"
    needs_H: bool = False  # the formed H_j (only the exact eigendecomposition needs it)

    def star(self, rho_star: RhoEstimates) -> Any:
        """(J,) the automatic rho_j* this rule uses (None: it uses none)."""
        return rho_star.estimate()

    def rho(self, factor: Any, rho_star: RhoEstimates) -> Any:
        return factor * self.star(rho_star)


@dataclass(frozen=True)
class ExactRho:
    """rho_j = ``params.rho[j]`` times the automatic rho_j*, by an eigendecomposition
    (several times slower on XLA:CPU; the reference the estimate is tested against)."""

    name: str = "eigh"
    needs_H: bool = True

    def star(self, rho_star: RhoEstimates) -> Any:
        return rho_star.exact()

    def rho(self, factor: Any, rho_star: RhoEstimates) -> Any:
        return factor * self.star(rho_star)


@dataclass(frozen=True)
class GivenRho:
    """rho_j = ``params.rho[j]`` itself (no rho_j*; for a singular H_j, where
    eq.opt_ro is undefined)."""

    name: str = "given"
    needs_H: bool = False

    def star(self, rho_star: RhoEstimates) -> Any:
        return None

    def rho(self, factor: Any, rho_star: RhoEstimates) -> Any:
        return factor


@dataclass(frozen=True)
class CarriedRho:
    """rho_j = ``params.rho[j]`` times the rho_j* the warm start carries (the
    previous step's), estimated as :class:`PowerRho` does only where none is
    carried (a cold start, or a solve that asked for a new estimate). Along a
    drive the model moves little between steps, and rho only sets the
    convergence rate: on bench/bench_peers.py's drives (N_p = 10) the held
    rho_j* gave the same iterations and error, with the setup 38 % cheaper
    (docs/bench_peers.md). Under ``vmap`` the estimate runs (for the whole
    batch) when some case carries none, not, as a batched ``lax.cond`` would,
    always (:func:`carried_or_estimate`)."""

    name: str = "carried"
    needs_H: bool = False

    def star(self, rho_star: RhoEstimates) -> Any:
        if rho_star.carried is None or rho_star.estimate_of is None:
            return rho_star.estimate()
        return carried_or_estimate(rho_star.carried, rho_star.args, rho_star.estimate_of)

    def rho(self, factor: Any, rho_star: RhoEstimates) -> Any:
        return factor * self.star(rho_star)


def carried_or_estimate(carried: Any, args: Any, estimate: Callable[[Any], Any]) -> Any:
    """(J,) ``carried`` where every entry is > 0, else ``estimate(args)``.

    One ``lax.cond``; under ``vmap`` one decision for the batch (a custom
    batching rule: the estimate runs, vmapped, when some case needs it, and is
    kept where it was needed). Differentiable (forward and reverse): the
    carried value is a constant, the estimate's derivative is its own."""

    def select(c: Any, a: Any) -> Any:
        return jax.lax.cond(jnp.all(c > 0), lambda x: c, estimate, a)

    @jax.custom_batching.custom_vmap
    def choose(c: Any, a: Any) -> Any:
        return select(c, a)

    @choose.def_vmap
    def rule(axis_size: int, in_batched: Any, c: Any, a: Any) -> tuple:
        c_b, a_b = in_batched

        def full(x: Any, b: bool) -> Any:
            return x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        c = full(c, c_b)
        a = jax.tree.map(full, a, a_b)
        need = ~jnp.all(c > 0, axis=-1)
        est = jax.lax.cond(jnp.any(need), lambda x: jax.vmap(estimate)(x), lambda x: c, a)
        return jnp.where(need[:, None], est, c), True

    @jax.custom_jvp
    def chosen(c: Any, a: Any) -> Any:
        return choose(c, a)

    @chosen.defjvp
    def chosen_jvp(primals: tuple, tangents: tuple) -> tuple:
        c, a = primals
        _, ta = tangents
        est, d_est = jax.jvp(estimate, (a,), (ta,))
        keep = jnp.all(c > 0)
        return jnp.where(keep, c, est), jnp.where(keep, jnp.zeros_like(d_est), d_est)

    return chosen(jax.lax.stop_gradient(carried), args)


RHO_STEPS = 4
"""Default Lanczos steps of eq.opt_ro's estimate (each applies H_j and H_j^-1 once
per objective). Rule: 4; reason: as close to the exact rho_j* as 8 steps of the
former power iteration (worst 6.9 % against 8.7 % on tests/admm/test_rho.py's
problems; 4.2 % and 3.6 % on bench/bench_peers.py's cruise drives at N_p = 10
and 20) at half the products: eq.opt_ro was 62 % to 76 % of a batched setup,
and the Riccati setup fell from 29.7 to 20.5 us a case-step (issue 30's
breakdown, docs/bench_peers.md)."""

RHO_RULES: dict[str, Any] = {r.name: r for r in (PowerRho(), ExactRho(), GivenRho(), CarriedRho())}
"""``rho_method`` name -> strategy."""


def select_rho(name: str, allowed: tuple[str, ...] = tuple(RHO_RULES)) -> Any:
    """The rho strategy ``name`` among ``allowed`` (a formulation's choices), or a
    ValueError naming ``rho_method``."""
    if name not in allowed:
        raise ValueError(f"rho_method: expected one of {allowed}, got {name!r}")
    return RHO_RULES[name]


# -- eq.opt_ro ------------------------------------------------------------------------
def _pencil(topology: Topology, AtA: Any, dtype: Any) -> tuple[Any, Any]:
    """(LamB, mask): the per-step block of Lambda = Abar'Abar with identities on
    padded inputs and rank-deficient objectives, and the (J, n) real-entry mask."""
    lay = padded_layout(topology)
    U = lay.cols.shape[1]
    N = topology.horizon
    full = np.asarray(lay.full)
    # Padded inputs: identity in A_in'A_in and in H, decoupled from the real
    # entries. Rank-deficient objectives get an identity here and the exact
    # form (:func:`_deficient`).
    eyeU = jnp.asarray(np.eye(U)[None] * (1.0 - lay.umask)[:, :, None], dtype)
    fixed = jnp.asarray((~full)[:, None, None] * np.eye(U), dtype)
    LamB = AtA * jnp.asarray(full[:, None, None], dtype) + eyeU + fixed
    mask = jnp.asarray(np.tile(lay.umask, (1, N)), dtype)
    return LamB, mask


def _with_deficient(
    topology: Topology, c: PaddedCosts, Ain: Any, own_rows: tuple, rho_full: Any
) -> Any:
    """(J,) rho_j*: ``rho_full`` for objectives with full column rank rows, the
    exact form with the known rank for the others (``c.H`` formed)."""
    lay = padded_layout(topology)
    U = lay.cols.shape[1]
    N = topology.horizon
    out = []
    for j, full in enumerate(lay.full):
        if full:
            out.append(rho_full[j])
        else:
            u = lay.u_sizes[j]
            Hj = unpad_matrix(c.H[j], u, U, N)
            Aj = Ain[j][own_rows[j], :u]
            out.append(optimal_rho(Hj, Aj, N, topology.group_rank[j]))
    return jnp.stack(out)


def eq_opt_ro_power(
    topology: Topology,
    c: PaddedCosts,
    Ain: Any,
    AtA: Any,
    own_rows: tuple,
    hessian: Any,
    iterations: int = 8,
) -> Any:
    """(J,) eq.opt_ro's rho_j*, its extreme eigenvalues by ``iterations`` Lanczos
    steps on the pencil (H_j, Abar_j'Abar_j), H_j and H_j^-1 applied
    by ``hessian`` (:mod:`~.hessian`: dense, Woodbury or Riccati).

    c : the padded costs; Ain : (J, R, U) per-step rows A_in,j in the layout;
    AtA : (J, U, U) A_in,j'A_in,j; own_rows : per objective, the positions of
    its own rows among the R (for the exact rank-deficient form).
    """
    if not any(padded_layout(topology).full):
        return _with_deficient(topology, c, Ain, own_rows, None)
    LamB, mask = _pencil(topology, AtA, c.E.dtype)
    return _with_deficient(topology, c, Ain, own_rows, hessian.pencil_rho(LamB, mask, iterations))


def eq_opt_ro_exact(topology: Topology, c: PaddedCosts, Ain: Any, AtA: Any, own_rows: tuple) -> Any:
    """(J,) eq.opt_ro's rho_j*, exactly: the eigenvalues of G = L^-1 H L^-T
    (``c.H`` formed; see :func:`optimal_rho`)."""
    lay = padded_layout(topology)
    if not any(lay.full):
        return _with_deficient(topology, c, Ain, own_rows, None)
    N = topology.horizon
    U = lay.cols.shape[1]
    dt = c.E.dtype
    LamB, mask = _pencil(topology, AtA, dt)
    # G = L^-1 H L^-T padded with the mean real eigenvalue (trace / n_j), which
    # lies between the extreme ones and so leaves mu_min, mu_max unchanged
    G = scaled_hessian(c.H, LamB, N)
    G = 0.5 * (G + jnp.swapaxes(G, 1, 2))
    nj = jnp.asarray([N * u for u in lay.u_sizes], dt)
    mean = jnp.einsum("jaa->j", G * mask[:, :, None]) / nj
    G = G * (mask[:, :, None] * mask[:, None, :]) + (1 - mask)[:, :, None] * (
        mean[:, None, None] * jnp.eye(N * U, dtype=dt)
    )
    mu = jnp.linalg.eigvalsh(G)
    eps = jnp.finfo(dt).eps
    rho_full = jnp.sqrt(jnp.maximum(mu[:, 0], eps * mu[:, -1]) * mu[:, -1])
    return _with_deficient(topology, c, Ain, own_rows, rho_full)


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
      two-sided boxes this is sqrt(lambda_min(H) lambda_max(H)) / 2 (paper-notes item 16).
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


def power_start(mask: Any, dtype: Any) -> Any:
    """The two chains' fixed start (J, 2, n): positive entries on real inputs
    (zero on padding, which the operators leave decoupled)."""
    J, n = mask.shape
    v0 = np.random.default_rng(12345).uniform(0.5, 1.5, n)
    return jnp.broadcast_to((jnp.asarray(v0, dtype) * mask)[:, None, :], (J, 2, n))


def power_rho(H: Any, Hinv: Any, LamB: Any, mask: Any, iterations: int) -> Any:
    """eq.opt_ro with mu_min, mu_max estimated by Lanczos steps on the pencil.

    mu are the eigenvalues of the pencil H x = mu Lambda x, Lambda = Abar'Abar
    (= I (x) A_in,j'A_in,j, positive definite for full column rank rows): the
    same as those of G = L^-1 H L^-T of :func:`optimal_rho`, without forming
    L. mu_max is the largest eigenvalue of Lambda^-1 H, 1 / mu_min that of
    H^-1 Lambda, both self-adjoint in the Lambda inner product; each estimate
    is the largest Ritz value of ``iterations`` Lanczos steps
    (:func:`lanczos_extremes`), which lies inside the spectrum, so mu_max is
    under- and mu_min over-estimated. rho only sets the convergence rate (the
    solution does not depend on it): 4 steps (:data:`RHO_STEPS`) gave rho
    within 10 % of the exact eigendecomposition on the generated problems
    (worst 6.9 %, ``test_power_rho_close_to_exact``), as 8 steps of power
    iteration did (8.7 %), with half the operator products.

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

    def op(v: Any) -> Any:
        return jnp.einsum("jpab,jpb->jpa", ops, v)

    return rho_from_ritz(lanczos_extremes(op, LamB, power_start(mask, H.dtype), iterations))


def power_rho_woodbury(hessian: Any, LamB: Any, mask: Any, iterations: int) -> Any:
    """:func:`power_rho` with H = Y_u' Q2 Y_u + I (x) BH applied and inverted in
    the Woodbury form (:class:`~.hessian.WoodburyHessian`).

    No n x n matrix is formed or factorised: each step applies::

        Lambda^-1 H x = (I (x) Lambda_B^-1) [(I (x) BH) x + Y_u'(Q2 (Y_u x))]
        H^-1 Lambda x = (I (x) BH^-1) Lambda x - W'(P (W Lambda x))

    which is O(n r) per product against the O(n^2 r) of forming the two
    operators: on the cruise example at N_p = 10 (n = 40) the setup took 26
    against 42 us per case batched over 32 cases, and 56 against 62 us for
    one problem (``bench/bench_local_explicit.py``).
    """
    Laminv = spd_inverse(LamB)

    def op(v: Any) -> Any:
        up = apply_blocks(Laminv, hessian.apply(v[:, :1]))  # Lambda^-1 H v
        down = hessian.solve(apply_blocks(LamB, v[:, 1:]))  # H^-1 Lambda v
        return jnp.concatenate([up, down], axis=1)

    return rho_from_ritz(lanczos_extremes(op, LamB, power_start(mask, LamB.dtype), iterations))


def power_rho_riccati(hessian: Any, LamB: Any, mask: Any, iterations: int) -> Any:
    """:func:`power_rho` with H_j and H_j^-1 applied by sweeps of the model
    (:class:`~.hessian.RiccatiHessian`).

    H x is a forward sweep from x_0 = 0 and an adjoint sweep back
    (:func:`~.riccati.hessian_apply`); H^-1 y the Riccati solve with the
    per-step block BH (no rho term). Neither Y_u,j nor any n x n matrix is
    formed: O(N_p (n_x^2 + n_x U)) per product.
    """
    Laminv = spd_inverse(LamB)

    def op(v: Any) -> Any:
        up = apply_blocks(Laminv, hessian.apply(v[:, :1]))  # Lambda^-1 H v
        down = hessian.solve(apply_blocks(LamB, v[:, 1:]))  # H^-1 Lambda v
        return jnp.concatenate([up, down], axis=1)

    return rho_from_ritz(lanczos_extremes(op, LamB, power_start(mask, LamB.dtype), iterations))


def lanczos_extremes(op: Any, LamB: Any, v: Any, steps: int) -> Any:
    """(J, 2) the largest Ritz value of each chain after ``steps`` Lanczos steps.

    ``op`` maps (J, 2, n) to (J, 2, n): chain 0 applies Lambda^-1 H, chain 1
    H^-1 Lambda, both self-adjoint in the Lambda inner product <x, y> = x'Lambda y
    (Lambda = I (x) LamB). From the start ``v`` (J, 2, n) the three-term recurrence
    builds the tridiagonal T_k = Q' Lambda op(Q) of the Krylov space (no
    reorthogonalisation: a lost orthogonality only repeats a converged Ritz
    value); its largest eigenvalue (:func:`tridiagonal_max`) lies inside the
    spectrum, below the largest eigenvalue of the operator (mu_max for chain 0,
    1 / mu_min for chain 1). A step whose residual vanishes (the Krylov space
    is invariant: n_j < ``steps``, or an exact eigenvector) ends its chain
    there (q = 0: the remaining steps add zeros to T, which leave its largest
    eigenvalue as it is).
    """

    def inner(x: Any, y: Any) -> Any:
        return jnp.sum(x * apply_blocks(LamB, y), axis=-1)

    eps = jnp.finfo(v.dtype).eps
    q = v / jnp.sqrt(inner(v, v))[..., None]
    q_prev = jnp.zeros_like(q)
    beta = jnp.zeros(q.shape[:-1], q.dtype)
    alphas, betas = [], []
    for _ in range(steps):  # steps is small and static: unrolled
        w = op(q)
        alpha = inner(w, q)
        w = w - alpha[..., None] * q - beta[..., None] * q_prev
        nrm = jnp.sqrt(jnp.maximum(inner(w, w), 0.0))
        alive = nrm > jnp.sqrt(eps) * jnp.abs(alpha)
        beta = jnp.where(alive, nrm, 0.0)
        q_prev, q = q, jnp.where(alive[..., None], w / jnp.where(alive, nrm, 1.0)[..., None], 0.0)
        alphas.append(alpha)
        betas.append(beta)
    return tridiagonal_max(jnp.stack(alphas, -1), jnp.stack(betas[:-1], -1))


def tridiagonal_max(a: Any, b: Any, bisections: int = 40) -> Any:
    """Largest eigenvalue of symmetric tridiagonal matrices (diagonal a (..., k),
    off-diagonal b (..., k - 1)), pure JAX.

    Located by bisection on Sturm counts: it lies in [max a, max (a_i +
    |b_(i-1)| + |b_i|)] (Gershgorin), and a point x is above it when every
    pivot of T - x I is negative (d_1 = a_1 - x, d_i = a_i - x - b_(i-1)^2 /
    d_(i-1)); the bracket is at most 3 max |a| wide, so 40 halvings leave a
    relative error below 1e-11. Returned as the Rayleigh quotient y'Ty / y'y
    at its eigenvector y (two steps of inverse iteration just above it, held
    constant), which has the eigenvalue's exact derivative (y' dT y / y'y), so
    gradients flow through eq.opt_ro as through the power iteration's quotient.
    """
    k = a.shape[-1]
    ab = jnp.abs(b)
    pad = jnp.zeros(a.shape[:-1] + (1,), a.dtype)
    radius = jnp.concatenate([pad, ab], -1) + jnp.concatenate([ab, pad], -1)
    a0, b0 = jax.lax.stop_gradient(a), jax.lax.stop_gradient(b)
    lo = jnp.max(a0, axis=-1)
    hi = jnp.max(a0 + jax.lax.stop_gradient(radius), axis=-1)
    tiny = jnp.finfo(a.dtype).tiny

    def above(x: Any) -> Any:  # every pivot of T - x I negative: x >= lambda_max
        d = a0[..., 0] - x
        ok = d < 0
        for i in range(1, k):
            d = a0[..., i] - x - b0[..., i - 1] ** 2 / jnp.minimum(d, -tiny)
            ok = ok & (d < 0)
        return ok

    def body(_: Any, bounds: tuple) -> tuple:
        lo, hi = bounds
        mid = 0.5 * (lo + hi)
        up = above(mid)
        return jnp.where(up, lo, mid), jnp.where(up, mid, hi)

    _, hi = jax.lax.fori_loop(0, bisections, body, (lo, hi))
    # inverse iteration with T - sigma I, sigma just above lambda_max: negative
    # definite, so the elimination needs no pivoting
    sigma = hi + jnp.sqrt(jnp.finfo(a.dtype).eps) * jnp.abs(hi) + tiny
    dd = a0 - sigma[..., None]
    y = jnp.ones_like(a0)
    for _ in range(2):
        c, z = [], []
        m = dd[..., 0]
        for i in range(k):
            if i:
                m = dd[..., i] - b0[..., i - 1] * c[-1]
            m = jnp.minimum(m, -tiny)
            c.append(b0[..., i] / m if i < k - 1 else None)
            z.append((y[..., i] - (b0[..., i - 1] * z[-1] if i else 0.0)) / m)
        x = [None] * k
        x[k - 1] = z[k - 1]
        for i in reversed(range(k - 1)):
            x[i] = z[i] - c[i] * x[i + 1]
        y = jnp.stack(x, -1)
        y = y / jnp.sqrt(jnp.sum(y * y, -1, keepdims=True))
    Ty = a * y
    if k > 1:
        Ty = Ty + jnp.concatenate([b * y[..., 1:], pad], -1)
        Ty = Ty + jnp.concatenate([pad, b * y[..., :-1]], -1)
    return jnp.sum(y * Ty, -1)


def rho_from_ritz(theta: Any) -> Any:
    """sqrt(mu_min mu_max) from the chains' largest Ritz values (J, 2): mu_max
    (chain 0) and 1 / mu_min (chain 1), mu_min floored at eps mu_max."""
    mu_max = theta[:, 0]
    mu_min = jnp.maximum(1.0 / theta[:, 1], jnp.finfo(theta.dtype).eps * mu_max)
    return jnp.sqrt(mu_min * mu_max)


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
