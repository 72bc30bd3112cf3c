"""`ampc tune` and `--params FILE` of `ampc solve` / `ampc simulate` (in-process main)."""

import json

import pytest

from ampc_jax.cli import main
from ampc_jax.io import read_params, write_params


def _solve(capsys, *args):
    code = main(["solve", "cruise_control", "--json", "--tol", "1e-4", *args])
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


@pytest.mark.timeout(60)
def test_tune_writes_params_figure_and_table(tmp_path, capsys):
    out = tmp_path / "tune"
    code = main(
        ["tune", "--family", "cruise_step", "--cases", "2", "--steps", "3", "--iterations",
         "4", "--heldout-cases", "2", "--quiet", "--out", str(out)]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 0
    tuned = read_params(out / "params.json")
    assert tuned.example == "cruise" and len(tuned.rho_scale) == 2
    assert 0 < tuned.relaxation < 2 and tuned.provenance["objective"] == "solver"
    doc = json.loads((out / "tune.json").read_text())
    assert len(doc["history"]) == 4 and doc["evaluation"]
    assert (out / "loss.png").stat().st_size > 0
    assert "eq.opt_ro" in text and "grid best" in text and "tuned" in text
    # the summary compares with what simulate and solve run without this file
    assert "example defaults" in text and "than the example defaults (median " in text


@pytest.mark.timeout(30)
def test_tune_rejects_a_loop_family_for_the_solver(tmp_path, capsys):
    code = main(["tune", "--family", "cruise_lane_change", "--out", str(tmp_path), "--quiet"])
    assert code == 2
    assert "ampc: error: --family: " in capsys.readouterr().err


@pytest.mark.timeout(60)
def test_solve_uses_the_params_file(tmp_path, capsys):
    base = _solve(capsys)
    path = tmp_path / "params.json"
    write_params(path, rho_scale=[2.0, 0.5], relaxation=1.5)
    tuned = _solve(capsys, "--params", str(path))
    for name, r in base["rho"].items():
        factor = {0: 2.0, 1: 0.5}[list(base["rho"]).index(name)]
        assert tuned["rho"][name] == pytest.approx(factor * r, rel=1e-9)
    assert tuned["iterations"] != base["iterations"]
    # an explicit flag wins over the file
    flag = _solve(capsys, "--params", str(path), "--rho-scale", "1")
    assert flag["rho"] == pytest.approx(base["rho"], rel=1e-9)


@pytest.mark.timeout(30)
def test_solve_rejects_a_bad_params_file(tmp_path, capsys):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"format": "ampc-params/1", "solver": {"relaxation": 3}}))
    code = main(["solve", "cruise_control", "--params", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and f"ampc: error: --params {path}: solver.relaxation: " in err


@pytest.mark.timeout(120)
def test_simulate_uses_the_params_file(tmp_path, capsys):
    path = tmp_path / "params.json"
    write_params(
        path, example="cruise", rho_scale=[2.0, 0.25], relaxation=1.7, settings={"horizon": 3}
    )
    out = tmp_path / "run"
    code = main(
        ["simulate", "cruise_lane_change", "--duration", "1", "--params", str(path), "--out",
         str(out), "--quiet", "--no-timing", "--no-shadow", "--relaxation", "1.2"]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    m = json.loads((out / "metrics.json").read_text())
    assert m["rho_scale"] == [2.0, 0.25] and m["horizon"] == 3
    assert m["relaxation"] == 1.2  # the explicit flag wins over the file
    code = main(
        ["simulate", "stability_dlc", "--duration", "1", "--params", str(path), "--out",
         str(out), "--quiet"]
    )  # fmt: skip
    assert code == 2
    assert f"--params {path}: example: " in capsys.readouterr().err


# ------------------------------------------------------- bounds that say why
def _doc(**fields):
    return {"format": "ampc-params/1", **fields}


@pytest.mark.timeout(60)
def test_params_file_bounds_say_why(tmp_path, capsys):
    """rho_scale 1e308 and q_yrt 1e308 were accepted (simulate stopped after one
    iteration 144 Nm off), 10**400 raised OverflowError and nesting
    RecursionError: each is refused naming the field, with the bound's reason."""
    from ampc_jax.closed_loop import config_for
    from ampc_jax.io.params_file import apply_params

    cfg = config_for("cruise_lane_change")
    path = tmp_path / "params.json"
    path.write_text(json.dumps(_doc(solver={"rho_scale": [1.0, 1e308]})))
    with pytest.raises(ValueError, match=r"^solver\.rho_scale\[1\]: .*\[1e-06, 1e\+06\].*float32"):
        read_params(path)
    path.write_text(json.dumps(_doc(solver={"rho_scale": 1e-9})))
    with pytest.raises(ValueError, match=r"^solver\.rho_scale: .*never converges"):
        read_params(path)
    path.write_text(json.dumps(_doc(example="cruise", settings={"q_yrt": 1e308})))
    with pytest.raises(ValueError, match=r"^settings\.q_yrt: .*factor 1e\+06 of the cruise"):
        apply_params(cfg, read_params(path))
    path.write_text(json.dumps(_doc(settings={"r_dtr": 1e-30})))
    with pytest.raises(ValueError, match=r"^settings\.r_dtr: "):
        apply_params(cfg, read_params(path))
    path.write_text(json.dumps(_doc(settings={"horizon": 10**6})))
    with pytest.raises(ValueError, match=r"^settings\.horizon: .*10 s"):
        apply_params(cfg, read_params(path))
    # a tuned value well inside the bounds still applies
    path.write_text(json.dumps(_doc(solver={"rho_scale": 1e5}, settings={"q_yrt": 1e9})))
    assert apply_params(cfg, read_params(path)).settings.q_yrt == 1e9
    texts = {
        "huge.json": '{"format": "ampc-params/1", "solver": {"rho_scale": 1' + "0" * 400 + "}}",
        "digits.json": '{"format": "ampc-params/1", "solver": {"relaxation": 1' + "0" * 5000 + "}}",
        "deep.json": '{"format": "ampc-params/1", "settings": {"q_yrt": '
        + "[" * 100_000
        + "]" * 100_000
        + "}}",
        "shallow.json": '{"format": "ampc-params/1", "settings": {"q_yrt": '
        + "[" * 500
        + "]" * 500
        + "}}",
    }
    for name, text in texts.items():
        bad = tmp_path / name
        bad.write_text(text)
        with pytest.raises(ValueError, match=r"^(params|solver|settings)"):
            apply_params(cfg, read_params(bad))
    # through the command line: one line, exit 2, the file and the field named
    cases = [("huge.json", "solver.rho_scale"), ("deep.json", "params"), ("params.json", "")]
    path.write_text(json.dumps(_doc(example="cruise", settings={"q_yrt": 1e308})))
    cases[-1] = ("params.json", "settings.q_yrt")
    for name, field in cases:
        argv = ["simulate", "cruise_lane_change", "--params", str(tmp_path / name)]
        code = main([*argv, "--quiet", "--out", str(tmp_path / "out")])
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err, err
        assert err.startswith(f"ampc: error: --params {tmp_path / name}: {field}"), err
        assert len(err.strip().splitlines()) == 1, err
