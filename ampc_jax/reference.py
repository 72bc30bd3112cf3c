"""Reference solvers of the integrated MPC: Clarabel (interior point) and OSQP.

The condensed QP of eq.integMPC (:func:`~ampc_jax.problem.condensed_qp`)
solved by established solvers that no one here wrote: the reference optimum
every formulation is tested against. Both return the same
:class:`~ampc_jax.results.SolveResult` as the formulations (numpy arrays).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from .problem.condensed import CondensedQP, condensed_qp, cost_offset
from .problem.data import ProblemData
from .problem.topology import Topology
from .results import SolveResult, SolveStats, Status, usable

__all__ = [
    "OSQPReference",
    "clarabel_solve",
    "qp_gap",
    "reference_gap",
    "reference_inputs",
    "solve_reference",
]


def _numpy_qp(topology: Topology, data: ProblemData) -> CondensedQP:
    qp = condensed_qp(topology, data)
    return CondensedQP(*(np.asarray(x, dtype=float) for x in qp))


def clarabel_solve(qp: CondensedQP, eps: float = 1e-9) -> Any:
    """Clarabel on ``min 1/2 U'HU + E'U s.t. G U <= h`` (numpy arrays); its
    solution object (``x``, multipliers ``z``, slacks ``s``, ``status``, ...).

    ``eps`` sets the gap and feasibility tolerances (and the KKT ratio, at most
    1e-6).
    """
    import clarabel

    P = sp.triu(sp.csc_matrix(qp.H), format="csc")
    A = sp.csc_matrix(qp.G)
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = eps
    settings.tol_gap_rel = eps
    settings.tol_feas = eps
    settings.tol_ktratio = min(1e-6, eps)
    cones = [clarabel.NonnegativeConeT(A.shape[0])] if A.shape[0] else []
    return clarabel.DefaultSolver(P, qp.E, A, qp.h, cones, settings).solve()


_REFERENCE_GAP = 1e-5
"""Relative duality gap above which a solve reported as solved is downgraded to
``solved_inaccurate`` (:func:`solve_reference`)."""


def reference_gap(qp: CondensedQP, x: Any, z: Any, offset: float) -> float:
    """The duality gap sum_i |z_i (h - G x)_i| of a QP solution, relative to
    max(1, J(x)) with J the full cost (condensed cost plus ``offset``).

    Solvers measure their gap relative to the condensed cost, which drops the
    constant: with large weights |1/2 x'Hx + E'x| is many orders above the
    true cost J, and a "solved" point can miss the optimum by far more than
    the requested tolerance in J (e.g. Q = 1e10: cost 22.5 against 19.45).
    """
    x = np.asarray(x, float)
    z = np.asarray(z, float)
    if qp.G.shape[0] == 0:
        return 0.0
    slack = qp.h - qp.G @ x
    gap = float(np.sum(np.abs(z * slack)))  # no cancellation between rows
    J = 0.5 * float(x @ qp.H @ x) + float(qp.E @ x) + offset
    return gap / max(1.0, abs(J))


def qp_gap(qp: CondensedQP, x: Any, z: Any) -> float:
    """The duality gap of ``x`` with multipliers ``z`` (clipped at 0) on the
    condensed QP: J(x) minus the Lagrangian dual bound of z, in the form of
    :func:`~ampc_jax.admm.stopping.duality_gap` (the same definition as the
    formulations' ``stats.gap``)::

        gap = 1/2 g'H^-1 g + z'(h - G x),   g = H x + E + G'z

    inf when x or z is not finite or H is singular."""
    x = np.asarray(x, float)
    z = np.maximum(np.asarray(z, float), 0.0)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(z))):
        return float("inf")
    g = qp.H @ x + qp.E + qp.G.T @ z
    try:
        Hg = np.linalg.solve(qp.H, g)
    except np.linalg.LinAlgError:
        return float("inf")
    return float(0.5 * g @ Hg + z @ (qp.h - qp.G @ x))


def solve_reference(
    topology: Topology,
    data: ProblemData,
    solver: str = "clarabel",
    *,
    eps: float = 1e-9,
) -> SolveResult:
    """Solve the integrated QP with Clarabel (default) or OSQP; numpy in, numpy out.

    ``eps`` sets the solver's tolerances. The returned ``u`` is (N_p, n_u);
    residual fields hold the solver's primal and dual residuals when it reports
    them (as 1-element arrays). ``stats.solve_time`` holds the solve time in
    seconds (Clarabel: setup and solve; OSQP: the solve after its setup) and
    ``stats.gap`` the duality gap of the solution (:func:`qp_gap`).

    A Clarabel solve it calls solved is reported as ``solved_inaccurate`` (5)
    when its duality gap exceeds 1e-5 of the full cost (:func:`reference_gap`):
    Clarabel's own gap test is relative to the condensed cost, which drops the
    constant and so can be orders of magnitude larger with large weights.
    """
    qp = _numpy_qp(topology, data)
    n = qp.H.shape[0]
    t0 = time.perf_counter()
    if solver == "clarabel":
        sol = clarabel_solve(qp, eps)
        elapsed = time.perf_counter() - t0
        name = str(sol.status)
        status = _reference_status(name)
        u = np.asarray(sol.x, dtype=float)
        if (
            status == Status.SOLVED
            and reference_gap(qp, u, sol.z, cost_offset(data)) > _REFERENCE_GAP
        ):
            status = Status.SOLVED_INACCURATE  # solved by Clarabel's measure, not the full cost's
        if not usable(status):  # an infeasibility certificate is no input
            u = np.full_like(u, np.nan)
        gap = qp_gap(qp, u, sol.z) if u.size == n else float("inf")
        iters = int(sol.iterations)
        pres = float(getattr(sol, "r_prim", np.nan))
        dres = float(getattr(sol, "r_dual", np.nan))
    elif solver == "osqp":
        ref = OSQPReference(topology, data, eps=eps)
        t0 = time.perf_counter()  # setup excluded, as for a warm update + solve
        res = ref.solve()
        elapsed = time.perf_counter() - t0
        return res._replace(stats=SolveStats(gap=ref.gap(res), solve_time=elapsed))
    else:
        raise ValueError(f"solver: expected 'clarabel' or 'osqp', got {solver!r}")
    return SolveResult(
        u=u.reshape(topology.horizon, topology.n_u)
        if u.size == n
        else np.full((topology.horizon, topology.n_u), np.nan),
        iterations=iters,
        converged=status == Status.SOLVED,
        status=int(status),
        primal_residual=np.array([pres]),
        dual_residual=np.array([dres]),
        rho=np.array([np.nan]),
        stats=SolveStats(gap=gap, solve_time=elapsed),
    )


def reference_inputs(topology: Topology, data: ProblemData, eps: float = 1e-9) -> np.ndarray:
    """U* (n, N_p, n_u) of every case of a batched ``data`` (leading axis n):
    the integrated optimum by Clarabel (:func:`solve_reference`), float64, NaN
    for a case without a usable solution."""
    import jax

    host = jax.tree.map(lambda x: np.asarray(x, np.float64), data)
    n = int(np.shape(host.x0)[0])
    out = np.full((n, topology.horizon, topology.n_u), np.nan)
    for i in range(n):
        res = solve_reference(topology, jax.tree.map(lambda x, i=i: x[i], host), eps=eps)
        if usable(int(res.status)):
            out[i] = np.asarray(res.u, float)
    return out


def _reference_status(name: str) -> Status:
    """Clarabel's or OSQP's status text as a :class:`~ampc_jax.results.Status`.

    Clarabel: ``Solved``, ``AlmostSolved``, ``PrimalInfeasible``, ...; OSQP:
    ``solved``, ``solved inaccurate``, ``primal infeasible``, ... An inaccurate
    solution is kept apart from a solved one (``SOLVED_INACCURATE``), so that a
    test asking for the reference optimum does not accept it.
    """
    low = name.lower().replace(" ", "").replace("_", "")
    if "infeasible" in low:
        return Status.INFEASIBLE
    if low.startswith("almostsolved") or (low.startswith("solved") and "inaccurate" in low):
        return Status.SOLVED_INACCURATE
    if low.startswith("solved"):
        return Status.SOLVED
    return Status.SOLVER_ERROR


class OSQPReference:
    """OSQP on the integrated QP with the ``setup`` / ``update`` / ``solve`` story.

    ``update(data)`` changes q, P (same sparsity: dense upper triangle), the
    general rows' coefficients (same sparsity: the diagonal blocks of
    I (x) A_in kept dense) and the right-hand sides for a new control step, and
    keeps the previous solution as warm start.
    """

    def __init__(self, topology: Topology, data: ProblemData, *, eps: float = 1e-6) -> None:
        import osqp

        self.topology = topology
        qp = _numpy_qp(topology, data)
        self._qp = qp  # the QP held, for the duality gap of a solution
        self._y: Any = None  # the last solve's multipliers
        n = qp.H.shape[0]
        rows, cols = np.triu_indices(n)
        # Dense upper triangle with explicit zeros kept, so updates never change sparsity.
        P = sp.coo_matrix((qp.H[rows, cols], (rows, cols)), shape=(n, n)).tocsc()
        self._P_rows = P.indices
        self._P_cols = np.repeat(np.arange(P.shape[1]), np.diff(P.indptr))
        # G = I_{N_p} (x) A_in: every entry of its diagonal blocks kept (explicit
        # zeros too), so new general-row coefficients never change its sparsity
        N = topology.horizon
        nc, nu = np.shape(data.Ain)
        blocks = sp.kron(sp.identity(N, format="csc"), np.ones((nc, nu)), format="csc")
        G_rows = blocks.indices
        G_cols = np.repeat(np.arange(blocks.shape[1]), np.diff(blocks.indptr))
        A = sp.csc_matrix((qp.G[G_rows, G_cols], blocks.indices, blocks.indptr), blocks.shape)
        self._G_rows, self._G_cols = G_rows, G_cols
        self.solver = osqp.OSQP()
        self.solver.setup(
            P=P,
            q=qp.E,
            A=A,
            l=np.full(qp.h.shape, -np.inf),
            u=qp.h,
            eps_abs=eps,
            eps_rel=eps,
            max_iter=100000,
            polishing=True,
            verbose=False,
        )

    def _p_values(self, H: np.ndarray) -> np.ndarray:
        """P's values in its CSC data order (column-major over the upper triangle)."""
        return H[self._P_rows, self._P_cols]

    def update(self, data: ProblemData) -> None:
        """New control step: condense ``data`` and update q, P, A and the bounds."""
        self.update_qp(_numpy_qp(self.topology, data))

    def update_qp(self, qp: CondensedQP) -> None:
        """Update from an already condensed QP (numpy), skipping the condensing:
        q, P, the constraint rows' coefficients and their right-hand sides."""
        self._qp = qp
        self.solver.update(
            q=qp.E,
            u=qp.h,
            Px=self._p_values(qp.H),
            Ax=np.asarray(qp.G)[self._G_rows, self._G_cols],
        )

    def solve(self) -> SolveResult:
        """Solve the current QP (warm started from the last solution). Its duality
        gap is :meth:`gap` (a linear solve on the host, apart so that a timed
        solve is OSQP's alone)."""
        res = self.solver.solve(raise_error=False)  # failures become a status
        self._y = res.y
        info = res.info
        status = _reference_status(str(info.status))
        T = self.topology
        x = (
            np.asarray(res.x, dtype=float)
            if res.x is not None and usable(status)
            else np.full(T.horizon * T.n_u, np.nan)
        )
        return SolveResult(
            u=x.reshape(T.horizon, T.n_u),
            iterations=int(info.iter),
            converged=status == Status.SOLVED,
            status=int(status),
            primal_residual=np.array([float(info.prim_res)]),
            dual_residual=np.array([float(info.dual_res)]),
            rho=np.array([float(info.rho_estimate)]),
            state=None,
            stats=SolveStats(),
        )

    def gap(self, result: SolveResult) -> float:
        """:func:`qp_gap` of the last :meth:`solve`'s ``result`` with its multipliers
        (upper rows only, the lower bounds being -inf: y >= 0 up to OSQP's
        tolerance); inf without a solution."""
        if self._y is None:
            return float("inf")
        return qp_gap(self._qp, np.asarray(result.u).reshape(-1), self._y)
