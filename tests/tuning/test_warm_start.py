"""Training a learned start (ampc_jax.tuning.warm_start): a tiny network trained on a
few cruise cases starts held-out cases closer to their fixed point than the cold
start does; refused settings name the field."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.learned_start import LearnedStart
from ampc_jax.formulations import PAPER_ITERATION, formulation
from ampc_jax.sweep import family
from ampc_jax.tuning.warm_start import start_table, tune_warm_start

jax.config.update("jax_enable_x64", True)

PLAIN = {"rho_scale": 1.0, "relaxation": 1.0, "anderson": 0}
"""eq.opt_ro's plain iteration: the cold start takes ~35 iterations on cruise_step."""


@pytest.fixture(scope="module")
def trained():
    return tune_warm_start(
        "cruise_step",
        cases=96,
        pretrain_steps=400,
        steps=3,
        iterations=4,
        hidden=(16,),
        batch=32,
        lr=1e-2,
        evaluate=False,
        progress=False,
        **PLAIN,
    )


@pytest.mark.timeout(400)
def test_a_trained_tiny_network_saves_iterations_on_held_out_cases(trained):
    model = trained.model
    assert model.kind == "step" and model.n_parameters == 122 * 16 + 16 + 16 * 8 + 8
    st = trained.settings
    assert st["tuned_for"]["anderson"] == 0 and st["tuned_for"]["relaxation"] == 1.0
    phases = [h["phase"] for h in trained.history]
    assert phases.count("pretrain") == 400 and phases.count("unrolled") == 3
    pre = [h["loss"] for h in trained.history if h["phase"] == "pretrain"]
    assert np.mean(pre[-20:]) < 0.2 * np.mean(pre[:20])
    held = family("cruise_step").sample(48, seed=7, dtype=jnp.float64)  # another seed
    inner = formulation("local_explicit", held.topology, max_iter=500, **PAPER_ITERATION)
    p = inner.params(tol_primal=1.0, tol_dual=1.0)
    solve = lambda s: jax.jit(jax.vmap(s.solve, in_axes=(0, None)))(held.data, p)  # noqa: E731
    cold, learned = solve(inner), solve(LearnedStart(inner, model))
    assert np.all(np.asarray(cold.converged)) and np.all(np.asarray(learned.converged))
    it_cold, it_learned = np.asarray(cold.iterations), np.asarray(learned.iterations)
    # a small, robust margin: the median and the mean at least 10 % fewer (measured:
    # median 28 against 34.5 iterations)
    assert np.median(it_learned) <= 0.9 * np.median(it_cold), (it_cold, it_learned)
    assert np.mean(it_learned) <= 0.9 * np.mean(it_cold), (it_cold, it_learned)
    # same fixed point: the first inputs agree to the tolerance's scale
    du0 = np.abs(np.asarray(learned.u0) - np.asarray(cold.u0))
    assert np.max(du0) < 20.0  # Nm, residuals of 1 Nm^2 at ~2000 Nm ranges


@pytest.mark.timeout(60)
def test_start_table_is_compact():
    ev = {
        "seed 1": {
            "cases": 10,
            "tol": 1.0,
            "rows": [
                {
                    "name": n,
                    "median": m,
                    "p95": q,
                    "max": 40,
                    "converged": 1.0,
                    "u0_error": 1.0,
                    "u0_rel_error": 0.01,
                }
                for n, m, q in (("eq.opt_ro, cold", 30.0, 50.0), ("learned start", 10.0, 20.0))
            ],
        }
    }
    text = start_table(ev)
    assert len(text.splitlines()) == 5
    assert "median 3.00x fewer, p95 2.50x fewer" in text


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "field, change",
    [
        ("cases", {"cases": 0}),
        ("steps", {"steps": -1}),
        ("iterations", {"iterations": 0}),
        ("schedule", {"schedule": 99}),
        ("loss", {"loss": "huber"}),
        ("lr", {"lr": float("nan")}),
        ("hidden", {"hidden": (0,)}),
        ("family", {"family_name": "nonsense"}),
    ],
)
def test_bad_settings_name_the_field(field, change):
    kw = {"cases": 4, "evaluate": False, "progress": False, **change}
    with pytest.raises(ValueError, match=field):
        tune_warm_start(**kw)
