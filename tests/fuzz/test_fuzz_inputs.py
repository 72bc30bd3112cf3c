"""Hostile input to the input readers: the tuned-parameters file (``--params``),
the problem file (``ampc solve FILE``) and a sweep's output directory and grid
(``ampc sweep``: ``sweep.json``, the chunks, ``--rho``).

Seeded random mutations (the same inputs every run): JSON values replaced by
hostile ones (1e308, 10**400, a 5,000-digit integer, NaN, nesting 100,000
deep, strings, nulls, empty containers), keys removed or added, text cut,
bytes flipped, invalid UTF-8. Whatever the input, the reader returns or
raises ValueError naming a field on one line; a refused input, given to the
command line in-process, prints one ``ampc: error: ...`` line with exit 2,
before any JAX compilation (an accepted one is not run: it would solve).
"""

from __future__ import annotations

import copy
import json
import random
import re
import warnings
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from jax import monitoring

from ampc_jax.cli import main
from ampc_jax.problem import Problem, ProblemError
from ampc_jax.sweep import rho_grid
from ampc_jax.sweep.run import SweepSpec, check_out

pytestmark = pytest.mark.timeout(120)

CASES = 120  # mutations per reader
CLI_CASES = 25  # of the refused ones, how many go through the command line too
DEEP = "<<DEEP>>"  # placeholders for what json.dumps cannot write
DIGITS = "<<DIGITS>>"
HOSTILE: list[Any] = [
    None,
    True,
    "",
    "x" * 2000,
    0,
    -1,
    1.5,
    1e308,
    -1e308,
    1e-320,
    10**400,
    float("nan"),
    float("inf"),
    -float("inf"),
    [],
    {},
    [[[1.0]]],
    [1.0] * 1000,
    {"a": {"b": [1, "c"]}},
    DEEP,
    DIGITS,
    10**6,
]


def _json_text(doc: Any) -> str:
    text = json.dumps(doc)
    text = text.replace(json.dumps(DEEP), "[" * 100_000 + "]" * 100_000)
    return text.replace(json.dumps(DIGITS), "7" * 5000)


def _paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path to a value inside a JSON tree (dict keys and list indices)."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(node, list) and len(node) <= 50:
        for i, v in enumerate(node):
            out += _paths(v, (*prefix, i))
    return out


def _mutate_tree(doc: Any, rng: random.Random) -> Any:
    doc = copy.deepcopy(doc)
    for _ in range(rng.choice((1, 1, 2, 3))):
        paths = _paths(doc)
        if not paths:
            return rng.choice(HOSTILE)
        path = rng.choice(paths)
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        key = path[-1]
        op = rng.random()
        if op < 0.6:
            parent[key] = rng.choice(HOSTILE)
        elif op < 0.75 and isinstance(parent, dict):
            del parent[key]
        elif op < 0.85 and isinstance(parent, dict):
            parent[rng.choice(("unknown", "x", "", "horizon"))] = rng.choice(HOSTILE)
        else:
            parent[key] = [parent[key]]  # one level deeper
    return doc


def _mutate_bytes(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    op = rng.random()
    if op < 0.25:
        return bytes(b[: rng.randrange(len(b) + 1)])  # cut
    if op < 0.5:
        for _ in range(rng.randint(1, 8)):  # flipped bytes
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if op < 0.75:
        i = rng.randrange(len(b) + 1)  # inserted: invalid UTF-8, digits, brackets
        return (
            bytes(b[:i])
            + rng.choice((b"\xff\xfe", b"9" * 400, b"[[[[", b"}", b"\x00"))
            + bytes(b[i:])
        )
    i, j = sorted(rng.randrange(len(b) + 1) for _ in range(2))
    return bytes(b[:i] + b[j:])  # a span removed


def _inputs(doc: Any, seed: int) -> list[bytes]:
    """CASES hostile variants of ``doc``: tree mutations, then bytes of some."""
    rng = random.Random(seed)
    out = []
    for k in range(CASES):
        text = _json_text(_mutate_tree(doc, rng)).encode()
        out.append(_mutate_bytes(text, rng) if k % 3 == 2 else text)
    return out


def _one_line(msg: str) -> None:
    assert msg and "\n" not in msg.strip() and "Traceback" not in msg, msg[:500]


_COMPILES: list[str] = []


def _count_compiles(name: str, secs: float, **kwargs: Any) -> None:
    if name.endswith("backend_compile_duration"):
        _COMPILES.append(name)


@pytest.fixture(autouse=True)
def _compile_events():
    """XLA compilations are counted while a test runs (JAX's monitoring events)."""
    monitoring.register_event_duration_secs_listener(_count_compiles)
    yield
    monitoring.unregister_event_duration_listener(_count_compiles)


def _cli(capsys, argv: list[str], prefix: str) -> None:
    _COMPILES.clear()
    code = main(argv)
    assert not _COMPILES, f"a refused input reached {len(_COMPILES)} XLA compilation(s): {argv}"
    err = capsys.readouterr().err
    assert code == 2, err[-2000:]
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ampc: error: {prefix}"), err[-2000:]
    assert "Traceback" not in err


# --------------------------------------------------------------------- params
PARAMS = {
    "format": "ampc-params/1",
    "example": "cruise",
    "formulation": "local_explicit",
    "solver": {"rho_scale": [0.8, 1.2], "relaxation": 1.5},
    "settings": {"q_yrt": 2e4, "horizon": 3, "r_dtr": 3e-7},
    "provenance": {"objective": "solver", "cases": 2},
}
PARAMS_FIELD = re.compile(
    r"^(params|format|example|formulation|provenance|solver(\.\w+)?(\[\d+\])?|"
    r"settings(\.\w+)?(\[\d+\])?|[A-Za-z_]\w*(?=: unknown field)): "
)


def test_params_reader_refuses_hostile_files_naming_the_field(tmp_path, capsys):
    from ampc_jax.closed_loop import config_for
    from ampc_jax.io.params_file import apply_params, read_params

    cfg = config_for("cruise_lane_change")
    path = tmp_path / "params.json"
    path.write_text(json.dumps(PARAMS))
    apply_params(cfg, read_params(path))  # the unmutated file is valid
    refused: list[tuple[Path, bool]] = []
    for k, data in enumerate(_inputs(PARAMS, seed=29)):
        f = tmp_path / f"p{k}.json"
        f.write_bytes(data)
        try:
            tuned = read_params(f)
        except ValueError as exc:
            assert PARAMS_FIELD.match(str(exc)), str(exc)[:300]
            _one_line(str(exc))
            refused.append((f, True))
            continue
        try:
            apply_params(cfg, tuned)
        except ValueError as exc:
            assert PARAMS_FIELD.match(str(exc)), str(exc)[:300]
            _one_line(str(exc))
            refused.append((f, False))
    assert len(refused) > CASES // 2
    for f, by_reader in refused[:CLI_CASES]:
        out = ["--quiet", "--out", str(tmp_path / "out")]
        _cli(
            capsys, ["simulate", "cruise_lane_change", "--params", str(f), *out], f"--params {f}: "
        )
        if by_reader:  # solve reads the solver numbers only
            _cli(capsys, ["solve", "cruise_control", "--params", str(f)], f"--params {f}: ")
    assert not (tmp_path / "out").exists()


# -------------------------------------------------------------------- problems
PROBLEM = {
    "horizon": 4,
    "A": [[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.9]],
    "x0": [0.0, 0.0, 0.0],
    "w": [0.0, 0.01, 0.0],
    "agents": [
        {"name": "a", "B": [[0.0], [1.0], [0.0]], "R": [0.1], "lb": [-1], "ub": [1]},
        {"name": "b", "B": [[0.0], [0.5], [1.0]], "R": [[0.2]], "lb": [-1], "ub": [1]},
    ],
    "objectives": [
        {"name": "pos", "C": [[1.0, 0.0, 0.0]], "Q": [1.0], "ref": [1.0]},
        {"name": "z", "C": [[0.0, 0.0, 1.0]], "Q": [[2.0]], "ref": [0.5], "agents": ["b"]},
    ],
    "constraints": [{"A": {"a": [[1.0]], "b": [[1.0]]}, "b": [1.5]}],
}
PROBLEM_FIELD = re.compile(r"^(problem|horizon|A|x0|w|agents|objectives|constraints)\b")


def test_problem_reader_refuses_hostile_files_naming_the_field(tmp_path, capsys):
    path = tmp_path / "problem.json"
    path.write_text(json.dumps(PROBLEM))
    Problem.from_json(path)  # the unmutated file is valid
    refused = []
    for k, data in enumerate(_inputs(PROBLEM, seed=11)):
        f = tmp_path / f"q{k}.json"
        f.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                Problem.from_json(f)
            except ProblemError as exc:
                assert PROBLEM_FIELD.match(str(exc)), str(exc)[:300]
                _one_line(str(exc))
                refused.append(f)
    assert len(refused) > CASES // 2
    for f in refused[:CLI_CASES]:
        _cli(capsys, ["solve", str(f), "--json"], f"{f}: ")


# ---------------------------------------------------------------------- sweeps
SPEC = SweepSpec(family="cruise_step", cases=6, rho=(0.5, 2.0), chunk=3)
SWEEP_ARGS = ["--family", "cruise_step", "--cases", "6", "--rho", "0.5,2", "--chunk", "3"]


def _sweep_dir(out: Path) -> None:
    """A finished sweep's directory as ``run_sweep`` leaves it (no solve needed:
    the readers look at the manifest and the chunks' footers)."""
    from ampc_jax.sweep import store
    from ampc_jax.sweep.run import _spec_dict

    spec = _spec_dict(SPEC)
    (out / "chunks").mkdir(parents=True)
    (out / "sweep.json").write_text(json.dumps({"format": "ampc-sweep/1", "spec": spec}))
    for k in range(2):
        cases = list(range(3 * k, 3 * k + 3))
        cols = {
            "case": [c for c in cases for _ in range(2)],
            "point": [0, 1] * 3,
            "rho_scale": [0.5, 2.0] * 3,
            "family": [SPEC.family] * 6,
            "formulation": [SPEC.formulation] * 6,
            "seed": [SPEC.seed] * 6,
        }
        record = {"spec_hash": store.spec_hash(spec), "chunk": k, "cases": [3 * k, 3 * k + 3]}
        table = pa.table(cols).replace_schema_metadata({store.META_KEY: json.dumps(record)})
        pq.write_table(table, out / "chunks" / store.chunk_name(k))


def _mutate_sweep(out: Path, rng: random.Random) -> None:
    from ampc_jax.sweep import store

    target = rng.choice(("manifest", "chunk", "record", "stray"))
    if target == "manifest":
        m = out / "sweep.json"
        doc = json.loads(m.read_text())
        data = _json_text(_mutate_tree(doc, rng)).encode()
        m.write_bytes(_mutate_bytes(data, rng) if rng.random() < 0.4 else data)
    elif target == "chunk":
        c = out / "chunks" / store.chunk_name(rng.randrange(2))
        c.write_bytes(_mutate_bytes(c.read_bytes(), rng))
    elif target == "record":
        c = out / "chunks" / store.chunk_name(rng.randrange(2))
        table = pq.read_table(c)
        record = json.loads(table.schema.metadata[store.META_KEY])
        raw = _json_text(_mutate_tree(record, rng)).encode()
        if rng.random() < 0.3:
            table = table.slice(0, rng.randrange(table.num_rows))
        meta = {} if rng.random() < 0.1 else {store.META_KEY: raw}
        pq.write_table(table.replace_schema_metadata(meta), c)
    else:
        name = rng.choice(("chunk_00002.parquet", "chunk_00000.p0of2.parquet", "chunk_x.parquet"))
        src = out / "chunks" / store.chunk_name(0)
        (out / "chunks" / name).write_bytes(src.read_bytes())


def test_sweep_reader_refuses_hostile_directories_naming_them(tmp_path, capsys):
    pristine = tmp_path / "pristine"
    _sweep_dir(pristine)
    check_out(pristine, SPEC, 1)  # the unmutated directory resumes
    rng = random.Random(8)
    refused = []
    for k in range(CASES):
        out = tmp_path / f"s{k}"
        _sweep_dir(out)
        _mutate_sweep(out, rng)
        try:
            check_out(out, SPEC, 1)
        except ValueError as exc:
            assert str(exc).startswith(f"out: {out}"), str(exc)[:300]
            _one_line(str(exc))
            refused.append(out)
    assert len(refused) > CASES // 2
    for out in refused[:CLI_CASES]:
        argv = ["sweep", *SWEEP_ARGS, "--quiet", "--no-figures", "--out", str(out)]
        _cli(capsys, argv, "--out: ")


RHO_TEXTS = ["", ":", "1:2", "1:2:3:4", "0:1:3", "-1:2:3", "1:2:0", "1:2:-5", "nan:1:3"]
RHO_TEXTS += ["1:inf:3", "1:2:1e3", "1,,", "1,x", "1,-2", "1,inf", "1e999", "1:2:" + "9" * 30]
RHO_TEXTS += ["\x00", "1:2:10000000", "0.1:10:" + str(10**12), ",".join(["1"] * 3) + ",0"]


def test_rho_grid_refuses_hostile_text_naming_the_flag(tmp_path, capsys):
    rng = random.Random(5)
    texts = list(RHO_TEXTS)
    for _ in range(CASES):
        base = rng.choice(("0.1:10:13", "0.3,1,3"))
        texts.append(_mutate_bytes(base.encode(), rng).decode("utf-8", "replace"))
    refused = []
    for text in texts:
        try:
            grid = rho_grid(text)
        except ValueError as exc:
            _one_line(str(exc))
            refused.append(text)
            continue
        assert grid and all(0 < r < float("inf") for r in grid)
    assert len(refused) >= len(RHO_TEXTS)
    for text in refused[:CLI_CASES]:
        argv = ["sweep", "--family", "cruise_step", f"--rho={text}", "--out", str(tmp_path / "o")]
        _cli(capsys, argv, "--rho: ")
