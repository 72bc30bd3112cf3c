"""The numbers of an ADMM solve one may tune, as a pytree of array leaves.

Static options (iteration cap, Anderson memory, KKT strategy, row layout,
how eq.opt_ro is found) are fields of the formulation object and fix the
compiled program; :class:`SolverParams` is an argument of the compiled step.
So one compiled step serves every rho, relaxation and tolerance, can be
vmapped over parameter points and scenarios together, and differentiated with
respect to them (through the fixed-iteration runner).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..validation import check_values

__all__ = ["DEFAULT_TOL", "DEFAULT_TOL_REL", "SolverParams", "as_params", "solver_params"]

DEFAULT_TOL = 1e-6
"""Default eps_r = eps_s of eq.Convergence (squared norms, the constraint rows' units)."""

DEFAULT_TOL_REL = 0.0
"""Default relative tolerance eps_rel: 0, the absolute rule alone, so that the
iteration counts and the closed-loop figures are those of the absolute rule."""


class SolverParams(NamedTuple):
    """Tunable numbers of an ADMM formulation (a pytree; every leaf an array).

    Attributes
    ----------
    rho : (J,) per objective. With ``rho_method`` ``"power"`` or ``"eigh"`` (the
        default), a factor on eq.opt_ro's rho_j*: rho_j = rho[j] * rho_j*, and
        1 is the paper's choice. With ``rho_method="given"``, rho_j itself.
    relaxation : () over-relaxation alpha in (0, 2) of the global and dual steps
        (Boyd et al. 2011, sec. 3.4.3): A U is replaced there by
        alpha A U + (1 - alpha)(b - Z_prev). alpha = 1 is the paper's iteration.
    tol_primal, tol_dual : () eps_r and eps_s of eq.Convergence, on squared
        norms, absolute, in the constraint rows' units squared.
    tol_rel : () eps_rel, relative, on norms (after OSQP, Stellato et al.
        2020, sec. 3.4): objective j stops when ||r_j|| <= sqrt(eps_r) +
        eps_rel * scale_j and ||s_j|| <= sqrt(eps_s) + eps_rel * scale_j, with
        scale_j the size of the iterates the residuals compare
        (:mod:`~ampc_jax.admm.stopping`). 0 (the default) is the absolute rule.
    """

    rho: Any
    relaxation: Any
    tol_primal: Any
    tol_dual: Any
    tol_rel: Any


def solver_params(
    n_objectives: int,
    *,
    rho: Any = 1.0,
    relaxation: Any = 1.0,
    tol_primal: Any = DEFAULT_TOL,
    tol_dual: Any = DEFAULT_TOL,
    tol_rel: Any = DEFAULT_TOL_REL,
    dtype: Any = None,
) -> SolverParams:
    """Validated :class:`SolverParams` for ``n_objectives`` objectives.

    ``rho``: a float (every objective) or one value per objective, positive and
    finite (default 1.0: eq.opt_ro's rho* itself); ``relaxation`` in (0, 2)
    (default 1.0, the paper); ``tol_primal``, ``tol_dual`` >= 0 and finite
    (default 1e-6); ``tol_rel`` >= 0 and finite (default 0). Each may carry leading batch axes (a parameter sweep: a
    ``rho`` of shape (P, J) with ``relaxation`` of shape (P,)), to be vmapped
    over. ValueError naming the field otherwise; traced values are not checked.
    """
    dt = jnp.result_type(float) if dtype is None else dtype
    J = int(n_objectives)
    vals = {
        "rho": rho,
        "relaxation": relaxation,
        "tol_primal": tol_primal,
        "tol_dual": tol_dual,
        "tol_rel": tol_rel,
    }
    if not any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(vals)):
        r = np.asarray(rho, dtype=float) if not isinstance(rho, bool) else None
        if r is None:
            raise ValueError(f"rho: expected numbers, got {rho!r}")
        if r.ndim >= 1 and r.shape[-1] not in (1, J):
            raise ValueError(
                f"rho: expected a float or {J} values (one per objective), got shape {r.shape}"
            )
        check_values(rho, "rho", 0.0, np.inf)
        check_values(relaxation, "relaxation", 0.0, 2.0)
        check_values(tol_primal, "tol_primal", 0.0, np.inf, open_low=False)
        check_values(tol_dual, "tol_dual", 0.0, np.inf, open_low=False)
        check_values(tol_rel, "tol_rel", 0.0, np.inf, open_low=False)
    r = jnp.asarray(rho, dt)
    r = r[..., None] if r.ndim == 0 else r
    rest = [jnp.asarray(v, dt) for v in (relaxation, tol_primal, tol_dual, tol_rel)]
    # one batch shape for every leaf, so that the result vmaps with in_axes=0
    try:
        batch = np.broadcast_shapes(r.shape[:-1], *(v.shape for v in rest))
    except ValueError:
        shapes = {"rho": r.shape, **{k: v.shape for k, v in zip(list(vals)[1:], rest, strict=True)}}
        raise ValueError(f"params: batch shapes do not broadcast: {shapes}") from None
    return SolverParams(
        jnp.broadcast_to(r, (*batch, J)), *(jnp.broadcast_to(v, batch) for v in rest)
    )


def as_params(params: SolverParams, n_objectives: int, dtype: Any) -> SolverParams:
    """``params`` for one solve: rho broadcast to (J,), every leaf cast to ``dtype``.

    TypeError when ``params`` is not a :class:`SolverParams`; ValueError on a
    rho of the wrong length.
    """
    if not isinstance(params, SolverParams):
        raise TypeError(
            f"params: expected a SolverParams (formulation.params(...)), got {type(params).__name__}"
        )
    r = jnp.asarray(params.rho, dtype)
    if r.ndim > 1 or (r.ndim == 1 and r.shape[0] not in (1, n_objectives)):
        raise ValueError(
            f"params.rho: expected () or ({n_objectives},) for one solve (vmap over "
            f"batch axes), got shape {r.shape}"
        )
    return SolverParams(
        rho=jnp.broadcast_to(r, (n_objectives,)),
        relaxation=jnp.asarray(params.relaxation, dtype),
        tol_primal=jnp.asarray(params.tol_primal, dtype),
        tol_dual=jnp.asarray(params.tol_dual, dtype),
        tol_rel=jnp.asarray(params.tol_rel, dtype),
    )
