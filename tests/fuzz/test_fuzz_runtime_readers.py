"""Hostile input to the runtime's readers: `ampc replay`'s (run.json, ticks.parquet,
the tick journal, the bridge's candump log) and `ampc run --artefact`'s (the
artefact zip and its manifest). Seeded random mutations (bytes flipped, cut,
inserted; JSON values replaced, removed, nested; rows, cells and lines
changed), each tried naively and as a forger who reseals the digests. Whatever
the input: the reader refuses with its own error (RunLogError, ArtefactError)
or accepts what it can vouch for, and the command line says one
``ampc: error: ...`` line with exit 2; never another exception.

The run logs are made here, by the runtime's own writer (TickJournal), with
torque frames encoded by the bridge's codec: a small, valid run to start each
mutation from, without a bus."""

from __future__ import annotations

import json
import random
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import can_bridge
from ampc_jax.cli import main
from ampc_jax.results import Status
from ampc_jax.runtime.artefact import ArtefactError, read_artefact, seal_manifest
from ampc_jax.runtime.runcheck import check_run
from ampc_jax.runtime.signals import BUS_FIELDS
from ampc_jax.runtime.ticklog import (
    COLUMNS,
    RunLogError,
    TickJournal,
    file_sha256,
    new_row,
    write_run_json,
)

pytestmark = pytest.mark.timeout(300)

SCENARIO = "cruise_lane_change"
WHEELS = ("FL", "FR", "RL", "RR")
CASES = 60  # mutations per family (seeded: the same inputs every run)
HOSTILE = [
    None,
    -1,
    0,
    1.5,
    float("nan"),
    float("inf"),
    10**400,
    1e308,
    "",
    "x" * 1000,
    [],
    {},
    True,
    [[[[[]]]]],
    {"a": {"b": {}}},
]


# -- a small valid run, written by the runtime's own writer ------------------------


def _step_hash() -> str:
    from ampc_jax.closed_loop import config_for
    from ampc_jax.runtime.step import RuntimeStep

    return RuntimeStep(config_for(SCENARIO, shadow=False)).config_hash()


def _frame_line(t: float, mode: str, torques: list[float], counter: int) -> str:
    values = {"Mode": mode, **{f"Torque{w}": x for w, x in zip(WHEELS, torques, strict=True)}}
    data = can_bridge.encode_message("WheelTorqueCmd", values, counter)
    return f"({t:.6f}) can0 101#{data.hex().upper()} T\n"


def _state_line(t: float, counter: int) -> str:
    data = can_bridge.encode_message(
        "SteeringState", {"SteeringAngle": 0.01 * counter}, counter % 15
    )
    return f"({t:.6f}) can0 203#{data.hex().upper()} R\n"


def _write_run(d: Path, *, finish: bool) -> None:
    """12 ticks: no state, 8 sent, a refused step, one late, the last two framed
    or not; the bridge's log with the frames the rows name, state frames between."""
    d.mkdir(parents=True)
    meta = {
        "scenario": SCENARIO,
        "formulation": "local_explicit",
        "dtype": "float64",
        "config_hash": _step_hash(),
    }
    journal = TickJournal(d, meta)
    rows, log, frame, seq = [], [], 0, 0
    for i in range(12):
        t = 1000.0 + 0.05 * i
        # the bridge frames once per tick: its log's torque frames and their count
        frame += 1
        torques = [-2.0 * i, -4.0 * i, 10.0 * i, 8.0 * i]
        mode = "active" if i else "safe"
        log.append(_frame_line(t, mode, torques, frame % 15))
        log.append(_state_line(t + 0.01, i))
        if rows and rows[-1]["skip"] != "late" and i != 11:
            rows[-1].update(bridge_mode=mode, bridge_tx_frames=frame)
            rows[-1].update({f"framed_{w}": x for w, x in zip(WHEELS, torques, strict=True)})
            journal.framed(rows[-1])
        if i == 0:
            row = new_row(i, 10**9, "state invalid (WheelSpeeds: timeout)", "state")
        elif i == 10:
            row = new_row(i, 10**9 + i, "late", "late")
        else:
            ok = i != 9
            row = new_row(
                i, 10**9 + i, "" if ok else "solve failed (status 4)", "" if ok else "step"
            )
            seq += ok
            row.update(
                stepped=True,
                sent=ok,
                seq=seq if ok else -1,
                iterations=7,
                status=int(Status.SOLVED),
            )
            row.update(compute_ms=1.0, margin_ms=20.0 if ok else float("nan"))
            row.update({f"bus_{n}": 0.1 * (j + i) for j, n in enumerate(BUS_FIELDS)})
            row.update({f"cmd_{w}": 5.0 * i for w in WHEELS})
        rows.append(row)
        journal.append(row)
    (d / "bridge.log").write_text("".join(log))
    sent = sum(r["sent"] for r in rows)
    summary = {
        "ticks": 12,
        "sent": sent,
        "misses": 1,
        "skipped": {"state": 1, "step": 1, "late": 1},
        "bridge": {"log_dropped": 0, "log_errors": 0},
    }
    if finish:
        journal.finish(rows, {**summary, "state": "finished"})
    else:
        journal.status(summary)
        journal.close()


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("runs")
    out = {"finished": base / "finished", "killed": base / "killed"}
    _write_run(out["finished"], finish=True)
    _write_run(out["killed"], finish=False)
    out["journal"] = base / "journal"
    shutil.copytree(out["killed"], out["journal"])
    (out["journal"] / "run.json").unlink()
    for d in out.values():
        check_run(d)  # the starting points are valid
    assert check_run(out["finished"]).frames_checked == 10
    return out


# -- mutations ---------------------------------------------------------------------


def _mutate_bytes(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    kind = rng.choice(["flip", "flip", "cut", "insert", "zero", "repeat"])
    pos = rng.randrange(max(len(b), 1))
    if kind == "flip":
        for _ in range(rng.randint(1, 3)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    elif kind == "cut":
        del b[pos:]
    elif kind == "insert":
        b[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    elif kind == "zero":
        b[pos : pos + rng.randint(1, 64)] = bytes(min(64, len(b) - pos))
    else:
        b[pos:pos] = b[pos : pos + rng.randint(1, 200)]
    return bytes(b)


NEST = "__nested__"


def _text(obj: Any, depth: int = 0) -> str:
    """``obj`` as JSON, the value NEST written as a list nested ``depth`` deep (which
    the json module itself cannot write beyond its recursion limit)."""
    return json.dumps(obj).replace(json.dumps(NEST), "[" * depth + "1" + "]" * depth)


def _mutate_json(obj: Any, rng: random.Random) -> tuple[Any, int]:
    """A copy of ``obj`` with one value replaced, removed, or nested deeply (the
    value NEST, and the depth for :func:`_text`)."""
    obj = json.loads(json.dumps(obj))
    paths: list[tuple[Any, Any]] = []

    def walk(x: Any) -> None:
        items = x.items() if isinstance(x, dict) else enumerate(x) if isinstance(x, list) else ()
        for k, v in items:
            paths.append((x, k))
            walk(v)

    walk(obj)
    if not paths:
        return rng.choice(HOSTILE), 0
    parent, key = rng.choice(paths)
    kind = rng.choice(["replace", "replace", "remove", "nest"])
    depth = 0
    if kind == "remove":
        del parent[key]
    elif kind == "nest":
        parent[key], depth = NEST, rng.choice([50, 5000, 100_000])
    else:
        parent[key] = rng.choice(HOSTILE)
    return obj, depth


def _mutate_json_text(text: str, rng: random.Random) -> str:
    return _text(*_mutate_json(json.loads(text), rng))


def _reseal_run(d: Path) -> None:
    try:
        meta = json.loads((d / "run.json").read_text())
        if isinstance(meta.get("files"), dict):
            meta["files"] = {n: file_sha256(d / n) for n in ("ticks.parquet", "bridge.log")}
        write_run_json(d / "run.json", meta)
    except (ValueError, TypeError, RecursionError, AttributeError, OSError):
        pass  # a run.json the forger cannot read stays as it is


def _mutate_table(path: Path, rng: random.Random) -> None:
    table = pq.read_table(path)
    cols = table.to_pydict()
    n = len(cols["tick"])
    kind = rng.choice(["cell", "cell", "cell", "drop row", "dup row", "swap", "column", "type"])
    name = rng.choice(list(COLUMNS))
    if kind == "cell":
        i = rng.randrange(n)
        x = cols[name][i]
        pool = {
            "int": lambda: [-1, 0, 1, 2**62, -(2**62), x + 1],
            "float": lambda: [float("nan"), float("inf"), -1e308, 0.0, x + 500.0],
            "bool": lambda: [not x],
            "str": lambda: ["", "late", "state", "step", "active", "x" * 500, "\x00"],
        }[COLUMNS[name]]()
        cols[name][i] = rng.choice(pool)
        table = pa.table(cols, schema=table.schema)
    elif kind in ("drop row", "dup row", "swap"):
        i = rng.randrange(n)
        order = list(range(n))
        if kind == "drop row":
            del order[i]
        elif kind == "dup row":
            order.insert(i, i)
        else:
            j = rng.randrange(n)
            order[i], order[j] = order[j], order[i]
        table = table.take(order)
    elif kind == "column":
        table = table.drop_columns([name])
    else:
        table = table.set_column(
            table.column_names.index(name), name, pa.array([str(x) for x in cols[name]])
        )
    pq.write_table(table, path)


def _mutate_lines(path: Path, rng: random.Random) -> None:
    lines = path.read_bytes().split(b"\n")
    i = rng.randrange(len(lines))
    kind = rng.choice(["drop", "dup", "swap", "bytes", "garbage"])
    if kind == "drop":
        del lines[i]
    elif kind == "dup":
        lines.insert(i, lines[i])
    elif kind == "swap":
        j = rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif kind == "bytes":
        lines[i] = _mutate_bytes(lines[i] or b" ", rng)
    else:
        lines[i] = rng.choice([b"(x) y z", b"(1.0) can0 101#ZZ T", b"{}", b"[1,2]", b"\xff\xfe"])
    path.write_bytes(b"\n".join(lines))


def _mutate_journal_json(path: Path, rng: random.Random) -> None:
    lines = path.read_text().split("\n")
    i = rng.randrange(len(lines) - 1)  # the last is "" after the final newline
    lines[i] = _mutate_json_text(lines[i], rng)
    path.write_text("\n".join(lines))


RUN_MUTATIONS: dict[str, tuple[str, Callable[[Path, random.Random], None]]] = {
    "run.json bytes": ("run.json", lambda p, r: p.write_bytes(_mutate_bytes(p.read_bytes(), r))),
    "run.json values": (
        "run.json",
        lambda p, r: p.write_text(_mutate_json_text(p.read_text(), r)),
    ),
    "ticks.parquet bytes": (
        "ticks.parquet",
        lambda p, r: p.write_bytes(_mutate_bytes(p.read_bytes(), r)),
    ),
    "ticks.parquet table": ("ticks.parquet", _mutate_table),
    "bridge.log lines": ("bridge.log", _mutate_lines),
    "bridge.log bytes": (
        "bridge.log",
        lambda p, r: p.write_bytes(_mutate_bytes(p.read_bytes(), r)),
    ),
    "journal lines": ("ticks.jsonl", _mutate_lines),
    "journal values": ("ticks.jsonl", _mutate_journal_json),
    "journal bytes": ("ticks.jsonl", lambda p, r: p.write_bytes(_mutate_bytes(p.read_bytes(), r))),
    # a run killed before run.json was written: its settings are the journal's header's
    "journal alone values": ("ticks.jsonl", _mutate_journal_json),
    "journal alone bytes": (
        "ticks.jsonl",
        lambda p, r: p.write_bytes(_mutate_bytes(p.read_bytes(), r)),
    ),
}


def _replay_refuses(d: Path, out: Path, capsys) -> None:
    capsys.readouterr()
    rc = main(["replay", str(d), "--out", str(out)])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("ampc: error: ")]
    assert rc == 2 and len(lines) == 1, (rc, err[-2000:])
    assert lines[0].startswith(f"ampc: error: replay: {d}"), lines[0]
    assert "Traceback" not in err


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
@pytest.mark.parametrize("family", sorted(RUN_MUTATIONS))
def test_replay_readers_refuse_or_vouch_never_crash(runs, tmp_path, capsys, family, reseal):
    name, mutate = RUN_MUTATIONS[family]
    start = runs[
        "journal" if "alone" in family else "killed" if name == "ticks.jsonl" else "finished"
    ]
    rng = random.Random(f"{family}/{reseal}")
    refused = 0
    for k in range(CASES):
        d = tmp_path / f"case{k}"
        shutil.copytree(start, d)
        mutate(d / name, rng)
        if reseal:
            _reseal_run(d)
        try:
            run = check_run(d)
        except RunLogError as exc:
            assert str(exc).startswith(str(d)), exc
            refused += 1
            if refused <= 10:  # the command line's wording, on a sample
                _replay_refuses(d, tmp_path / "replay", capsys)
        else:
            # accepted: only what the checks cannot tell from the run it was
            if not reseal and name != "ticks.jsonl":
                # every file of a run that ended is under a digest: the content is the same
                same = check_run(start)
                assert run.meta == same.meta
                for key, col in same.cols.items():
                    assert np.array_equal(run.cols[key], col, equal_nan=col.dtype.kind == "f")
        shutil.rmtree(d)
    assert refused > 0


# -- the artefact ------------------------------------------------------------------


@pytest.fixture(scope="module")
def artefact(tmp_path_factory):
    """One `ampc export` of the scenario's float64 step, and what `ampc run` expects."""
    import contextlib
    import io

    from ampc_jax.cli.runtime import _golden_bus
    from ampc_jax.closed_loop import config_for
    from ampc_jax.runtime.step import RuntimeStep
    from ampc_jax.vehicle import SCENARIOS

    path = tmp_path_factory.mktemp("artefact") / "step.zip"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["export", "--scenario", SCENARIO, "--out", str(path)]) == 0
    step = RuntimeStep(config_for(SCENARIO, shadow=False))
    expect = {
        "expect_config_hash": step.config_hash(),
        "step": step,
        "golden_bus": _golden_bus(SCENARIOS[SCENARIO]),
        "scenario": SCENARIO,
    }
    with zipfile.ZipFile(path) as z:
        manifest = json.loads(z.read("manifest.json"))
        blob = z.read("step.stablehlo")
    return path, manifest, blob, expect


def _run_refuses(path: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("the bridge opened for a refused artefact")

    monkeypatch.setattr(can_bridge, "Bridge", refuse)
    capsys.readouterr()
    rc = main(["run", "--channel", "slcan-pty:", "--scenario", SCENARIO, "--quiet"]
              + ["--artefact", str(path), "--out", str(tmp_path / "out")])  # fmt: skip
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("ampc: error: ")]
    assert rc == 2 and len(lines) == 1, (rc, err[-2000:])
    assert lines[0].startswith("ampc: error: --artefact: "), lines[0]


def test_artefact_reader_refuses_damaged_bytes_never_crashes(
    artefact, tmp_path, capsys, monkeypatch
):
    path, manifest, _, expect = artefact
    data = path.read_bytes()
    rng = random.Random("artefact bytes")
    refused = 0
    for k in range(3 * CASES):
        p = tmp_path / f"case{k}.zip"
        p.write_bytes(_mutate_bytes(data, rng))
        try:
            art = read_artefact(p, **expect)
        except ArtefactError as exc:
            assert str(p) in str(exc), exc
            refused += 1
            if refused <= 10:
                _run_refuses(p, tmp_path, capsys, monkeypatch)
        else:  # bytes that held no content (a header's time stamp): the same artefact
            assert art.manifest == manifest
        p.unlink()
    assert refused > 2 * CASES


@pytest.mark.parametrize("reseal", [False, True], ids=["naive", "forger"])
def test_artefact_reader_refuses_hostile_manifests_never_crashes(
    artefact, tmp_path, capsys, monkeypatch, reseal
):
    path, manifest, blob, expect = artefact
    rng = random.Random(f"artefact manifest/{reseal}")
    refused = accepted = 0
    for k in range(2 * CASES):
        edited, depth = _mutate_json(manifest, rng)
        if reseal and isinstance(edited, dict):
            edited = seal_manifest(edited)  # over the value NEST: a nested one does not match
        p = tmp_path / f"case{k}.zip"
        text = _text(edited, depth)
        with zipfile.ZipFile(p, "w", compression=zipfile.ZIP_DEFLATED) as z:
            z.writestr("step.stablehlo", blob)
            z.writestr("manifest.json", text)
        try:
            art = read_artefact(p, **expect)
        except ArtefactError as exc:
            assert str(p) in str(exc), exc
            refused += 1
            if refused <= 10:
                _run_refuses(p, tmp_path, capsys, monkeypatch)
        else:
            # a resealed edit of what nothing can check (the exporter's versions), or
            # of the golden outputs, which the compiled step then refuses
            accepted += 1
            changed = {key for key in manifest if art.manifest.get(key) != manifest[key]}
            assert reseal and changed <= {"jax", "jaxlib", "golden", "manifest_sha256"}, changed
            if "golden" in changed and accepted <= 3:  # each compiles the step (cached)
                try:
                    art.compiled()
                except ArtefactError as exc:
                    assert "golden" in str(exc), exc
        p.unlink()
    assert refused > CASES


def test_a_resealed_step_mutation_is_refused_before_the_bridge_opens(
    artefact, tmp_path, capsys, monkeypatch
):
    """Bytes of step.stablehlo mutated, its digest and the manifest's resealed: the
    reader refuses (ArtefactError, MLIR's diagnostics kept off stderr) or the
    deserialized step is still well formed, and then compiling it checks its golden
    pair; `ampc run` says one line, before the bridge opens."""
    import hashlib

    path, manifest, blob, expect = artefact
    rng = random.Random("resealed step")
    refused = compiled = 0
    for k in range(CASES // 2):
        step = _mutate_bytes(blob, rng)
        m = seal_manifest({**manifest, "step_sha256": hashlib.sha256(step).hexdigest()})
        p = tmp_path / f"case{k}.zip"
        with zipfile.ZipFile(p, "w") as z:
            z.writestr("step.stablehlo", step)
            z.writestr("manifest.json", json.dumps(m))
        capsys.readouterr()
        try:
            art = read_artefact(p, **expect)
        except ArtefactError as exc:
            assert str(p) in str(exc), exc
            refused += 1
            assert "loc(" not in capsys.readouterr().err
            if refused <= 3:
                _run_refuses(p, tmp_path, capsys, monkeypatch)
        else:
            if compiled < 2:  # each compiles a program of its own
                compiled += 1
                try:
                    art.compiled()
                except ArtefactError as exc:
                    assert str(p) in str(exc), exc
        p.unlink()
    assert refused > CASES // 4
