"""The iterate of the ADMM formulations, its cold start and the MPC warm start."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ..problem.topology import Topology
from .layout import padded_layout

__all__ = ["ADMMState", "cold_state", "shift_horizon", "shift_state", "warm_start"]


class ADMMState(NamedTuple):
    """Iterate of an ADMM formulation in its padded, objective-stacked layout.

    The loop carries this state as it is, so a warm start goes in and the
    final iterate comes out without any regrouping (a control step costs no
    more array arguments with more objectives). J objectives, each padded to
    U = max_j n_u,j input columns and R constraint rows:

    U : (J, N_p, U) local inputs U_j; column a of objective j is input
        ``Topology.group_columns(j)[a]``, padded columns are ignored.
    Z : (N_p, n_c) global slack.
    gamma : (J, N_p, R) multipliers gamma_j, zero on the rows objective j does
        not carry and on padding. R is n_c (rows in the problem's numbering)
        or, when no objective carries every row, max_j n_c,j (objective j's own
        rows first, in ``Topology.group_rows(j)`` order).
    iteration : () int32.
    primal, dual : (J,) ||r_j||^2 and ||s_j||^2 of the last iteration.
    rho_star : (J,) eq.opt_ro's rho_j* the solve that made this iterate used, 0
        where none (the cold start; a solve asking the next one to estimate
        anew). ``rho_method="carried"`` starts from it instead of estimating.

    Per-objective views: :meth:`LocalExplicit.local_inputs`,
    :meth:`LocalExplicit.multipliers`; from per-objective arrays:
    :meth:`LocalExplicit.state_of`; cold start: :func:`cold_state`.
    """

    U: Any
    Z: Any
    gamma: Any
    iteration: Any
    primal: Any
    dual: Any
    rho_star: Any


def shift_horizon(x: Any, steps: int = 1, axis: int = 0) -> Any:
    """x moved one step along its horizon axis ``axis``, the last step repeated
    (``steps=1``), or unchanged (``steps=0``): the MPC warm start."""
    if steps not in (0, 1):
        raise ValueError(f"steps: expected 0 (hold) or 1 (shift), got {steps!r}")
    if not steps:
        return x
    n = x.shape[axis]
    head = jax.lax.slice_in_dim(x, 1, n, axis=axis)
    return jnp.concatenate([head, jax.lax.slice_in_dim(x, n - 1, n, axis=axis)], axis=axis)


def shift_state(state: ADMMState, steps: int = 1) -> ADMMState:
    """Warm start: the previous step's iterate shifted along the horizon.

    ``steps=1`` (default): step k+1 becomes step k and the last step is
    repeated, the usual MPC warm start. ``steps=0`` holds the previous iterate
    as it is (only the iteration count and residuals are reset): on the
    vehicle examples' short horizons (N_p = 2 to 3) that needed fewer
    iterations in the stability example (``docs/results.md``).
    """
    inf = jnp.full_like(state.primal, jnp.inf)
    return ADMMState(
        U=shift_horizon(state.U, steps, axis=1),
        Z=shift_horizon(state.Z, steps),
        gamma=shift_horizon(state.gamma, steps, axis=1),
        iteration=jnp.zeros((), jnp.int32),
        primal=inf,
        dual=inf,
        rho_star=state.rho_star,
    )


def cold_state(topology: Topology, dtype: Any = None) -> ADMMState:
    """The cold start of alg:1 for ``topology``: zeros, residuals inf (``dtype``:
    default JAX's float, float64 with ``jax_enable_x64``)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    lay = padded_layout(topology)
    J, U = lay.cols.shape
    N = topology.horizon
    return ADMMState(
        U=jnp.zeros((J, N, U), dtype),
        Z=jnp.zeros((N, topology.n_c), dtype),
        gamma=jnp.zeros((J, N, lay.rows.shape[1]), dtype),
        iteration=jnp.zeros((), jnp.int32),
        primal=jnp.full((J,), jnp.inf, dtype),
        dual=jnp.full((J,), jnp.inf, dtype),
        rho_star=jnp.zeros((J,), dtype),
    )


def warm_start(cold: Any, warm: Any, expected: str, shape_hint: str = "") -> Any:
    """``warm`` checked against the formulation's ``cold`` state (its NamedTuple type
    and every field's shape), with its iteration count and residuals reset, so
    that a previous result's ``.state`` passed as it is still iterates on new
    data; ``cold`` when ``warm`` is None. ``expected`` and ``shape_hint`` word
    the TypeError and ValueError."""
    if warm is None:
        return cold
    if not isinstance(warm, type(cold)):
        raise TypeError(f"warm: expected {expected}, got {type(warm).__name__}")
    for name, want, got in zip(type(cold)._fields, cold, warm, strict=True):
        if jnp.shape(got) != want.shape:
            raise ValueError(
                f"warm.{name}: expected shape {want.shape} for this topology"
                f"{shape_hint}, got {jnp.shape(got)}"
            )
    return warm._replace(iteration=cold.iteration, primal=cold.primal, dual=cold.dual)
