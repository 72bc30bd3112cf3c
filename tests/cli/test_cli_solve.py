"""`ampc solve` (ampc_jax.cli.solve): the JSON contract, the solver options, problem files."""

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


def run_json_file(capsys, path, *args):
    code = main(["solve", str(path), "--json", *args])
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


def exit_code(args):
    """main's return code, or argparse's exit status for a rejected option."""
    try:
        return main(args)
    except SystemExit as e:
        return e.code


@pytest.fixture(scope="module")
def base():
    """The shipped example by Local Explicit at --tol 1e-8 (within 1e-4 Nm of
    Clarabel): one run (one compilation) for the tests that compare against it."""
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main(["solve", "cruise_control", "--json", "--tol", "1e-8"]) == 0
    return json.loads(out.getvalue())


@pytest.fixture(scope="module")
def plain():
    """The same by the paper's iteration alone (--finish none)."""
    import contextlib
    import io

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main(["solve", "cruise_control", "--json", "--tol", "1e-8", "--finish", "none"]) == 0
    return json.loads(out.getvalue())


def test_solve_json_contract_and_rho_scale(capsys, base, plain):
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
        "compile_time_s",
        "warm_state",
        "constraint_violation",
    ):
        assert key in base
    assert base["formulation"] == "local_explicit" and base["converged"]
    scaled = run_json(capsys, "--tol", "1e-8", "--rho-scale", "2,0.5", "--relaxation", "1.6")
    names = list(base["rho"])
    assert scaled["rho"][names[0]] == pytest.approx(2 * base["rho"][names[0]], rel=1e-9)
    assert scaled["rho"][names[1]] == pytest.approx(0.5 * base["rho"][names[1]], rel=1e-9)
    # same optimum either way (rho and relaxation only change the path)
    for agent, u0 in base["u0"].items():
        np.testing.assert_allclose(scaled["u0"][agent], u0, atol=5e-2)
    # Anderson shortens the iteration itself (the finish would end both early)
    accelerated = run_json(capsys, "--tol", "1e-8", "--anderson", "3", "--finish", "none")
    assert accelerated["converged"] and accelerated["iterations"] < plain["iterations"]
    for agent, u0 in base["u0"].items():
        np.testing.assert_allclose(accelerated["u0"][agent], u0, atol=5e-2)


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["--rho-scale", "1,2,3"],
            "ampc: error: --rho-scale: expected a float or 2 values (one per objective)",
        ),
        (["--rho-scale", "-1"], "ampc: error: --rho-scale: expected positive finite numbers"),
        (["--rho-scale", "1,x"], "ampc: error: --rho-scale: expected comma-separated positive"),
        (["--relaxation", "2.5"], "ampc: error: --relaxation: expected a value in (0, 2), got 2.5"),
        (["--relaxation", "abc"], "ampc: error: --relaxation: expected a number, got 'abc'"),
        (["--relaxation", "0"], "ampc: error: --relaxation: "),
        (["--anderson", "4"], "ampc: error: --anderson: invalid choice: 4"),
        (["--rho", "-2"], "ampc: error: --rho: expected a positive finite number, got '-2'"),
        (["--rho", "nan"], "ampc: error: --rho: expected a positive finite number"),
        (["--tol", "0"], "ampc: error: --tol: expected a positive finite number"),
        (["--max-iter", "2.5"], "ampc: error: --max-iter: expected an integer, got '2.5'"),
    ],
)
def test_solve_rejects_bad_solver_options(capsys, args, message):
    assert exit_code(["solve", "cruise_control", *args]) == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith(message), err
    assert "argument " not in err  # argparse's "argument --x: --x: ..." is rewritten


def test_warm_start_file_round_trip(capsys, tmp_path, base):
    """--warm-start reads a previous --json output (per-objective U, Z, gamma)."""
    cold = base  # --tol 1e-8
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
    # the iterate is used, not only read and checked: one iteration from it lands
    # far nearer the optimum than one from the cold start (a warm state dropped
    # after parsing gives the cold iterate exactly; measured 48 against 587 Nm)
    agents = list(cold["u0"])
    opt = np.concatenate([cold["u0"][a] for a in agents])

    def one_iteration(*extra):
        r = run_json(capsys, "--tol", "1e-8", "--max-iter", "1", "--finish", "none", *extra)
        assert r["iterations"] == 1
        return np.max(np.abs(np.concatenate([r["u0"][a] for a in agents]) - opt))

    far, near = one_iteration(), one_iteration("--warm-start", str(path))
    assert near < 0.25 * far, (near, far)
    bad = dict(cold, warm_state=dict(ws, gamma=ws["gamma"][:1]))
    path.write_text(json.dumps(bad))
    code = exit_code(["solve", "cruise_control", "--warm-start", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"ampc: error: --warm-start {path}: "), err
    assert "does not match this problem" in err and "one array per objective" in err
    # a file that is no --json result
    path.write_text(json.dumps({"u0": {}}))
    assert main(["solve", "cruise_control", "--warm-start", str(path)]) == 2
    assert "no 'warm_state' object" in capsys.readouterr().err
    # a warm start applies to Local Explicit only
    assert (
        main(["solve", "cruise_control", "--formulation", "integrated", "--warm-start", str(path)])
        == 2
    )
    assert "ampc: error: --warm-start: applies to --formulation local_explicit only" in (
        capsys.readouterr().err
    )


def _problem_file(tmp_path, name="problem.json", **changes):
    """A small problem (two objectives sharing agent b) written to a file."""
    d = {
        "horizon": 4,
        "A": [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.9]],
        "x0": [0.0, 0.0, 0.0],
        "agents": [
            {"name": "a", "B": [[0.0], [1.0], [0.0]], "R": [0.1], "lb": [-1], "ub": [1]},
            {"name": "b", "B": [[0.0], [0.5], [1.0]], "R": [0.2], "lb": [-1], "ub": [1]},
            {"name": "c", "B": [[0.0], [0.0], [1.0]], "R": [0.3], "lb": [-2], "ub": [2]},
        ],
        "objectives": [
            {"name": "pos", "C": [[1.0, 0.0, 0.0]], "Q": [1.0], "ref": [1.0]},
            {"name": "z", "C": [[0.0, 0.0, 1.0]], "Q": [2.0], "ref": [0.5]},
        ],
    }
    d.update(changes)
    path = tmp_path / name
    path.write_text(json.dumps(d))
    return str(path)


def test_integrated_solvers_agree_with_local_explicit(capsys, base):
    le = base  # --tol 1e-8: within 1e-4 Nm of the optimum
    for solver in ("clarabel", "osqp", "jax"):
        ref = run_json(
            capsys,
            "--formulation",
            "integrated",
            "--solver",
            solver,
            "--tol",
            "1e-10",
            *(["--max-iter", "20000"] if solver == "jax" else []),
        )
        assert ref["status"] == "solved", solver
        assert ref["formulation"] == "integrated" and "warm_state" not in ref
        for agent, u0 in le["u0"].items():
            np.testing.assert_allclose(ref["u0"][agent], u0, rtol=1e-3, atol=1e-4, err_msg=solver)
        if solver == "jax":
            assert list(ref["rho"]) == ["integrated"]
        else:
            assert ref["rho"] == {}


def test_solver_defaults_to_clarabel_for_integrated(capsys):
    """--solver's default is None: Clarabel for the integrated formulation, no note."""
    out = run_json(capsys, "--formulation", "integrated")
    assert out["status"] == "solved" and out["rho"] == {}
    assert main(["solve", "cruise_control", "--formulation", "integrated"]) == 0
    captured = capsys.readouterr()
    assert "ignored" not in captured.err
    assert captured.out.startswith("formulation  integrated")


def test_given_rho_and_iteration_cap(capsys):
    # the iteration alone: the cap is the iteration's (a finish may end it sooner)
    args = ["--rho", "3.5", "--max-iter", "3", "--finish", "none"]
    code = main(["solve", "cruise_control", "--json", *args])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    out = json.loads(captured.out)
    assert set(out["rho"].values()) == {3.5}
    assert out["iterations"] == 3 and out["status"] == "max_iter_reached"
    assert not out["converged"]
    # the iteration cap is reported on stderr (u is still the projected last iterate)
    assert "ampc: not converged: stopped at --max-iter 3" in captured.err
    assert "ignored" not in captured.err


def test_table_output(capsys):
    assert main(["solve", "cruise_control"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("formulation  local_explicit")
    assert "status       solved after" in text and "first-step inputs U^(0)" in text
    assert "\nrho          LST=" in text and "solve time " in text
    for agent in ("DTR", "RTV", "FDB"):
        assert f"\n{agent} " in text


@pytest.mark.parametrize("solver", ["clarabel", "osqp"])
def test_infeasible_problem_prints_no_inputs(capsys, tmp_path, solver):
    # -u_a <= -5 with u_a <= 1: no input satisfies both
    path = _problem_file(tmp_path, constraints=[{"A": {"a": [[-1.0]]}, "b": [-5.0]}])
    code = main(["solve", path, "--formulation", "integrated", "--solver", solver, "--json"])
    out = capsys.readouterr()
    assert code == 1
    result = json.loads(out.out, parse_constant=pytest.fail)  # strict JSON: no NaN/Infinity
    assert result["status"] == "infeasible"
    assert set(result["u0"].values()) == {None} and set(result["u"].values()) == {None}
    assert "no solution (infeasible)" in out.err
    # the table says so instead of printing numbers
    assert main(["solve", path, "--formulation", "integrated", "--solver", solver]) == 1
    assert "no solution" in capsys.readouterr().out


@pytest.mark.parametrize(
    "formulation", ["local_explicit", "fully_distributed", "virtual_center", "integrated"]
)
def test_every_admm_formulation_certifies_an_infeasible_problem(capsys, tmp_path, formulation):
    """-a <= -5 with a in its bounds: every ADMM formulation stops with status
    infeasible and a Farkas certificate (y >= 0, A_in' y = 0, b' y < 0), prints
    no inputs and exits 1."""
    path = _problem_file(tmp_path, constraints=[{"A": {"a": [[-1.0]]}, "b": [-5.0]}])
    args = ["solve", path, "--formulation", formulation, "--max-iter", "300", "--json"]
    code = main(args + (["--solver", "jax"] if formulation == "integrated" else []))
    out = capsys.readouterr()
    assert code == 1
    result = json.loads(out.out, parse_constant=pytest.fail)
    assert result["status"] == "infeasible"
    assert set(result["u0"].values()) == {None}
    cert = result["certificate"]
    y = np.asarray(cert["y"])
    assert np.all(y >= 0) and y.max() == pytest.approx(1.0)
    assert cert["Ain_t_y_inf_norm"] < 1e-6 and cert["b_t_y"] < 0
    assert "the constraint set is empty at prediction step" in out.err
    assert "no solution (infeasible)" in out.err


def test_an_early_stop_on_a_feasible_problem_prints_its_inputs(capsys, tmp_path):
    # a feasible problem with an active general row, stopped a little early: its
    # violation is of the order a converged result may have (sqrt(tol)), so the
    # inputs are printed
    row = _problem_file(
        tmp_path, "row.json", constraints=[{"A": {"a": [[1.0]], "b": [[1.0]]}, "b": [0.3]}]
    )
    plain = ("--tol", "1e-3", "--finish", "none")  # the iteration's own stop
    done = run_json_file(capsys, row, *plain)
    assert done["status"] == "solved"
    early = main(["solve", row, *plain, "--max-iter", str(done["iterations"] - 1)])
    out = capsys.readouterr()
    assert early == 0 and "may be infeasible" not in out.err


def test_cli_input_mistakes_are_named(capsys, tmp_path, base):
    # a mistyped example name lists the shipped ones
    assert main(["solve", "cruise_contro"]) == 2
    assert "nor a shipped example (cruise_control" in capsys.readouterr().err
    # a non-finite tolerance
    assert exit_code(["solve", "cruise_control", "--tol", "inf"]) == 2
    assert "ampc: error: --tol: expected a positive finite number" in capsys.readouterr().err
    # a warm start whose iterate is not finite (a result without a usable iterate)
    first = json.loads(json.dumps(base))
    first["warm_state"]["Z"][0][0] = None
    bad = tmp_path / "warm.json"
    bad.write_text(json.dumps(first))
    assert main(["solve", "cruise_control", "--warm-start", str(bad)]) == 2
    assert "warm_state.Z contains a null" in capsys.readouterr().err
    # options the reference solvers do not take are reported, not silently dropped
    assert main(["solve", "cruise_control", "--formulation", "integrated", "--rho", "2"]) == 0
    assert "ampc: --rho ignored by --solver clarabel" in capsys.readouterr().err
    code = main(
        ["solve", "cruise_control", "--formulation", "integrated", "--solver", "osqp",
         "--relaxation", "1.5", "--anderson", "2", "--max-iter", "50"]
    )  # fmt: skip
    assert code == 0
    assert (
        "ampc: --relaxation, --anderson, --max-iter ignored by --solver osqp"
        in capsys.readouterr().err
    )


def test_rho_scale_next_to_a_given_rho_is_reported_once_with_its_cause(capsys, tmp_path):
    small = _problem_file(tmp_path)
    assert main(["solve", small, "--rho", "2", "--rho-scale", "2", "--json"]) == 0
    err = capsys.readouterr().err
    assert "--rho-scale ignored by --rho" in err and "--solver" not in err, err
    code = main(
        ["solve", small, "--formulation", "integrated", "--rho", "2", "--rho-scale", "2",
         "--json"]
    )  # fmt: skip
    assert code == 0
    err = capsys.readouterr().err
    assert err.count("--rho-scale") == 1, err


def test_bad_problem_files_go_to_stderr(capsys, tmp_path):
    assert main(["solve", str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: ") and "missing.json" in err
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    assert main(["solve", str(broken)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ampc: error: ") and "broken.json" in err
    # agent c without bounds is on no constraint row (paper-notes item 10)
    free = _problem_file(tmp_path)
    d = json.loads(open(free).read())
    d["agents"][2].update(lb=[float("-inf")], ub=[float("inf")])
    with open(free, "w") as f:
        f.write(json.dumps(d).replace("Infinity", "1e999"))
    code = main(["solve", free, "--formulation", "local_explicit", "--json"])
    out = capsys.readouterr()
    assert code == 2 and out.out == ""
    assert out.err.startswith(
        f"ampc: error: {free}: agents[2] (c): input 0 appears in no constraint row"
    )
    # the integrated formulation takes it (Clarabel needs no bounds)
    ok = run_json_file(capsys, free, "--formulation", "integrated")
    assert ok["status"] == "solved"


def test_overflowing_problem_gives_strict_json(capsys, tmp_path):
    """x0 near float32's limit: no solution, and the output (warm state
    included) is still strict JSON, every non-finite number null."""
    from ampc_jax.cli.solve import _finite_or_none

    assert _finite_or_none({"a": [1.0, float("nan")], "b": float("inf"), "c": 2}) == {
        "a": [1.0, None],
        "b": None,
        "c": 2,
    }
    path = _problem_file(tmp_path, x0=[3e38, 3e38, 3e38])
    code = main(["solve", path, "--float32", "--json"])
    out = capsys.readouterr()
    assert code == 1 and "no solution" in out.err
    result = json.loads(out.out, parse_constant=pytest.fail)
    assert set(result["u0"].values()) == {None} and result["status"] == "numerical_error"


def _hessian_problem(tmp_path, r_a, name):
    """Agent a with weight r_a, observed only through its integral: Q is blind to
    a's last step, so r_a alone makes H_j definite (r_a = 0: singular)."""
    bounds = {"lb": [-1], "ub": [1]} if r_a > 0 else {}
    path = tmp_path / name
    path.write_text(
        json.dumps(
            {
                "horizon": 3,
                "A": [[1.0, 0.1], [0.0, 1.0]],
                "x0": [0.0, 0.0],
                "agents": [
                    {"name": "a", "B": [[0.0], [1.0]], "R": [r_a], **bounds},
                    {"name": "b", "B": [[0.0], [0.5]], "R": [0.1], "lb": [-1], "ub": [1]},
                ],
                "objectives": [
                    {"name": "o", "C": [[1.0, 0.0], [0.0, 1.0]], "Q": [1.0, 0.0], "ref": [1.0, 0.0]}
                ],
                **(
                    {}
                    if r_a > 0
                    else {"constraints": [{"A": {"a": [[1.0]], "b": [[1.0]]}, "b": [0.5]}]}
                ),
            }
        )
    )
    return path


def test_singular_hessian_needs_a_given_rho(capsys, tmp_path):
    """R_a = 0 and Q blind to a's last step: H_j is singular, eq.opt_ro's rho*
    (which needs H_j^-1) is undefined: refused naming the objective; with
    --rho the solve matches Clarabel's first step."""
    from ampc_jax.admm.costs import singular_hessians
    from ampc_jax.problem import Problem

    path = _hessian_problem(tmp_path, 0.0, "singular.json")
    p = Problem.from_json(path)
    ((j, low, high),) = singular_hessians(p.topology, p.data())
    assert j == 0 and abs(low) <= 1e-12 * high
    for extra in ([], ["--formulation", "integrated", "--solver", "jax"]):
        assert main(["solve", str(path), "--json", *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("ampc: error: objectives[0] ("), err
        assert "its Hessian H_j is singular" in err
        assert "give --rho VALUE" in err
    given = run_json_file(capsys, path, "--rho", "0.5", "--max-iter", "5000", "--tol", "1e-10")
    ref = run_json_file(capsys, path, "--formulation", "integrated", "--solver", "clarabel")
    assert given["converged"]
    for agent, u0 in ref["u0"].items():
        np.testing.assert_allclose(given["u0"][agent], u0, rtol=1e-3, atol=1e-4)


def test_ill_conditioned_hessian_is_not_called_singular(capsys, tmp_path):
    """R_a = 1e-13 (positive) and Q blind to a's last step: H_j is positive
    definite with a condition number above 1e12; the refusal says so instead
    of blaming R = 0."""
    path = _hessian_problem(tmp_path, 1e-13, "illcond.json")
    assert main(["solve", str(path), "--json"]) == 2
    err = capsys.readouterr().err
    assert "numerically singular (condition number" in err and "R_(i) singular" not in err


@pytest.fixture(scope="module")
def slow_problem(tmp_path_factory):
    """A generated box-only problem that needs thousands of iterations (seed 26,
    three objectives), as a problem file, and Clarabel's optimum U*."""
    from ampc_jax.generate import problem_dict, random_problem
    from ampc_jax.reference import solve_reference

    p = random_problem(26, 3)
    path = tmp_path_factory.mktemp("slow") / "slow.json"
    path.write_text(json.dumps(problem_dict(p)))
    return path, solve_reference(p.topology, p.data(), eps=1e-12)


@pytest.mark.parametrize("formulation", ["local_explicit", "fully_distributed", "virtual_center"])
def test_tol_rel_stops_within_the_stated_error_bound(capsys, slow_problem, formulation):
    """--tol with --tol-rel on a problem that needs thousands of iterations: the
    first-step inputs are within the printed error_bound of Clarabel's optimum
    (the bound sqrt(2 gap / lambda_min(H)) from the result's duality gap)."""
    path, ref = slow_problem
    out = run_json_file(
        capsys,
        path,
        "--formulation",
        formulation,
        "--tol",
        "1e-9",
        "--tol-rel",
        "1e-6",
        "--max-iter",
        "30000",
        *(["--finish", "none"] if formulation == "local_explicit" else []),  # the iteration's
    )
    assert out["status"] == "solved" and out["iterations"] > 1000, out["iterations"]
    assert out["gap"] > 0 and out["error_bound"] is not None
    u0 = np.concatenate([np.asarray(v, float) for v in out["u0"].values()])  # agent order
    err = float(np.linalg.norm(u0 - ref.u[0]))
    assert err <= out["error_bound"], (err, out["error_bound"], out["gap"])


def test_tol_rel_is_checked_and_the_gap_is_printed(capsys, base):
    assert base["gap"] >= 0 and base["error_bound"] is not None
    assert exit_code(["solve", "cruise_control", "--tol-rel", "-1"]) == 2
    assert "ampc: error: --tol-rel: expected a finite number >= 0" in capsys.readouterr().err
    assert main(["solve", "cruise_control", "--tol", "1e-8"]) == 0
    text = capsys.readouterr().out
    assert "gap          " in text
    assert "of the optimum: the 2-norm over every agent's inputs and every step of the " in text
    assert "horizon, in the inputs' own units)" in text


def test_finish_flag(capsys, base, plain):
    """--finish: its choices are the library's finishes; the default (active_set) and
    none reach the same optimum, the finish in no more iterations; a formulation
    without an exact finish refuses it by name."""
    from ampc_jax.admm.finish import FINISHES
    from ampc_jax.cli.args import FINISH_CHOICES

    assert set(FINISH_CHOICES) == set(FINISHES)
    assert plain["status"] == base["status"] == "solved"
    assert base["iterations"] <= plain["iterations"]
    for agent, u0 in base["u0"].items():
        np.testing.assert_allclose(plain["u0"][agent], u0, atol=1e-3)
    args = ["solve", "cruise_control", "--formulation", "fully_distributed", "--finish", "none"]
    assert exit_code(args) == 2
    assert (
        "--finish: --formulation fully_distributed has no exact finish" in capsys.readouterr().err
    )
    assert exit_code(["solve", "cruise_control", "--finish", "exact"]) == 2
