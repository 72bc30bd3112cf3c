"""`ampc solve`: the JSON contract and the solver options."""

import json

import numpy as np
import pytest

from ampc_jax.cli import main

pytestmark = pytest.mark.timeout(300)


def run_json(capsys, *args):
    code = main(["solve", "cruise_control", "--json", *args])
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


def test_solve_json_contract_and_rho_scale(capsys):
    base = run_json(capsys, "--formulation", "local_explicit")
    for key in (
        "formulation",
        "u0",
        "u",
        "iterations",
        "converged",
        "status",
        "primal_residual",
        "dual_residual",
        "rho",
        "solve_time_s",
    ):
        assert key in base
    assert base["converged"]
    scaled = run_json(capsys, "--rho-scale", "2,0.5", "--relaxation", "1.6")
    names = list(base["rho"])
    assert scaled["rho"][names[0]] == pytest.approx(2 * base["rho"][names[0]], rel=1e-9)
    assert scaled["rho"][names[1]] == pytest.approx(0.5 * base["rho"][names[1]], rel=1e-9)
    # same optimum either way (rho and relaxation only change the path)
    for agent, u0 in base["u0"].items():
        np.testing.assert_allclose(scaled["u0"][agent], u0, atol=5e-2)
    accelerated = run_json(capsys, "--anderson", "3")
    assert accelerated["converged"] and accelerated["iterations"] < base["iterations"]
    for agent, u0 in base["u0"].items():
        np.testing.assert_allclose(accelerated["u0"][agent], u0, atol=5e-2)


def exit_code(args):
    """main's return code, or argparse's exit status for a rejected option."""
    try:
        return main(args)
    except SystemExit as e:
        return e.code


@pytest.mark.parametrize(
    "args, message",
    [
        (["--rho-scale", "1,2,3"], "rho_scale"),
        (["--rho-scale", "-1"], "positive"),
        (["--relaxation", "2.5"], "relaxation"),
        (["--anderson", "4"], "anderson"),
    ],
)
def test_solve_rejects_bad_solver_options(capsys, args, message):
    assert exit_code(["solve", "cruise_control", *args]) == 2
    assert message in capsys.readouterr().err


def test_warm_start_file_round_trip(capsys, tmp_path):
    """--warm-start reads a previous --json output (per-objective U, Z, gamma)."""
    cold = run_json(capsys, "--formulation", "local_explicit", "--tol", "1e-8")
    ws = cold["warm_state"]
    assert len(ws["U"]) == len(ws["gamma"]) == len(cold["rho"])
    path = tmp_path / "first.json"
    path.write_text(json.dumps(cold))
    warm = run_json(
        capsys, "--formulation", "local_explicit", "--tol", "1e-8", "--warm-start", str(path)
    )
    assert warm["converged"]
    for agent, u0 in cold["u0"].items():
        np.testing.assert_allclose(warm["u0"][agent], u0, rtol=1e-3, atol=1e-2)
    bad = dict(cold, warm_state=dict(ws, gamma=ws["gamma"][:1]))
    path.write_text(json.dumps(bad))
    code = exit_code(["solve", "cruise_control", "--warm-start", str(path)])
    err = capsys.readouterr().err
    assert code != 0 and "does not match this problem" in err and "one array per objective" in err
