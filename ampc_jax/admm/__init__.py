"""The consensus-ADMM machinery every formulation shares (paper, alg:1).

* :mod:`~.layout` -- the padded, objective-stacked layout;
* :mod:`~.costs` -- each objective's local cost H_j, E_j (eq.F3_primal_1);
* :mod:`~.linalg` -- the small factorisations (pure JAX when batched);
* :mod:`~.kkt` -- the KKT solve strategies of the local step;
* :mod:`~.rho` -- eq.opt_ro, exactly or by power iteration;
* :mod:`~.acceleration` -- Anderson acceleration;
* :mod:`~.params` -- :class:`SolverParams`, the tunable numbers as data;
* :mod:`~.state` -- :class:`ADMMState`, cold and warm starts;
* :mod:`~.runners` -- the ``while_loop`` and fixed-``scan`` runners;
* :mod:`~.core` -- :class:`ADMMSolver`, the core protocol every formulation
  implements (setup, init, step, converged, result, point / at) and the
  runners written once on it; :class:`FormulationInfo`, what a formulation
  declares it is.
"""

from .core import ADMMSolver, FormulationInfo
from .params import DEFAULT_TOL, SolverParams, solver_params
from .state import ADMMState, cold_state, shift_horizon, shift_state

__all__ = [
    "DEFAULT_TOL",
    "ADMMSolver",
    "ADMMState",
    "FormulationInfo",
    "SolverParams",
    "cold_state",
    "shift_horizon",
    "shift_state",
    "solver_params",
]
