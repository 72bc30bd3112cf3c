"""`ampc tune --objective warm_start` and a learned start in the tuned-parameters
file, applied by `ampc solve` and `ampc simulate` (in-process main)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.learned_start import StartModel, model_document, n_features
from ampc_jax.cli import main
from ampc_jax.formulations import formulation
from ampc_jax.io import read_params, write_params
from ampc_jax.sweep import family

jax.config.update("jax_enable_x64", True)


def _model(kind, topology, data, *, zero_last=True, seed=0):
    """A small network for ``topology``'s problem; with ``zero_last`` a "loop" network
    is the previous step's iterate and a "step" network the middle of every range."""
    inner = formulation("local_explicit", topology)
    n_point = int(np.size(inner.point(inner.cold_state())))
    n_in = n_features(data) + (n_point if kind == "loop" else 0)
    n_out = n_point if kind == "loop" else topology.horizon * topology.n_u
    rng = np.random.default_rng(seed)
    W2 = np.zeros((6, n_out)) if zero_last else 0.1 * rng.standard_normal((6, n_out))
    return StartModel(
        kind=kind,
        layers=((0.1 * rng.standard_normal((n_in, 6)), np.zeros(6)), (W2, np.zeros(n_out))),
        input_mean=np.zeros(n_in),
        input_scale=np.full(n_in, 100.0),
        out_mean=np.full(n_out, 0.5 if kind == "step" else 0.0),
        out_scale=np.ones(n_out),
        out_mask=np.ones(n_out),
        schedule_rho=np.zeros((0, topology.n_objectives)),
        schedule_relaxation=np.zeros(0),
        n_point=n_point,
        objectives=topology.objective_names,
        horizon=topology.horizon,
    )


def _cruise_step_model(kind):
    cases = family("cruise_step").sample(1, dtype=jnp.float64)
    return _model(kind, cases.topology, jax.tree.map(lambda x: x[0], cases.data))


def _solve(capsys, *args):
    code = main(["solve", "cruise_control", "--json", "--tol", "1e-6", *args])
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


@pytest.mark.timeout(600)
def test_tune_warm_start_writes_the_network(tmp_path, capsys):
    out = tmp_path / "tune"
    code = main(
        ["tune", "--objective", "warm_start", "--family", "cruise_step", "--cases", "16",
         "--pretrain-steps", "20", "--steps", "1", "--iterations", "2", "--hidden", "4",
         "--batch", "8", "--heldout-cases", "0", "--quiet", "--out", str(out)]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 0, text
    tuned = read_params(out / "params.json")
    assert isinstance(tuned.warm_start, StartModel) and tuned.warm_start.kind == "step"
    assert [W.shape[1] for W, _ in tuned.warm_start.layers] == [4, 8]
    # tuned as simulate runs the cruise example: Anderson 3, relaxation 1.5, rho (1, 0.5)
    assert tuned.tuned_for["anderson"] == 3 and tuned.tuned_for["relaxation"] == 1.5
    assert tuned.tuned_for["rho_scale"] == [1.0, 0.5] and tuned.tuned_for["dtype"] == "float64"
    doc = json.loads((out / "tune.json").read_text())
    assert doc["objective"] == "warm_start" and doc["settings"]["pretrain_steps"] == 20
    assert len(text.splitlines()) <= 6  # compact: the full record is in tune.json


@pytest.mark.timeout(300)
def test_solve_applies_the_learned_start(tmp_path, capsys):
    from ampc_jax.cli.solve import _resolve_problem
    from ampc_jax.problem import Problem

    problem = Problem.from_json(_resolve_problem("cruise_control"))
    data = problem.data(jnp.float64)
    path = tmp_path / "params.json"
    write_params(path, warm_start=_model("step", problem.topology, data))
    base = _solve(capsys, "--finish", "none")  # the iteration the start is made for
    learned = _solve(capsys, "--params", str(path), "--finish", "none")
    assert learned["converged"] and base["converged"]
    assert learned["iterations"] != base["iterations"]  # the start moved
    for agent, u0 in base["u0"].items():  # the same solution
        np.testing.assert_allclose(learned["u0"][agent], u0, atol=0.05)
    # a network for another problem (cruise_step's N_p = 2) is refused naming the field
    write_params(path, warm_start=_cruise_step_model("step"))
    code = main(["solve", "cruise_control", "--json", "--params", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and f"ampc: error: --params {path}: warm_start: " in err, err


@pytest.mark.timeout(400)
def test_simulate_with_an_untrained_loop_network_is_todays_warm_start(tmp_path, capsys):
    path = tmp_path / "params.json"
    write_params(path, example="cruise", warm_start=_cruise_step_model("loop"))
    metrics = []
    for params in ((), ("--params", str(path))):
        out = tmp_path / f"run{len(params)}"
        code = main(
            ["simulate", "cruise_lane_change", "--duration", "1", *params, "--out", str(out),
             "--quiet", "--no-timing", "--no-shadow"]
        )  # fmt: skip
        assert code == 0, capsys.readouterr().err
        metrics.append(json.loads((out / "metrics.json").read_text()))
    keys = ("iterations_p50", "iterations_max", "yaw_rms", "speed_rms", "rear_slip_abs_max")
    assert [metrics[1][k] for k in keys] == [metrics[0][k] for k in keys]
    assert metrics[1]["learned_start"].startswith("StartModel(kind='loop'")
    assert metrics[0]["learned_start"] is None


@pytest.mark.timeout(60)
def test_a_bad_warm_start_entry_is_refused_naming_the_field(tmp_path, capsys):
    good = model_document(_cruise_step_model("step"))
    cases = {
        "warm_start.layers[0].W": {**good, "layers": [{"W": [[1.0, "x"]], "b": [0.0]}]},
        "warm_start.kind": {**good, "kind": "psychic"},
        "warm_start.input_scale": {**good, "input_scale": [0.0] * len(good["input_scale"])},
        "warm_start.horizon": {**good, "horizon": -1},
        "warm_start: unknown field": {**good, "colour": 1},
    }
    for field, ws in cases.items():
        path = tmp_path / "params.json"
        path.write_text(json.dumps({"format": "ampc-params/1", "warm_start": ws}))
        with pytest.raises(ValueError, match=field.replace("[", r"\[").replace("]", r"\]")):
            read_params(path)
        code = main(["solve", "cruise_control", "--json", "--params", str(path)])
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err and field in err, err


@pytest.mark.timeout(400)
def test_export_carries_the_network(tmp_path, capsys):
    """The exported step embeds the network's weights (constants of the StableHLO):
    the artefact reproduces its golden pair with nothing but the file, and its
    golden outputs are the learned start's, not the previous-step warm start's."""
    import zipfile

    from ampc_jax.runtime.artefact import read_artefact

    path = tmp_path / "params.json"
    model = _cruise_step_model("step")
    write_params(path, example="cruise", warm_start=model)
    manifests, arts = [], []
    for params in ((), ("--params", str(path))):
        art = tmp_path / f"step{len(params)}.ampc"
        code = main(["export", "--scenario", "cruise_lane_change", *params, "--out", str(art)])
        assert code == 0, capsys.readouterr().err
        with zipfile.ZipFile(art) as z:
            manifests.append(json.loads(z.read("manifest.json")))
        arts.append(art)
    assert manifests[0]["config_hash"] != manifests[1]["config_hash"]
    assert manifests[0]["golden"]["outputs"] != manifests[1]["golden"]["outputs"]
    read_artefact(arts[1]).compiled()  # the golden pair, from the file alone
