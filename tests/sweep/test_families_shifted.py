"""The step families' other friction and speed range (``ranges``) and the
stability example's loop family."""

import numpy as np
import pytest

from ampc_jax.sweep import family
from ampc_jax.sweep.families import ENVELOPES, SHIFTED_RANGES


@pytest.mark.timeout(120)
@pytest.mark.parametrize("name", ["cruise", "stability"])
def test_shifted_ranges_draw_inside_them(name):
    cases = family(f"{name}_step").sample(16, seed=2, ranges="shifted")
    for key, (lo, hi) in SHIFTED_RANGES[name].items():
        col = np.asarray(cases.columns[key])
        assert np.all((col >= lo) & (col <= hi)), key
        assert (lo, hi) != ENVELOPES[name][key]  # another range than the default's
    plain = family(f"{name}_step").sample(16, seed=2)
    assert not np.allclose(plain.columns["mu"], cases.columns["mu"])


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "ranges, field",
    [
        ("sideways", "ranges"),
        ({"colour": (0, 1)}, "ranges"),
        ({"mu": (0.5, 0.2)}, r"ranges\.mu"),
        ({"v_x": (-3.0, 5.0)}, r"ranges\.v_x"),
        ({"mu": "low"}, r"ranges\.mu"),
    ],
)
def test_bad_ranges_name_the_field(ranges, field):
    with pytest.raises(ValueError, match=field):
        family("cruise_step").sample(2, ranges=ranges)


@pytest.mark.timeout(60)
def test_stability_manoeuvres_draws_both_manoeuvres():
    cases = family("stability_manoeuvres").sample(12, seed=0)
    assert cases.config.example == "stability"
    dlc = np.asarray(cases.columns["dlc"])
    assert dlc.any() and not dlc.all()
    mu = np.asarray(cases.columns["mu"])
    assert np.all(mu[dlc] >= 0.6) and np.all(mu[~dlc] <= 0.5)
    assert np.shape(cases.scenarios.mu)[0] == 12 and cases.n_steps > 0
