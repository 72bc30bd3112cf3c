"""One source of solver defaults per example: `ampc sweep` runs the example's
relaxation and Anderson memory, as `simulate` and `tune --objective warm_start`
do, and says so in its header line."""

import json

import pytest

from ampc_jax.cli import main
from ampc_jax.vehicle import StabilitySettings
from ampc_jax.vehicle.examples import example

BASE = ["sweep", "--cases", "2", "--rho", "1", "--quiet", "--no-figures"]


def _spec(out):
    doc = json.loads((out / "sweep.json").read_text())
    return doc.get("spec", doc)


@pytest.mark.timeout(300)
def test_sweep_runs_the_examples_solver_defaults(tmp_path, capsys):
    d = example("cruise").solver_defaults
    out = tmp_path / "a"
    assert main([*BASE, "--family", "cruise_step", "--out", str(out)]) == 0
    head = capsys.readouterr().out.splitlines()[0]
    assert head == (
        f"ampc sweep: cruise_step, relaxation {d['relaxation']:g}, Anderson {d['anderson']} "
        f"(the cruise example's defaults where not given)"
    )
    spec = _spec(out)
    assert spec["relaxation"] == d["relaxation"] == 1.5 and spec["anderson"] == d["anderson"] == 3
    # explicit flags win
    out = tmp_path / "b"
    argv = [*BASE, "--family", "cruise_step", "--relaxation", "1", "--anderson", "0"]
    assert main([*argv, "--out", str(out)]) == 0
    assert "relaxation 1, Anderson 0 (as given)" in capsys.readouterr().out
    assert _spec(out)["relaxation"] == 1.0 and _spec(out)["anderson"] == 0


@pytest.mark.timeout(300)
def test_sweep_of_generated_problems_runs_the_plain_iteration(tmp_path, capsys):
    out = tmp_path / "g"
    assert main([*BASE, "--family", "generated", "--out", str(out)]) == 0
    head = capsys.readouterr().out.splitlines()[0]
    assert head.startswith("ampc sweep: generated, relaxation 1, Anderson 0 (the paper's"), head
    assert _spec(out)["relaxation"] == 1.0 and _spec(out)["anderson"] == 0


@pytest.mark.timeout(300)
def test_tune_runs_the_examples_anderson_and_records_it(tmp_path, capsys):
    from ampc_jax.io import read_params

    out = tmp_path / "t"
    code = main(
        ["tune", "--family", "cruise_step", "--cases", "2", "--steps", "2", "--iterations", "3",
         "--heldout-cases", "2", "--quiet", "--out", str(out)]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 0, text
    assert text.splitlines()[0].startswith(
        "ampc tune: solver on cruise_step, Anderson 3 (the cruise example's defaults"
    )
    tuned = read_params(out / "params.json")
    assert tuned.tuned_for["anderson"] == 3 and tuned.provenance["anderson"] == 3
    # the residual loss unrolls plain ADMM: Anderson 0 unless given
    code = main(
        ["tune", "--family", "cruise_step", "--cases", "2", "--steps", "1", "--iterations", "3",
         "--heldout-cases", "2", "--loss", "residual", "--quiet", "--out", str(tmp_path / "r")]
    )  # fmt: skip
    assert code == 0
    assert "Anderson 0" in capsys.readouterr().out.splitlines()[0]


@pytest.mark.timeout(300)
def test_simulate_names_the_examples_defaults_in_its_header(tmp_path, capsys):
    """The header names the example's solver defaults, the precision and the
    settings changed; a disabled objective's rho scale is not in it; metrics.json
    records the precision and the change beside its default."""
    code = main(
        ["simulate", "stability_dlc", "--duration", "0.2", "--out", str(tmp_path / "s"),
         "--quiet", "--no-timing", "--no-shadow", "--float32", "--set", "q_vsc=8",
         "--disable", "WSC"]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0, out
    d = example("stability").solver_defaults
    q_default = StabilitySettings().q_vsc
    assert out.splitlines()[0] == (
        f"ampc simulate: stability_dlc, local_explicit, VSC (WSC disabled), rho scale "
        f"{d['rho_scale'][0]:g}, relaxation {d['relaxation']:g}, Anderson {d['anderson']}, "
        f"finish {d['finish']}, "
        f"float32; settings q_vsc=8 (default {q_default:g}) (the stability example's solver "
        f"defaults where no flag or --params gave one)"
    )
    assert "; float32]" in out and f"q_vsc 8 (default {q_default:g})" in out  # the summary
    m = json.loads((tmp_path / "s" / "metrics.json").read_text())
    assert m["relaxation"] == d["relaxation"] and m["anderson"] == d["anderson"]
    assert m["dtype"] == "float32" and m["objectives"] == ["VSC"]
    assert m["settings_changed"] == {"q_vsc": {"value": 8.0, "default": q_default}}
