"""The padded, objective-stacked layout the ADMM formulations iterate in.

The objectives are stacked on a leading axis j and padded to common sizes, so
every per-objective operation is one batched call (one factorisation, one
matrix-vector product per iteration for all objectives). Padded inputs carry
an identity block in K_j and zero columns in A_in,j, so they never move.
:func:`padded_layout` gives the static index maps of one topology.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from ..problem.topology import Topology

__all__ = ["COMPACT_ROWS", "Layout", "padded_layout"]


class Layout(NamedTuple):
    """Static index maps of the padded, objective-stacked layout."""

    cols: np.ndarray  # (J, U) input index of each padded column; n_u for padding
    umask: np.ndarray  # (J, U) 1 for a real input
    carried: np.ndarray  # (J, n_c) 1 where objective j carries constraint row c
    compact: bool  # rows gathered per objective (see COMPACT_ROWS) instead of all n_c
    rows: np.ndarray  # (J, R) constraint row behind each of objective j's R rows; n_c (a
    # zero row) for padding or a row j does not carry. Compact: R = C, j's own rows
    # first; otherwise R = n_c in the problem's numbering.
    inv: np.ndarray  # (J, n_c) compact: padded row of objective j carrying row c; C if none
    P: np.ndarray  # (J, U, n_u) 0/1 selection: padded column -> input
    scale: np.ndarray  # (J, U) 1 / m_(i) of each column's agent (0 for padding)
    u_sizes: tuple  # n_u,j
    c_sizes: tuple  # n_c,j
    y_sizes: tuple  # n_y,j
    full: tuple  # A_in,j has full column rank (eq.opt_ro without a threshold)


@functools.lru_cache(maxsize=64)
def padded_layout(topology: Topology) -> Layout:
    T = topology
    J = T.n_objectives
    u_sizes = tuple(len(T.group_columns(j)) for j in range(J))
    c_sizes = tuple(len(T.group_rows(j)) for j in range(J))
    U = max(u_sizes)
    cols = np.full((J, U), T.n_u, np.int32)
    carried = np.zeros((J, T.n_c))
    C = max(1, max(c_sizes))
    rows = np.full((J, C), T.n_c, np.int32)
    inv = np.full((J, T.n_c), C, np.int32)
    P = np.zeros((J, U, T.n_u))
    scale = np.zeros((J, U))
    mult = T.multiplicity
    for j in range(J):
        cj = T.group_columns(j)
        cols[j, : len(cj)] = cj
        for a, k in enumerate(cj):
            P[j, a, k] = 1.0
            scale[j, a] = 1.0 / mult[T.agent_of_input(k)]
        rj = list(T.group_rows(j))
        carried[j, rj] = 1.0
        rows[j, : len(rj)] = rj
        inv[j, rj] = np.arange(len(rj))
    compact = T.n_c > COMPACT_ROWS * C
    if not compact:
        rows = np.where(carried > 0, np.arange(T.n_c), T.n_c).astype(np.int32)
    umask = (cols < T.n_u).astype(np.float64)
    full = tuple(T.group_rank[j] == u_sizes[j] for j in range(J))
    return Layout(
        cols,
        umask,
        carried,
        compact,
        rows,
        inv,
        P,
        scale,
        u_sizes,
        c_sizes,
        tuple(T.output_sizes),
        full,
    )


# Row layout of the iteration. When some objective carries every constraint row
# (C = n_c; the cruise benchmark, the integrated problem), every objective works
# on all n_c rows in the problem's numbering, those it does not carry masked:
# the global step then needs no gather (batched at N_p = 10, 0.90 against
# 1.13 us per iteration gathered). Otherwise (n_c > COMPACT_ROWS * C) each
# objective's own rows are gathered into C padded rows: with all rows, generated
# chains of J objectives (N_p = 10, one problem, K^-1 formed or factored) cost
# 1.1x to 1.2x per iteration at J = 2, 1.8x to 2.1x at J = 8 and 3.3x to 3.8x
# at J = 16, and the closed-loop cruise step (n_c = 8, C = 6) about 1 us more.
COMPACT_ROWS = 1.0
