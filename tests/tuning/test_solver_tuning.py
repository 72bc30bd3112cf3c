"""Gradient tuning of the solver (ampc_jax.tuning.solver) and the tuned-parameters file."""

import json

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.formulations import formulation
from ampc_jax.sweep import family
from ampc_jax.tuning import TunedParams, read_params, write_params
from ampc_jax.tuning.solver import (
    Theta,
    reference_inputs,
    theta_of,
    tune_solver,
    unpack,
    unrolled_loss,
)

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def batch():
    cases = family("cruise_step").sample(2, seed=0, dtype=jnp.float64)
    solver = formulation("local_explicit", cases.topology)
    u_star = jnp.asarray(reference_inputs(cases.topology, cases.data))
    return solver, cases, u_star


@pytest.mark.timeout(60)
def test_parametrisation_round_trips():
    th = theta_of((0.5, 2.0), 1.6, 2, jnp.float64)
    rho, alpha = unpack(th)
    np.testing.assert_allclose(np.asarray(rho), [0.5, 2.0], rtol=1e-12)
    assert abs(float(alpha) - 1.6) < 1e-12
    rho, alpha = unpack(Theta(jnp.zeros(2), jnp.asarray(50.0)))
    assert float(alpha) <= 2.0 and np.all(np.asarray(rho) == 1.0)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("loss", ["error", "residual"])
def test_unrolled_gradient_matches_central_differences(batch, loss):
    solver, cases, u_star = batch
    K, s = 6, float(cases.topology.horizon * cases.topology.n_u)
    th0 = theta_of((0.7, 1.3), 1.2, 2, jnp.float64)

    def f(th):
        return unrolled_loss(solver, th, cases.data, u_star, K, s, loss)

    fj = jax.jit(f)
    g = jax.jit(jax.grad(f))(th0)
    flat0, unravel = jax.flatten_util.ravel_pytree(th0)
    gflat = np.asarray(jax.flatten_util.ravel_pytree(g)[0])
    assert gflat.shape == (3,)  # log rho of each objective, the relaxation logit
    h = 1e-5  # central differences: truncation ~h^2, round-off ~1e-16 / h
    for k in range(3):
        e = jnp.zeros_like(flat0).at[k].set(h)
        fd = (float(fj(unravel(flat0 + e))) - float(fj(unravel(flat0 - e)))) / (2 * h)
        assert abs(gflat[k] - fd) <= 1e-4 * max(abs(fd), 1e-8), (k, gflat[k], fd)
        assert abs(fd) > 0  # each parameter moves the loss


@pytest.mark.timeout(60)
def test_short_tuning_lowers_the_loss():
    res = tune_solver(
        "cruise_step", cases=4, steps=12, iterations=6, lr=0.1, evaluate=False, progress=False
    )
    losses = [h["loss"] for h in res.history]
    assert len(losses) == 13 and min(losses[1:]) < losses[0]
    assert len(res.rho_scale) == 2 and 0 < res.relaxation < 2
    assert res.settings["example"] == "cruise" and res.evaluation == {}


@pytest.mark.timeout(60)
def test_evaluation_table_rows():
    from ampc_jax.tuning.solver import evaluation_table

    res = tune_solver(
        "cruise_step", cases=2, steps=2, iterations=4, heldout_cases=4, progress=False
    )
    (ev,) = res.evaluation.values()
    names = [r["name"] for r in ev["rows"]]
    assert names == ["eq.opt_ro", "grid best", "tuned"] and len(ev["grid"]) == 13
    for r in ev["rows"]:
        assert r["converged"] == 1.0 and r["median"] > 0 and r["u0_rel_error"] < 0.05
    assert "grid best" in evaluation_table(res.evaluation)


@pytest.mark.timeout(30)
def test_params_file_round_trips(tmp_path):
    path = tmp_path / "params.json"
    written = write_params(
        path,
        example="cruise",
        rho_scale=np.array([0.5, 2.0]),
        relaxation=1.6,
        settings={"q_yrt": 2e4, "horizon": 3},
        provenance={"steps": 10},
    )
    back = read_params(path)
    assert back == written
    assert back == TunedParams(
        "cruise", "local_explicit", (0.5, 2.0), 1.6, {"q_yrt": 2e4, "horizon": 3.0}, {"steps": 10}
    )
    doc = json.loads(path.read_text())
    assert doc["format"] == "ampc-params/1" and doc["solver"]["rho_scale"] == [0.5, 2.0]
    write_params(path)  # everything optional
    assert read_params(path) == TunedParams()


def _doc(**changes):
    doc = {
        "format": "ampc-params/1",
        "example": None,
        "formulation": "local_explicit",
        "solver": {"rho_scale": [1.0, 0.5], "relaxation": 1.5},
    }
    doc.update(changes)
    return doc


@pytest.mark.timeout(30)
@pytest.mark.parametrize(
    ("doc", "field"),
    [
        (_doc(format="ampc-params/9"), "format"),
        (_doc(example=3), "example"),
        (_doc(formulation="newton"), "formulation"),
        (_doc(solver=[1]), "solver"),
        (_doc(solver={"rho_scale": [1.0, -2.0]}), "solver.rho_scale[1]"),
        (_doc(solver={"rho_scale": "big"}), "solver.rho_scale"),
        (_doc(solver={"relaxation": 2.5}), "solver.relaxation"),
        (_doc(solver={"rho": 1.0}), "solver.rho"),
        (_doc(settings={"q_yrt": "x"}), "settings.q_yrt"),
        (_doc(settings=[1]), "settings"),
        (_doc(provenance=5), "provenance"),
        (_doc(extra=1), "extra"),
    ],
)
def test_bad_params_files_name_the_field(tmp_path, doc, field):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=rf"^{__import__('re').escape(field)}: "):
        read_params(path)


@pytest.mark.timeout(30)
def test_unreadable_params_file(tmp_path):
    with pytest.raises(ValueError, match="^params: cannot read"):
        read_params(tmp_path / "missing.json")
    (tmp_path / "x.json").write_text("{")
    with pytest.raises(ValueError, match="^params: .* is not JSON"):
        read_params(tmp_path / "x.json")
    with pytest.raises(ValueError, match="^solver.relaxation: "):
        write_params(tmp_path / "y.json", relaxation=0.0)
    assert not (tmp_path / "y.json").exists()


@pytest.mark.timeout(30)
def test_apply_params_to_a_config():
    from ampc_jax.closed_loop import SimConfig
    from ampc_jax.tuning import apply_params

    cfg = SimConfig(example="cruise")
    tuned = TunedParams("cruise", rho_scale=(2.0, 0.25), relaxation=1.7, settings={"horizon": 3.0})
    out = apply_params(cfg, tuned)
    assert out.rho_scale == (2.0, 0.25) and out.relaxation == 1.7 and out.horizon == 3
    kept = apply_params(cfg, tuned, keep=("relaxation",))
    assert kept.relaxation == cfg.relaxation and kept.rho_scale == (2.0, 0.25)
    with pytest.raises(ValueError, match="^example: "):
        apply_params(SimConfig(example="stability"), tuned)
    with pytest.raises(ValueError, match="^settings.q_nope: "):
        apply_params(cfg, TunedParams(settings={"q_nope": 1.0}))
    with pytest.raises(ValueError, match="^solver.rho_scale: "):
        apply_params(cfg, TunedParams(rho_scale=(1.0, 2.0, 3.0)))
