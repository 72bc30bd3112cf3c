"""The tuned-parameters file (ampc_jax.io.params_file): written, read back, refused
naming the field, applied to a closed-loop configuration."""

import json

import numpy as np
import pytest

from ampc_jax.io import TunedParams, read_params, write_params


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
    from ampc_jax.io import apply_params

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
