"""The integrated (centralised) MPC, eq.integMPC with eq_linear, as one condensed QP.

Condensed over the horizon the integrated MPC is::

    min_U  1/2 U' H U + E' U      s.t.  Abar U <= bbar,
    H = 2 (sum_j Y_u,j' Qbar_j Y_u,j + Rbar),
    E = 2 sum_j Y_u,j' Qbar_j (Y_x,j X^(0) + Y_w,j Wbar - Xbar_ref,j),

with U = [U^(0); ...; U^(N_p-1)] over all agents and Abar = I (x) A_in. It is
the same problem as one objective that stacks every C_j, Q_j and reference and
owns all agents (:func:`merged_topology`, :func:`merged_data`): the JAX-native
integrated solver runs on that form, the reference solvers
(:mod:`ampc_jax.reference`) on :func:`condensed_qp`.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from ..prediction import prediction_matrices, quadratic_cost
from .data import ProblemData
from .topology import Topology

__all__ = ["CondensedQP", "condensed_qp", "cost_offset", "merged_data", "merged_topology"]


class CondensedQP(NamedTuple):
    """H (n, n), E (n,), G (m, n), h (m,) of ``min 1/2 U'HU + E'U s.t. G U <= h``."""

    H: Any
    E: Any
    G: Any
    h: Any


def merged_topology(topology: Topology) -> Topology:
    """The undecomposed problem as a one-objective topology (all agents, all outputs)."""
    return Topology(
        n_x=topology.n_x,
        horizon=topology.horizon,
        agent_names=topology.agent_names,
        agent_sizes=topology.agent_sizes,
        objective_names=("integrated",),
        output_sizes=(sum(topology.output_sizes),),
        groups=(tuple(range(topology.n_agents)),),
        box_rows=topology.box_rows,
        general_agents=topology.general_agents,
        covered_inputs=topology.covered_inputs,
        pinned_rank=topology.pinned_rank,
        group_rank=(topology.total_rank,),
        total_rank=topology.total_rank,
        singular_r=topology.singular_r,
    )


def merged_data(data: ProblemData) -> ProblemData:
    """Stack the objectives' C_j, block-diagonal Q_j and references into one objective."""
    return data._replace(
        C=(jnp.concatenate(data.C, axis=0),),
        Q=(jsl.block_diag(*data.Q),),
        ref=(jnp.concatenate(data.ref, axis=1),),
    )


# Jitted (the topology static): called eagerly (the reference solvers, ``ampc solve``'s
# checks) it is one compiled program instead of about 20 single operations, each a
# compilation of its own (0.7 s of ``ampc solve``'s start, ``bench/bench_compile.py``);
# inside a caller's ``jit`` it is inlined.
@partial(jax.jit, static_argnums=0)
def condensed_qp(topology: Topology, data: ProblemData) -> CondensedQP:
    """The integrated MPC as a condensed QP (jittable), from :mod:`ampc_jax.prediction`."""
    m = merged_data(data)
    pred = prediction_matrices(m.A, m.B, m.C[0], topology.horizon)
    H, E = quadratic_cost(pred, m.Q[0], m.R, m.x0, m.w, m.ref[0])
    G = jnp.kron(jnp.eye(topology.horizon, dtype=data.Ain.dtype), data.Ain)
    return CondensedQP(H=H, E=E, G=G, h=data.bin.reshape(-1))


def cost_offset(data: ProblemData) -> float:
    """The constant the condensed QP drops: sum_j sum_k e_j,k' Q_j e_j,k, with
    e_j,k = C_j x_free^(k+1) - ref_j^(k) the free response's tracking error
    (numpy). ``1/2 U'HU + E'U + cost_offset`` is eq.integMPC's cost J(U) >= 0.
    """
    A = np.asarray(data.A, float)
    x = np.asarray(data.x0, float)
    w = np.asarray(data.w, float)
    c0 = 0.0
    for k in range(w.shape[0]):
        x = A @ x + w[k]
        for C, Q, ref in zip(data.C, data.Q, data.ref, strict=True):
            e = np.asarray(C, float) @ x - np.asarray(ref, float)[k]
            c0 += float(e @ np.asarray(Q, float) @ e)
    return c0
