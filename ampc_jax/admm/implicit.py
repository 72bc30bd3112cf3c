"""Implicit differentiation of a solve to tolerance, at the ADMM fixed point.

Any formulation on the core protocol (:class:`~ampc_jax.admm.core.ADMMSolver`)
is one map of its iterate x = ``point(state)`` (Local Explicit: (Z, gamma);
Formulations 1 and 2: (Z, gamma, s, y)) with parameters theta, the setup
(costs, rho_j, factorisations, relaxation: everything ``setup(data, params)``
builds)::

    y = S(x; theta) = step(theta, at(x, .))      (the next state: U, x+, residuals)
    T(x; theta)     = point(S(x; theta))          (alg:1 as a fixed-point map)

The solve to tolerance (:meth:`~ampc_jax.admm.core.ADMMSolver.run`, a
``while_loop``, plain or Anderson-accelerated) ends at x* = T(x*; theta) up to
its tolerance. By the implicit function theorem, dx* = (I - T_x)^-1 T_theta
dtheta, so for a cotangent c of the final state y* = S(x*; theta)::

    a = S_x' c,  b = S_theta' c
    lambda = a + T_x' lambda              (the adjoint equation, (I - T_x)' lambda = a)
    dtheta = b + T_theta' lambda

and both T_x' and T_theta' are one reverse-mode product of one plain step
(``jax.vjp`` of S, with the cotangent ``at(lambda, 0)``). The adjoint equation
is solved by its own fixed-point iteration lambda <- a + T_x' lambda (the
Neumann series of (I - T_x')^-1): it converges because ADMM's map is averaged
(Douglas-Rachford; the relaxed map for alpha in (0, 2)), so T_x' has the
same spectrum as the forward iteration's linearisation and the adjoint
converges at the forward iteration's own local rate. With Anderson memory m
the adjoint iteration is Anderson-accelerated too (a linear map, where
Anderson is GMRES-like; :mod:`~ampc_jax.admm.acceleration`). It stops when
||lambda+ - lambda|| <= ``adjoint_tol`` ||a|| or after ``adjoint_max_iter``
iterations (default the solver's ``max_iter``).

Anderson acceleration changes only the path to x*, not x* itself, so the
derivative is that of the plain map at x*, whatever the runner did. This is
what unrolling the accelerated iteration does not give: once it has
converged to round-off, the least squares of Anderson's extrapolation are no
longer smooth, and the reverse- and forward-mode derivatives through it
disagree (even in sign) with central differences of the converged solve.

Nonsmoothness: the map contains projections (eq.F3_dual's max(0, .), the
local QPs' slack projection), which are not differentiable where a row is
exactly at its boundary. The derivative computed is the one of the active
set at x* (rows with Z_c > 0 active, the rest held at zero): the derivative
of the solution almost everywhere, and a one-sided one where the active set
changes.

What does and does not move: x* is the solution of the (decomposed) problem,
so it depends on the data (Q_j, R, references, x0, rows) but not on how it
is found. With a unique fixed point the converged inputs do not depend on
rho_j or on the relaxation alpha: their implicit derivative is zero (up to
the adjoint tolerance), which is what central differences of a solve to a
tight tolerance give. Tuning rho or alpha for speed needs a loss of the path
(the unrolled runner, :meth:`~ampc_jax.admm.core.ADMMSolver.solve_fixed`);
the implicit derivative is for losses of the solution (weights, learned
references, a network's outputs feeding the data).

Only reverse mode (``jax.grad``, ``jax.vjp``): a ``custom_vjp`` has no
forward-mode rule. The gradient is that of the solution the loop reached:
loosen the forward tolerance and the gradient is of an approximate
fixed point (error of the order of the residual times the adjoint's size).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..problem.data import ProblemData
from ..results import SolveResult
from ..validation import check_count, check_positive
from .acceleration import anderson_init, anderson_step
from .core import ADMMSolver
from .feasibility import with_certificate
from .params import SolverParams

__all__ = ["adjoint_tolerance", "run_implicit", "solve_implicit"]


def adjoint_tolerance(dtype: Any) -> float:
    """The default ``adjoint_tol`` for ``dtype``: 1e-10, or 100 machine epsilons if
    larger (1.2e-5 in float32)."""
    return max(1e-10, 100.0 * float(jnp.finfo(dtype).eps))


def _zero_cotangent(x: Any) -> Any:
    """A zero cotangent for the primal ``x`` (``float0`` for integer and bool leaves)."""
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


def _add(u: Any, v: Any) -> Any:
    return u if getattr(u, "dtype", None) == jax.dtypes.float0 else u + v


def _check_options(adjoint_tol: Any, adjoint_max_iter: Any) -> None:
    if adjoint_tol is not None:
        check_positive(adjoint_tol, "adjoint_tol")
    if adjoint_max_iter is not None:
        check_count(adjoint_max_iter, "adjoint_max_iter")


def _adjoint(solver: ADMMSolver, vjp_x: Any, a: Any, tol: Any, max_iter: int) -> Any:
    """lambda with lambda = a + T_x' lambda (``vjp_x(lam)`` = T_x' lam), by the
    fixed-point iteration from lambda = a, Anderson-accelerated with the
    solver's memory; stops at ||g(lambda) - lambda|| <= tol ||a|| or ``max_iter``."""
    dt = a.dtype
    scale = jnp.sqrt(jnp.sum(a * a)) * tol + jnp.finfo(dt).tiny

    def g(lam: Any) -> Any:
        return a + vjp_x(lam)

    def going(c: tuple) -> Any:  # under the cap, above the tolerance and finite
        k, res = c[1], c[2]
        return (k < max_iter) & ((k == 0) | ((res > scale) & jnp.isfinite(res)))

    m = int(solver.anderson)
    if m:

        def body(c: tuple) -> tuple:
            acc, k, _ = c
            out = g(acc.x)
            res = jnp.sqrt(jnp.sum((out - acc.x) ** 2))
            return anderson_step(acc, out), k + 1, res

        init = (anderson_init(a, m), jnp.zeros((), jnp.int32), jnp.asarray(jnp.inf, dt))
        acc, _, _ = jax.lax.while_loop(going, body, init)
        return acc.x

    def plain(c: tuple) -> tuple:
        lam, k, _ = c
        out = g(lam)
        return out, k + 1, jnp.sqrt(jnp.sum((out - lam) ** 2))

    lam, _, _ = jax.lax.while_loop(
        going, plain, (a, jnp.zeros((), jnp.int32), jnp.asarray(jnp.inf, dt))
    )
    return lam


def run_implicit(
    solver: ADMMSolver,
    setup: Any,
    state: Any,
    *,
    adjoint_tol: Any = None,
    adjoint_max_iter: int | None = None,
) -> Any:
    """``solver.run(setup, state, finish=False)`` (the ``while_loop`` to tolerance,
    plain or Anderson, without the formulation's exact finish: a finished
    iterate keeps the multipliers of the iterate it replaced, so it is no fixed
    point of the map) with a reverse-mode derivative with respect to ``setup``: the
    adjoint of the plain map at the fixed point (module docstring). ``state``
    (the start) gets a zero cotangent: the fixed point does not depend on it.

    ``adjoint_tol``: relative stopping tolerance of the adjoint iteration
    (default :func:`adjoint_tolerance` of the setup's dtype); ``adjoint_max_iter``:
    its cap (default ``solver.max_iter``)."""
    _check_options(adjoint_tol, adjoint_max_iter)
    cap = int(solver.max_iter if adjoint_max_iter is None else adjoint_max_iter)

    @jax.custom_vjp
    def fixed(setup: Any, start: Any) -> Any:
        return solver.run(setup, start, finish=False)

    def fwd(setup: Any, start: Any) -> tuple[Any, Any]:
        out = solver.run(setup, start, finish=False)
        return out, (setup, out, start)

    def bwd(res: tuple, ct: Any) -> tuple[Any, Any]:
        setup, out, start = res
        x = solver.point(out)
        tol = adjoint_tolerance(x.dtype) if adjoint_tol is None else float(adjoint_tol)

        def S(x: Any, th: Any) -> Any:
            return solver.step(th, solver.at(x, out))

        # T_x' alone inside the adjoint loop: a product with respect to x only, so
        # that no iteration forms the setup's cotangent (outer products the size
        # of the factorisations); the setup's is formed once, at the end
        _, vjp_x = jax.vjp(lambda x: S(x, setup), x)
        _, vjp = jax.vjp(S, x, setup)
        zero = jax.tree.map(_zero_cotangent, out)

        def T_x(lam: Any) -> Any:
            return vjp_x(solver.at(lam, zero))[0]

        lam = _adjoint(solver, T_x, vjp_x(ct)[0], tol, cap)
        # c S_theta + lambda T_theta in one product: S's cotangent ct + at(lambda, 0)
        both = jax.tree.map(_add, ct, solver.at(lam, zero))
        return vjp(both)[1], jax.tree.map(_zero_cotangent, start)

    fixed.defvjp(fwd, bwd)
    return fixed(setup, jax.lax.stop_gradient(state))


def solve_implicit(
    solver: ADMMSolver,
    data: ProblemData,
    params: SolverParams | None = None,
    warm: Any = None,
    *,
    adjoint_tol: Any = None,
    adjoint_max_iter: int | None = None,
) -> SolveResult:
    """:meth:`solver.solve <ampc_jax.admm.core.ADMMSolver.solve>` without its exact
    finish (the iteration alone to tolerance: the finish is forward only, see
    :func:`run_implicit`; with ``finish="none"`` the same result and program
    forward as ``solve``) with reverse-mode derivatives with respect to ``data``
    (Q_j, R, references, x0, rows: every float leaf of
    :class:`~ampc_jax.problem.ProblemData`) and ``params`` (rho scales,
    relaxation) by implicit differentiation at the fixed point
    (:func:`run_implicit`; module docstring for the equations).

    Differentiable outputs: ``u``, ``stats.gap``, the residuals and the final
    ``state``'s float fields; ``iterations``, ``status`` and ``converged`` are
    integers and booleans. ``warm`` (a previous result's state) only moves the
    start: it gets no gradient. Pure and jittable; vmap over ``data`` and
    ``params`` together. TypeError when ``solver`` is not an
    :class:`~ampc_jax.admm.core.ADMMSolver`; ValueError naming ``adjoint_tol``
    or ``adjoint_max_iter`` on a bad option."""
    if not isinstance(solver, ADMMSolver):
        raise TypeError(
            f"solver: expected an ADMMSolver (a formulation), got {type(solver).__name__}"
        )
    if not isinstance(data, ProblemData):
        raise TypeError(f"data: expected a ProblemData, got {type(data).__name__}")
    _check_options(adjoint_tol, adjoint_max_iter)
    setup = solver.setup(data, params)
    start = solver.init(jax.lax.stop_gradient(setup), warm)
    state = run_implicit(
        solver, setup, start, adjoint_tol=adjoint_tol, adjoint_max_iter=adjoint_max_iter
    )
    return with_certificate(solver.result(setup, state), data)
