"""The stopping rule (eq.Convergence, with relative tolerances) and the duality gap.

eq.Convergence tests, per objective, ||r_j||^2 <= eps_r and ||s_j||^2 <= eps_s:
absolute tolerances on squared norms, in the units of the rows. After OSQP
(Stellato et al. 2020, sec. 3.4: eps_abs + eps_rel x scale) a relative
tolerance eps_rel (``SolverParams.tol_rel``) widens both tests to
(:func:`converged`)::

    ||r_j||^2 <= eps_r + eps_rel^2 scale_j^2,    ||s_j||^2 <= eps_s + eps_rel^2 scale_j'^2

with scale_j^2 = ||Z_j||^2 + ||b_j||^2, the sizes of objective j's part of
the global iterate Z and of the right-hand sides its rows are measured
against (scale_j' = rho_j scale_j for the dual residual as printed), so that
the rule reads the same whatever the problem's units; eps_rel = 0 is the
absolute rule exactly.

Neither residual bounds the distance to the optimum. The duality gap of a
result does (:func:`duality_gap`): for inputs u that satisfy every row,
1/2 ||u - U*||_H^2 <= J(u) - J* <= gap, H the integrated Hessian, so
||u - U*|| <= sqrt(2 gap / lambda_min(H)).

What s_j is comes in two forms, strategies behind one interface (``dual``,
``scale``) chosen by name at construction (``dual_residual``;
:func:`select_dual_residual`):

* :class:`ChangeResidual` (``"slack"`` in Local Explicit, ``"change"`` in
  Formulations 1 and 2; the default) -- the change of the global variable
  between iterations, Z_j^q - Z_j^(q-1), in its own units;
* :class:`PaperResidual` (``"paper"``) -- rho_j (Z_j^q - Z_j^(q-1)), as printed.
  It scales with rho_j, and eq.opt_ro gives rho_j ~ 1e-6 when the weights are
  per Nm^2 (the vehicle examples): a fixed eps_s is then met while Z still
  moves by newtons.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp

__all__ = [
    "DUAL_RESIDUALS",
    "ChangeResidual",
    "PaperResidual",
    "converged",
    "duality_gap",
    "select_dual_residual",
]


@dataclass(frozen=True)
class ChangeResidual:
    """s_j = Z_j^q - Z_j^(q-1): the global variable's change, in its own units."""

    name: str = "slack"

    def dual(self, rho: Any, dz: Any) -> Any:
        """The tested dual residual from the change ``dz`` (J, ...) and rho (J, 1, 1)."""
        return dz

    def scale(self, rho: Any, scale2: Any) -> Any:
        """(J,) the dual test's squared scale from the primal one's (rho (J,))."""
        return scale2


@dataclass(frozen=True)
class PaperResidual:
    """s_j = rho_j (Z_j^q - Z_j^(q-1)), eq.Convergence as printed."""

    name: str = "paper"

    def dual(self, rho: Any, dz: Any) -> Any:
        return rho * dz

    def scale(self, rho: Any, scale2: Any) -> Any:
        return rho * rho * scale2


DUAL_RESIDUALS: dict[str, Any] = {
    "slack": ChangeResidual("slack"),
    "change": ChangeResidual("change"),
    "paper": PaperResidual(),
}
"""``dual_residual`` name -> strategy (a formulation accepts some of them)."""


def select_dual_residual(name: str, allowed: tuple[str, ...]) -> Any:
    """The dual-residual strategy ``name`` among ``allowed``, or a ValueError
    naming ``dual_residual``."""
    if name not in allowed:
        raise ValueError(f"dual_residual: expected one of {allowed}, got {name!r}")
    return DUAL_RESIDUALS[name]


def converged(
    primal: Any,
    dual: Any,
    tol_primal: Any,
    tol_dual: Any,
    tol_rel: Any,
    scale2: Any,
    dual_scale2: Any,
) -> Any:
    """eq.Convergence for every objective with the relative tolerance::

        ||r_j||^2 <= eps_r + eps_rel^2 scale_j^2,   ||s_j||^2 <= eps_s + eps_rel^2 scale_j'^2

    (squared residuals (J,); ``scale2``, ``dual_scale2`` the squared scales).
    OSQP's eps_abs + eps_rel * scale with the two parts added in quadrature
    (within a factor sqrt(2) of the sum): no square root per iteration, and
    eps_rel = 0 is the absolute rule exactly. Rule: a scale costs a few
    operations per iteration, the data part precomputed in the setup, because
    the test runs in every iteration's loop condition: OSQP's max(||Abar_j
    U_j||, ||Z_j||) summed over (J, N_p, R) there took 0.5 us of an
    iteration's 1.5 us on the cruise example at N_p = 10 (a step of 36
    iterations, 213 against 230 us), ``||Z_j||^2`` as one product no
    measurable time.
    """
    rel2 = tol_rel * tol_rel
    ok = (primal <= tol_primal + rel2 * scale2) & (dual <= tol_dual + rel2 * dual_scale2)
    return jnp.all(ok)


def duality_gap(hessian: Any, E: Any, u: Any, mu: Any, complementarity: Any) -> Any:
    """() J(u) - g(mu, lambda): the cost of inputs u minus a Lagrangian dual bound.

    The integrated MPC is min sum_j f_j(P_j U) s.t. Abar U <= b, with f_j(x) =
    1/2 x'H_j x + E_j'x + c_j objective j's local cost (its tracking cost and
    its agents' R_(i) / m_(i); the sum is the integrated cost when every agent
    that moves O_j's outputs is in S_j). With the copies U_j = P_j U dualised
    by mu_j and the rows by lambda >= 0, where sum_j P_j' mu_j = Abar' lambda,
    the dual function is g = sum_j [c_j - 1/2 w_j' H_j^-1 w_j] - lambda'b <= J*
    (w_j = E_j + mu_j). Its gap at u is, exactly::

        gap = sum_j 1/2 g_j' H_j^-1 g_j + lambda'(b - Abar u),
        g_j = H_j u_j + E_j + mu_j

    (each local Lagrangian's gradient at u, and the complementarity): two sums
    of terms >= 0 for feasible u, with no cancellation between large
    numbers, so the gap is accurate where it is small. gap >= J(u) - J*.

    Arguments, objectives stacked on axis 0 in the padded layout: ``hessian``
    (:mod:`~.hessian`), ``E``, ``u``, ``mu`` (J, n), ``complementarity`` () =
    lambda'(b - Abar u). Computed in a result, not per iteration.
    """
    g = hessian.apply(u[:, None])[:, 0] + E + mu
    return 0.5 * jnp.sum(g * hessian.solve(g[:, None])[:, 0]) + complementarity
