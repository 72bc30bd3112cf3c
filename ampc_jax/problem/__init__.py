"""The problem model: what a multi-objective MACS is, validated (paper, "Multi-objective MACS").

* :mod:`~ampc_jax.problem.spec` -- :class:`Problem` and its parts
  (:class:`Agent`, :class:`Objective`, :class:`Constraint`), from JSON or Python;
* :mod:`~ampc_jax.problem.topology` -- the static :class:`Topology`;
* :mod:`~ampc_jax.problem.data` -- the :class:`ProblemData` pytree and :func:`make_data`;
* :mod:`~ampc_jax.problem.condensed` -- the integrated MPC as one condensed QP
  (the reference optimum every formulation is measured against).
"""

from .condensed import CondensedQP, condensed_qp, cost_offset, merged_data, merged_topology
from .data import ProblemData, make_data
from .errors import ProblemError, ProblemWarning
from .spec import GROUP_TOL, Agent, Constraint, Objective, Problem
from .topology import Topology

__all__ = [
    "GROUP_TOL",
    "Agent",
    "CondensedQP",
    "Constraint",
    "Objective",
    "Problem",
    "ProblemData",
    "ProblemError",
    "ProblemWarning",
    "Topology",
    "condensed_qp",
    "cost_offset",
    "make_data",
    "merged_data",
    "merged_topology",
]
