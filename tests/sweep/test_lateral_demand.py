"""The cruise lane-change family asks no more lateral acceleration of the road
than it can give (ampc_jax.sweep.families.lateral_demand, LATERAL_DEMAND_MAX)."""

import jax
import numpy as np
import pytest

from ampc_jax.sweep.families import LATERAL_DEMAND_MAX, family, lateral_demand
from ampc_jax.vehicle.manoeuvres import path_y, scenario
from ampc_jax.vehicle.params import VehicleParams

pytestmark = pytest.mark.timeout(60)


def _demand_by_differences(sc, dt=0.01):
    """max |d^2 y / dt^2| along the path at the reference speed, y(X(t)) from the
    path's own function and the second difference in time (no formula for y'')."""
    st, sv = np.asarray(sc.speed_t, float), np.asarray(sc.speed_v, float)
    t = np.arange(0.0, float(st.max()) + 60.0, dt)
    v = np.interp(t, st, sv)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    y = np.asarray(path_y(sc.path, x), float)
    ypp_t = np.gradient(np.gradient(y, t), t)  # y'(X) v^2 + y'(X) v', v' ~ 0 in the turns
    return float(np.max(np.abs(ypp_t)))


def test_lateral_demand_matches_second_differences_of_the_path():
    sc = scenario("cruise_lane_change").scenario
    a = lateral_demand(sc)
    assert a == pytest.approx(_demand_by_differences(sc), rel=0.03)
    # the paper's manoeuvre on mu = 1 asks what the cap allows a drawn case
    assert a / VehicleParams().g == pytest.approx(LATERAL_DEMAND_MAX, abs=0.01)


def test_drawn_lane_changes_stay_within_the_road_friction():
    """Seed 0 draws cases asking up to 1.56 mu g; they are scaled down to 0.95 mu g
    (the cases that spun the car and made the rear slip reach hundreds), the
    others keep their drawn offset."""
    cases = family("cruise_lane_change").sample(32, seed=0)
    c = cases.columns
    g = VehicleParams().g
    scaled = c["offset"] < c["offset_drawn"]
    assert scaled.any() and not scaled.all()
    assert np.all(c["lateral_demand_mu_g"] <= LATERAL_DEMAND_MAX + 1e-12)
    np.testing.assert_array_equal(c["offset"][~scaled], c["offset_drawn"][~scaled])
    for i in np.flatnonzero(scaled)[:4]:
        one = jax.tree.map(lambda x, i=i: np.asarray(x)[i], cases.scenarios)
        asked = lateral_demand(one) / (c["mu"][i] * g)
        assert asked == pytest.approx(LATERAL_DEMAND_MAX, rel=1e-6)
