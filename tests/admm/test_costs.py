"""ampc_jax.admm.costs: the padded, objective-stacked local costs H_j, E_j."""

import numpy as np
import pytest

from ampc_jax.admm.costs import local_costs
from ampc_jax.generate import random_problem

pytestmark = pytest.mark.timeout(60)


def test_local_costs_match_prediction_quadratic_cost():
    """The batched, padded costs equal the per-objective prediction module's."""
    from ampc_jax.prediction import prediction_matrices, quadratic_cost

    p = random_problem(3, 3, shared="both")
    T, d = p.topology, p.data()
    H, E = local_costs(T, d)
    for j in range(T.n_objectives):
        cols = np.asarray(T.group_columns(j))
        scale = np.concatenate(
            [np.full(T.agent_sizes[i], 1.0 / T.multiplicity[i]) for i in T.groups[j]]
        )
        R = np.asarray(d.R)[np.ix_(cols, cols)] * scale[:, None]
        pred = prediction_matrices(d.A, d.B[:, cols], d.C[j], T.horizon)
        Hr, Er = quadratic_cost(pred, d.Q[j], R, d.x0, d.w, d.ref[j])
        np.testing.assert_allclose(H[j], Hr, rtol=1e-10, atol=1e-12 * np.abs(Hr).max())
        np.testing.assert_allclose(E[j], Er, rtol=1e-10, atol=1e-12 * np.abs(Er).max())
