"""ampc_jax.problem: the problem description (spec), its topology and data: groups,
derived quantities and every bad input's message."""

import copy
import json
import math

import numpy as np
import pytest

from ampc_jax.problem import Agent, Objective, Problem, ProblemError, ProblemWarning

pytestmark = pytest.mark.timeout(60)


def base() -> dict:
    return {
        "horizon": 5,
        "A": [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.9]],
        "x0": [0.0, 0.0, 0.0],
        "agents": [
            {"name": "a", "B": [[0.0], [1.0], [0.0]], "R": [0.1], "lb": [-1], "ub": [1]},
            {
                "name": "b",
                "B": [[0.0, 0.0], [0.5, 0.0], [0.0, 1.0]],
                "R": [0.1, 0.2],
                "lb": [-1, -1],
                "ub": [1, 1],
            },
            {"name": "c", "B": [[0.0], [0.0], [1.0]], "R": [[0.3]], "lb": [-2], "ub": [2]},
        ],
        "objectives": [
            {"name": "pos", "C": [[1.0, 0.0, 0.0]], "Q": [1.0], "ref": [1.0]},
            {"name": "z", "C": [[0.0, 0.0, 1.0]], "Q": [[2.0]], "ref": [0.5]},
        ],
    }


def test_groups_derived_from_model():
    p = Problem.from_dict(base())
    T = p.topology
    # pos = x1 sees a and b through A[0,1] (k >= 1); z = x3 sees b and c directly.
    assert T.groups == ((0, 1), (1, 2))
    assert T.multiplicity == (1, 2, 1)
    assert T.contributions(1) == (0, 1)
    assert T.n_u == 4 and T.n_c == 8
    # box rows of shared agent b are carried by both objectives (m_(c) = 2)
    mult = T.row_multiplicity
    for c, (k, _) in enumerate(T.box_rows):
        assert mult[c] == (2 if k in (1, 2) else 1)


def test_group_needs_horizon_long_enough():
    d = base()
    d["horizon"] = 1  # A^0 only: pos = x1 is not reached by a or b in one step
    with pytest.raises(ProblemError, match=r"objectives\[0\] \(pos\): no agent influences"):
        Problem.from_dict(d)


def test_explicit_group_and_warning_for_ignored_influence():
    d = base()
    d["objectives"][0]["agents"] = ["a"]
    with pytest.warns(ProblemWarning, match=r"agents \['b'\] influence C_j X"):
        p = Problem.from_dict(d)
    assert p.topology.groups[0] == (0,)


def test_python_and_file_agree(tmp_path):
    d = base()
    f = tmp_path / "p.json"
    f.write_text(json.dumps(d))
    p1 = Problem.from_json(f)
    agents = [Agent(a["name"], a["B"], a["R"], a["lb"], a["ub"]) for a in d["agents"]]
    objs = [Objective(o["name"], o["C"], o["Q"], o["ref"]) for o in d["objectives"]]
    p2 = Problem(horizon=5, A=d["A"], x0=d["x0"], agents=agents, objectives=objs)
    assert p1.topology == p2.topology
    for x, y in zip(p1.data(), p2.data(), strict=True):
        if isinstance(x, tuple):
            for a, b in zip(x, y, strict=True):
                np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_array_equal(x, y)


def test_per_step_reference_and_constraints():
    d = base()
    d["objectives"][0]["ref"] = [[float(k)] for k in range(5)]
    d["constraints"] = [{"A": {"a": [[1.0]], "c": [[1.0]]}, "b": [0.5]}]
    d["objectives"][1]["agents"] = ["a", "b", "c"]
    p = Problem.from_dict(d)
    data = p.data()
    assert data.ref[0].shape == (5, 1)
    np.testing.assert_array_equal(data.ref[0][:, 0], np.arange(5.0))
    assert data.Ain.shape == (9, 4) and data.bin.shape == (5, 9)
    assert p.topology.general_agents == ((0, 2),)
    assert 8 in p.topology.group_rows(1) and 8 not in p.topology.group_rows(0)


def mutate(path, value):
    d = copy.deepcopy(base())
    target = d
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return d


BAD = [
    (("horizon",), 0, r"horizon: expected an integer >= 1"),
    (("horizon",), 2.5, r"horizon: expected an integer >= 1"),
    (("A",), [[1, 0], [0, 1], [0, 0]], r"A: expected a square"),
    (("A",), [[1, 0, 0], [0, math.nan, 0], [0, 0, 1]], r"A: contains NaN"),
    (("x0",), [0, 0], r"x0: expected 3 numbers"),
    (("x0",), [0, math.inf, 0], r"x0: contains inf"),
    (("w",), [[0, 0, 0]] * 4, r"w: expected 3 numbers or a 5 x 3 sequence"),
    (("agents", 0, "B"), [[1.0], [0.0]], r"agents\[0\]\.B \(a\): expected an 3 x n_u matrix"),
    (("agents", 1, "name"), "a", r"agents\[1\]\.name: duplicate agent name 'a'"),
    (
        ("agents", 1, "R"),
        [0.1, -0.2],
        r"agents\[1\]\.R \(b\): must be positive semi-definite, not negative",
    ),
    (("agents", 1, "R"), [[0.1, 0.05], [0.0, 0.2]], r"agents\[1\]\.R \(b\): must be symmetric"),
    (
        ("agents", 1, "R"),
        [0.1, 0.2, 0.3],
        r"agents\[1\]\.R \(b\): expected 2 x 2 or a diagonal of length 2",
    ),
    (("agents", 0, "lb"), [2.0], r"agents\[0\]\.lb \(a\): lb > ub at input 0"),
    (("agents", 0, "ub"), [math.nan], r"agents\[0\]\.ub \(a\): contains NaN"),
    (("agents", 0, "B"), KeyError, r"agents\[0\]\.B: required key is missing"),
    (
        ("objectives", 0, "Q"),
        [-1.0],
        r"objectives\[0\]\.Q \(pos\): must be positive semi-definite, not negative",
    ),
    (("objectives", 0, "Q"), [math.inf], r"objectives\[0\]\.Q \(pos\): contains inf"),
    (("agents", 1, "lb"), [-1], r"agents\[1\]\.lb \(b\): expected 2 numbers, got shape \(1,\)"),
    (
        ("agents", 1, "ub"),
        [1, 1, 1],
        r"agents\[1\]\.ub \(b\): expected 2 numbers, got shape \(3,\)",
    ),
    (("agents", 0, "lb"), [math.inf], r"agents\[0\]\.lb \(a\): contains \+inf, which no input"),
    (("agents", 0, "ub"), [-math.inf], r"agents\[0\]\.ub \(a\): contains -inf, which no input"),
    (("agents", 0, "B"), [[0.0], [math.inf], [0.0]], r"agents\[0\]\.B \(a\): contains inf"),
    (("agents", 1, "R"), [0.1, math.inf], r"agents\[1\]\.R \(b\): contains inf"),
    (("A",), [[1, 0, 0], [0, -math.inf, 0], [0, 0, 1]], r"A: contains inf"),
    (("w",), [0, math.inf, 0], r"w: contains inf"),
    (("objectives", 0, "C"), [[math.inf, 0, 0]], r"objectives\[0\]\.C \(pos\): contains inf"),
    (("objectives", 0, "ref"), [math.inf], r"objectives\[0\]\.ref \(pos\): contains inf"),
    (
        ("objectives", 0, "agents"),
        ["a", "a"],
        r"objectives\[0\]\.agents \(pos\): agent 'a' listed twice",
    ),
    (("objectives", 1, "Q"), [[1.0, 2.0], [2.0, 1.0]], r"objectives\[1\]\.Q \(z\): expected 1 x 1"),
    (
        ("objectives", 0, "C"),
        [[1.0, 0.0]],
        r"objectives\[0\]\.C \(pos\): expected an n_y x 3 matrix",
    ),
    (("objectives", 0, "ref"), [1.0, 2.0], r"objectives\[0\]\.ref \(pos\): expected 1 numbers"),
    (("objectives", 0, "ref"), [math.nan], r"objectives\[0\]\.ref \(pos\): contains NaN"),
    (
        ("objectives", 0, "agents"),
        ["a", "nope"],
        r"objectives\[0\]\.agents \(pos\): unknown agent 'nope'",
    ),
    (("objectives", 1, "name"), "pos", r"objectives\[1\]\.name: duplicate objective name 'pos'"),
    (("agents",), [], r"agents: expected a non-empty list"),
    (("objectives",), [], r"objectives: expected a non-empty list"),
    (("bogus",), 1, r"problem: unknown key\(s\) \['bogus'\]"),
    (("A",), [[1, 0, 0], [0, "0.95", 0], [0, 0, 1]], r"A: expected numbers, got '0\.95'"),
    (("objectives", 0, "Q"), ["10"], r"objectives\[0\]\.Q \(pos\): expected numbers, got '10'"),
    (("agents", 0, "lb"), [True], r"agents\[0\]\.lb \(a\): expected 1 numbers, got True"),
    (("agents", 0, "ub"), ["inf"], r"agents\[0\]\.ub \(a\): expected 1 numbers, got 'inf'"),
    (("x0",), [0.0, None, 0.0], r"x0: expected numbers, got null"),
]


@pytest.mark.parametrize("path,value,message", BAD, ids=[m for _, _, m in BAD])
def test_bad_input_names_the_field(path, value, message):
    with pytest.raises(ProblemError, match=message):
        Problem.from_dict(mutate(path, value))


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        # B of agent b widened to 3 columns: R, lb and ub (2 entries) no longer fit
        (
            ("agents", 1, "B"),
            [[0.0] * 3, [0.5, 0.0, 0.0], [0.0, 1.0, 0.0]],
            r"agents\[1\]\.R \(b\)",
        ),
        (("objectives", 0, "C"), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], r"objectives\[0\]\.Q \(pos\)"),
    ],
)
def test_size_error_says_where_the_size_comes_from(path, value, message):
    """A weight or bound that no longer fits after B or C changed says which
    field set its size (it is the consistent one that is reported wrong)."""
    with pytest.raises(ProblemError, match=message) as info:
        Problem.from_dict(mutate(path, value))
    text = str(info.value)
    if path[0] == "agents":
        assert "(n_u = 3: the columns of agents[1].B)" in text
    else:
        assert "(n_y = 2: the rows of objectives[0].C)" in text


def test_bound_and_reference_size_errors_name_their_source():
    d = mutate(("agents", 1, "lb"), [-1, -1, -1])
    with pytest.raises(ProblemError, match=r"agents\[1\]\.lb \(b\).*n_u = 2: the columns"):
        Problem.from_dict(d)
    d = mutate(("objectives", 1, "ref"), [0.5, 0.5])
    with pytest.raises(ProblemError, match=r"objectives\[1\]\.ref \(z\).*n_y = 1: the rows"):
        Problem.from_dict(d)


def test_agent_in_no_objective():
    d = base()
    d["objectives"][0]["agents"] = ["a", "b"]
    d["objectives"][1]["agents"] = ["b"]
    # c influences objective z, which leaves it out: a warning before the error
    with (
        pytest.warns(UserWarning, match=r"objectives\[1\] \(z\): agents \['c'\] influence"),
        pytest.raises(ProblemError, match=r"agents\[2\] \(c\): the agent belongs to no objective"),
    ):
        Problem.from_dict(d)


def test_unknown_agent_in_constraint():
    d = base()
    d["constraints"] = [{"A": {"zz": [[1.0]]}, "b": [1.0]}]
    with pytest.raises(ProblemError, match=r"constraints\[0\]\.A: unknown agent 'zz'"):
        Problem.from_dict(d)


def test_constraint_shape():
    d = base()
    d["constraints"] = [{"A": {"b": [[1.0]]}, "b": [1.0]}]
    with pytest.raises(
        ProblemError, match=r"constraints\[0\]\.A\.b: expected shape \(1 x 2\)"
    ) as e:
        Problem.from_dict(d)
    assert "(n_u = 2: the columns of agents[1].B)" in str(e.value)


def test_uncovered_input_refused_for_local_explicit():
    d = base()
    d["agents"][2]["lb"] = [-math.inf]
    d["agents"][2]["ub"] = [math.inf]
    p = Problem.from_dict(d)  # fine for the integrated MPC
    with pytest.raises(
        ProblemError,
        match=r"agents\[2\] \(c\): input 0 appears in no constraint row.*paper-notes item 10",
    ) as e:
        p.check_local_explicit()
    # the message suggests the fix
    assert "give the agent finite 'lb' and 'ub'" in str(e.value)


def test_shared_agent_needs_own_rows():
    d = base()
    # b is shared; bound only its first input, cover the second by a row coupling it with c
    d["agents"][1]["lb"] = [-1, -math.inf]
    d["agents"][1]["ub"] = [1, math.inf]
    d["constraints"] = [{"A": {"b": [[0.0, 1.0]], "c": [[1.0]]}, "b": [1.0]}]
    p = Problem.from_dict(d)
    with pytest.raises(ProblemError, match=r"agents\[1\] \(b\): shared by objectives"):
        p.check_local_explicit()


def test_row_across_groups_refused():
    d = base()
    d["constraints"] = [{"A": {"a": [[1.0]], "c": [[1.0]]}, "b": [1.0]}]
    p = Problem.from_dict(d)
    with pytest.raises(ProblemError, match=r"couples agents \['a', 'c'\] that share no objective"):
        p.check_local_explicit()


def test_missing_file_and_bad_json(tmp_path):
    with pytest.raises(ProblemError, match=r"cannot read"):
        Problem.from_json(tmp_path / "nope.json")
    f = tmp_path / "bad.json"
    f.write_text("{not json")
    with pytest.raises(ProblemError, match=r"not valid JSON"):
        Problem.from_json(f)


@pytest.mark.parametrize(
    "Q,message",
    [
        ([[1.0, 0.5], [0.0, 1.0]], r"objectives\[1\]\.Q \(z\): must be symmetric"),
        (
            [[1.0, 2.0], [2.0, 1.0]],
            r"objectives\[1\]\.Q \(z\): must be positive semi-definite, not negative "
            r"\(smallest eigenvalue -1\)",
        ),
    ],
)
def test_bad_matrix_weight_of_two_outputs(Q, message):
    d = base()
    d["objectives"][1]["C"] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
    d["objectives"][1]["ref"] = [0.5, 0.0]
    d["objectives"][1]["Q"] = Q
    with pytest.raises(ProblemError, match=message):
        Problem.from_dict(d)


def test_semidefinite_weight_and_one_sided_bounds_are_accepted():
    d = base()
    d["objectives"][1]["C"] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
    d["objectives"][1]["ref"] = [0.5, 0.0]
    d["objectives"][1]["Q"] = [[1.0, 1.0], [1.0, 1.0]]  # rank 1: weights x3 + x2
    d["agents"][0]["lb"] = [-math.inf]
    d["agents"][2]["ub"] = [math.inf]
    p = Problem.from_dict(d)
    np.testing.assert_allclose(p.data().Q[1], [[1.0, 1.0], [1.0, 1.0]])
    # an infinite side makes no constraint row: 8 box rows less the two free sides
    assert p.topology.n_c == 6


# ----------------------------------------------------- sizes and magnitudes
def _to_file(tmp_path, d, name="p.json"):
    path = tmp_path / name
    path.write_text(json.dumps(d))
    return path


@pytest.mark.timeout(30)
def test_a_horizon_beyond_the_machines_memory_is_refused_naming_it(tmp_path):
    """N_p = 10**6: the condensed forms a solve builds grow as N_p^3 (about 6e19
    bytes); refused at once, naming the field and the estimate, before any
    N_p-sized work (the derived groups alone took minutes)."""
    d = base()
    d["horizon"] = 10**6
    with pytest.raises(ProblemError, match=r"^horizon: N_p = 1000000 .* about [\d.]+ [EPTG]B"):
        Problem.from_json(_to_file(tmp_path, d))
    # the estimate against the memory the machine has: a horizon that fits passes
    from ampc_jax.problem.limits import available_memory, condensed_bytes

    avail = available_memory()
    assert avail is None or avail > condensed_bytes(horizon=5, n_x=3, n_u=4, n_y=(1, 1))
    Problem.from_dict(base())


@pytest.mark.parametrize(
    "where,value,field",
    [
        (("A", 0, 0), 1e308, r"A"),
        (("objectives", 0, "Q"), [1e308], r"objectives\[0\]\.Q \(pos\)"),
        (("agents", 1, "R"), [1e200, 0.2], r"agents\[1\]\.R \(b\)"),
        (("agents", 0, "B", 1, 0), 1e160, r"agents\[0\]\.B \(a\)"),
        (("x0", 2), -1e300, r"x0"),
    ],
)
def test_absurd_magnitudes_are_refused_naming_the_field(where, value, field):
    """1e308 in A or Q gave numpy's "Eigenvalues did not converge"; any entry
    whose square overflows float64 (the residuals of eq.Convergence are
    squared norms) is refused naming its field."""
    d = base()
    node = d
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    with pytest.raises(ProblemError, match=rf"^{field}: .*1e\+?150"):
        Problem.from_dict(d)


def test_a_model_whose_prediction_overflows_is_refused_naming_the_field():
    """Entries each below the limit whose condensed Hessian Y_u' Q Y_u does not
    fit: A = 10 A_0 over N_p = 80 grows as about 10^79, squared in H_j."""
    d = base()
    d["A"] = [[10.0 * x for x in row] for row in d["A"]]
    d["horizon"] = 80
    with pytest.raises(ProblemError, match=r"^A: .*A\^k.*1e\+?150"):
        Problem.from_dict(d)
    d["horizon"] = 5  # 10^4: fine
    Problem.from_dict(d)


@pytest.mark.parametrize("depth", [50, 5000, 200_000])
def test_deeply_nested_json_is_refused(tmp_path, depth):
    """Nesting deeper than a matrix: RecursionError from the JSON reader or
    the number check before; now a ProblemError naming the file or field."""
    path = tmp_path / "deep.json"
    d = base()
    text = json.dumps(d).replace('"x0": [0.0, 0.0, 0.0]', '"x0": ' + "[" * depth + "]" * depth)
    path.write_text(text)
    with pytest.raises(ProblemError, match=r"(x0|deep\.json)"):
        Problem.from_json(path)


def test_integers_beyond_float_are_refused(tmp_path):
    d = base()
    d["x0"] = [10**400, 0, 0]
    with pytest.raises(ProblemError, match=r"^x0: "):
        Problem.from_dict(d)
    path = tmp_path / "big.json"
    path.write_text(json.dumps(base()).replace('"horizon": 5', '"horizon": ' + "9" * 5000))
    with pytest.raises(ProblemError, match=r"big\.json"):
        Problem.from_json(path)
