"""The numbers of one MACS instance: the :class:`ProblemData` pytree.

Only these arrays are traced by JAX, so a time-varying model (the vehicle
examples re-linearise every step) is rebuilt inside one compiled step with
:func:`make_data`, and batches of scenarios are ``vmap``-ed over
:class:`ProblemData`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .topology import Topology

__all__ = ["ProblemData", "make_data"]


class ProblemData(NamedTuple):
    """Arrays of one MACS instance (a pytree; ``vmap`` over a leading batch axis).

    Attributes
    ----------
    A : (n_x, n_x) A_d.
    B : (n_x, n_u) [B_d(i) for all agents], columns in agent order.
    w : (N_p, n_x) W_d^(k), k = 0..N_p-1.
    x0 : (n_x,) X^(0).
    R : (n_u, n_u) block-diagonal [R_(i)].
    C, Q, ref : tuples over objectives of (n_y, n_x), (n_y, n_y), (N_p, n_y);
        ``ref[j][k]`` is the reference of C_j X^(k+1).
    Ain : (n_c, n_u) constraint rows A_in (box rows, then general rows).
    bin : (N_p, n_c) right-hand sides b_in^(k).
    lb, ub : (N_p, n_u) the bounds (+-inf where absent), for projecting outputs.
    """

    A: Any
    B: Any
    w: Any
    x0: Any
    R: Any
    C: tuple
    Q: tuple
    ref: tuple
    Ain: Any
    bin: Any
    lb: Any
    ub: Any


def make_data(
    topology: Topology,
    *,
    A: Any,
    B: Any,
    x0: Any,
    C: Sequence[Any],
    Q: Sequence[Any],
    ref: Sequence[Any],
    R: Any,
    lb: Any,
    ub: Any,
    w: Any = None,
    G: Any = None,
    g: Any = None,
    dtype: Any = None,
) -> ProblemData:
    """Assemble :class:`ProblemData` (jittable; used for time-varying models).

    ``B`` may be the (n_x, n_u) concatenation or a sequence of per-agent blocks;
    ``R`` the (n_u, n_u) matrix or a sequence of per-agent blocks; ``lb``/``ub``
    (n_u,) or (N_p, n_u) (also sequences of per-agent vectors); ``ref[j]``
    (n_y,) or (N_p, n_y); ``w`` (n_x,) or (N_p, n_x); ``G`` (n_g, n_u) and ``g``
    (n_g,) or (N_p, n_g) the general rows.
    """
    Np, nx, nu = topology.horizon, topology.n_x, topology.n_u
    if dtype is None:
        dtype = jnp.result_type(float)

    def arr(x: Any) -> Any:
        return jnp.asarray(x, dtype=dtype)

    def per_step(x: Any, n: int) -> Any:
        x = arr(x)
        return jnp.broadcast_to(x, (Np, n)) if x.ndim <= 1 else x

    if isinstance(B, (list, tuple)):
        B = jnp.concatenate([arr(b).reshape(nx, -1) for b in B], axis=1)
    if isinstance(R, (list, tuple)):
        blocks = [arr(r) for r in R]
        blocks = [jnp.diag(r) if r.ndim == 1 else r.reshape(r.shape[-1], -1) for r in blocks]
        R = jsl.block_diag(*blocks)
    if isinstance(lb, (list, tuple)):
        lb = jnp.concatenate([jnp.atleast_1d(arr(x)) for x in lb], axis=-1)
    if isinstance(ub, (list, tuple)):
        ub = jnp.concatenate([jnp.atleast_1d(arr(x)) for x in ub], axis=-1)
    lb, ub = per_step(lb, nu), per_step(ub, nu)
    w = jnp.zeros((Np, nx), dtype) if w is None else per_step(w, nx)
    Cs = tuple(arr(c).reshape(ny, nx) for c, ny in zip(C, topology.output_sizes, strict=True))
    Qs = tuple(
        (jnp.diag(arr(q).reshape(ny)) if arr(q).ndim <= 1 else arr(q))
        for q, ny in zip(Q, topology.output_sizes, strict=True)
    )
    refs = tuple(per_step(r, ny) for r, ny in zip(ref, topology.output_sizes, strict=True))

    up = [k for k, s in topology.box_rows if s > 0]
    lo = [k for k, s in topology.box_rows if s < 0]
    box_A = np.zeros((len(topology.box_rows), nu))
    for r, (k, s) in enumerate(topology.box_rows):
        box_A[r, k] = s
    box_b = jnp.concatenate([ub[:, up], -lb[:, lo]], axis=1)
    n_gen = len(topology.general_agents)
    if n_gen:
        G = arr(G).reshape(n_gen, nu)
        g = per_step(g, n_gen)
        Ain = jnp.concatenate([arr(box_A), G], axis=0)
        bin_ = jnp.concatenate([box_b, g], axis=1)
    else:
        Ain, bin_ = arr(box_A), box_b
    return ProblemData(
        A=arr(A),
        B=arr(B),
        w=w,
        x0=arr(x0),
        R=arr(R),
        C=Cs,
        Q=Qs,
        ref=refs,
        Ain=Ain,
        bin=bin_,
        lb=lb,
        ub=ub,
    )
