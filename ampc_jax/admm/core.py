"""The ADMM core protocol, declared once, and its runners, written once.

After jaxopt's ``IterativeSolver`` (a solver is ``init`` and ``update``; the
base class runs them) and optax's ``init`` / ``update`` pair: every
formulation is an :class:`ADMMSolver` and implements the protocol

* ``setup(data, params) -> setup`` -- per control step: costs, rho_j and the
  factorisations, built once (everything the iteration only reads);
* ``init(setup, warm=None) -> state`` -- the cold start of alg:1, or a warm
  start with its iteration count and residuals reset;
* ``step(setup, state) -> state`` -- one iteration of alg:1 (local, global
  and dual updates, and the stopping rule's residuals);
* ``converged(setup, state) -> bool`` -- the stopping rule (eq.Convergence);
* ``result(setup, state) -> SolveResult`` -- the inputs, the status and
  the residuals of the iterate;
* ``point(state) -> x`` and ``at(x, state) -> state`` -- the ADMM map's
  argument as one vector and back, what Anderson acceleration extrapolates;
* ``cold_state(dtype)`` and ``shift(state, steps)`` -- the warm-start story;

with its static options as fields (``topology``, ``max_iter``, ``anderson``,
...). The runners are this class's: :meth:`~ADMMSolver.run` (a ``while_loop``
to the stopping rule, for deployment), :meth:`~ADMMSolver.run_fixed` (a
fixed-length ``scan``, differentiable, for tuning), :meth:`~ADMMSolver.solve`
and :meth:`~ADMMSolver.solve_fixed` (setup, init, run, result) and
:meth:`~ADMMSolver.params`. Anything that iterates a formulation in its own
way (the sweep engine's segmented runner, :mod:`ampc_jax.sweep.engine`) uses
these protocol methods only.
"""

from __future__ import annotations

import abc
from typing import Any

from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..results import SolveResult
from .feasibility import with_certificate
from .params import DEFAULT_TOL, DEFAULT_TOL_REL, SolverParams, solver_params
from .runners import run_fixed, run_while

__all__ = ["ADMMSolver"]


class ADMMSolver(abc.ABC):
    """An ADMM formulation: the core protocol (abstract) and the runners built on it.

    Subclasses are frozen dataclasses whose fields are the static options;
    they must have ``topology``, ``max_iter`` (the ``while_loop`` runner's cap)
    and ``anderson`` (Anderson memory, 0 for the plain iteration). The numbers
    one tunes are the :class:`~ampc_jax.admm.params.SolverParams` argument, so
    one compiled step serves every parameter point.
    """

    topology: Topology
    max_iter: int
    anderson: int

    # -- the protocol ------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def n_rho(self) -> int:
        """Number of rho_j (the length of ``params.rho``)."""

    @abc.abstractmethod
    def setup(self, data: ProblemData, params: SolverParams | None = None) -> Any:
        """Everything the iteration reads, built and factorised once per control step."""

    @abc.abstractmethod
    def init(self, setup: Any, warm: Any = None) -> Any:
        """The cold start, or ``warm`` (checked) with its iteration count and residuals reset."""

    @abc.abstractmethod
    def step(self, setup: Any, state: Any) -> Any:
        """One iteration (alg:1 steps 5-9), with the stopping rule's residuals."""

    @abc.abstractmethod
    def converged(self, setup: Any, state: Any) -> Any:
        """The stopping rule (eq.Convergence) at ``state``: a () bool."""

    @abc.abstractmethod
    def result(self, setup: Any, state: Any) -> SolveResult:
        """The :class:`~ampc_jax.results.SolveResult` of ``state``."""

    @abc.abstractmethod
    def point(self, state: Any) -> Any:
        """The ADMM map's argument at ``state`` as one vector (what Anderson extrapolates)."""

    @abc.abstractmethod
    def at(self, x: Any, state: Any) -> Any:
        """``state`` with its map argument replaced by the vector ``x`` (:meth:`point`'s inverse)."""

    @abc.abstractmethod
    def cold_state(self, dtype: Any = None) -> Any:
        """alg:1's cold start (zeros, residuals inf) in ``dtype``."""

    @abc.abstractmethod
    def shift(self, state: Any, steps: int = 1) -> Any:
        """The MPC warm start: ``state`` moved ``steps`` (0 or 1) along the horizon."""

    # -- the runners, once ---------------------------------------------------------------
    def params(
        self,
        rho: Any = 1.0,
        relaxation: Any = 1.0,
        tol_primal: Any = DEFAULT_TOL,
        tol_dual: Any = DEFAULT_TOL,
        dtype: Any = None,
        *,
        tol_rel: Any = DEFAULT_TOL_REL,
    ) -> SolverParams:
        """Validated :class:`SolverParams` with ``n_rho`` rho values
        (:func:`~ampc_jax.admm.params.solver_params`): ``rho`` a factor on the
        formulation's automatic rho_j (rho_j itself with ``rho_method="given"``),
        default 1.0; ``relaxation`` in (0, 2), default 1.0 (the paper);
        absolute tolerances default 1e-6, the relative one ``tol_rel`` 0
        (:class:`~ampc_jax.admm.params.SolverParams`)."""
        return solver_params(
            self.n_rho,
            rho=rho,
            relaxation=relaxation,
            tol_primal=tol_primal,
            tol_dual=tol_dual,
            tol_rel=tol_rel,
            dtype=dtype,
        )

    def setup_from(self, data: ProblemData, params: SolverParams | None, warm: Any) -> Any:
        """:meth:`setup` for a solve starting from ``warm`` (a previous result's
        state or None): a formulation whose setup reuses something the warm
        start carries (Local Explicit's ``rho_method="carried"``) overrides it."""
        return self.setup(data, params)

    def finisher(self, setup: Any) -> Any:
        """The exact finish of an iterate, ``finish(before, after, ran) -> state``
        (:mod:`~.finish`), tried every :attr:`finish_every` iterations by the
        runners; None (default) where the formulation has none or it is off."""
        return None

    finish_every: int = 1
    finish_first: int = 1

    def run(self, setup: Any, state: Any) -> Any:
        """``lax.while_loop`` until :meth:`converged`, ``max_iter`` or a non-finite
        residual (deployment; no reverse-mode derivative); with a finish
        (:meth:`finisher`), in segments of ``finish_every`` iterations, each
        ended by a finish attempt."""
        return run_while(
            lambda st: self.step(setup, st),
            lambda st: self.converged(setup, st),
            state,
            self.max_iter,
            anderson=self.anderson,
            point=self.point,
            at=self.at,
            finish=self.finisher(setup),
            every=self.finish_every,
            first=self.finish_first,
        )

    def run_fixed(self, setup: Any, state: Any, iterations: int) -> Any:
        """Exactly ``iterations`` iterations under ``lax.scan`` (differentiable)."""
        return run_fixed(
            lambda st: self.step(setup, st),
            state,
            iterations,
            anderson=self.anderson,
            point=self.point,
            at=self.at,
        )

    def solve(
        self, data: ProblemData, params: SolverParams | None = None, warm: Any = None
    ) -> SolveResult:
        """One control step to tolerance: setup, init, :meth:`run`, result, and
        the infeasibility search when it did not converge
        (:func:`~ampc_jax.admm.feasibility.with_certificate`).

        ``params``: the :class:`SolverParams` (default :meth:`params` ()), an
        argument of the compiled step; ``warm``: a previous result's ``state``
        (shifted with :meth:`shift`). Pure and jittable; vmap over ``data`` and
        ``params`` together."""
        setup = self.setup_from(data, params, warm)
        res = self.result(setup, self.run(setup, self.init(setup, warm)))
        return with_certificate(res, data)

    def solve_fixed(
        self,
        data: ProblemData,
        iterations: int,
        params: SolverParams | None = None,
        warm: Any = None,
    ) -> SolveResult:
        """One control step with a fixed iteration count (:meth:`run_fixed`): for
        ``jax.grad`` with respect to ``data`` and ``params``."""
        setup = self.setup_from(data, params, warm)
        return self.result(setup, self.run_fixed(setup, self.init(setup, warm), iterations))
