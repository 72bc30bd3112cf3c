"""Input validation of ``ampc run``, ``ampc plant``, ``ampc export`` and ``ampc
replay`` (ampc_jax.cli.runtime): every refusal is one ``ampc: error: ...`` line
with exit code 2, given before anything starts (no bridge, no plant, no
compilation); ``--help`` states every option's default."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import struct
import zipfile

import pytest

from ampc_jax.cli import build_parser, main

pytestmark = pytest.mark.timeout(120)

SCENARIO = "cruise_lane_change"
COMMANDS = ("run", "plant", "export", "replay")


def _error(capsys) -> str:
    """The one error line on stderr (argparse prints its usage above it)."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("ampc: error: ")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture
def nothing_starts(monkeypatch):
    """Fail the test if the bridge is opened or the loop starts."""
    import ampc_jax.runtime.runner as runner
    import can_bridge

    def refuse(*args, **kwargs):
        raise AssertionError("started after a refusal")

    monkeypatch.setattr(can_bridge, "Bridge", refuse)
    monkeypatch.setattr(runner, "run_controller", refuse)


def _run(tmp_path, *args: str) -> list[str]:
    return ["run", "--scenario", SCENARIO, "--out", str(tmp_path / "out"), *args]


# -- run ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "channel", ["socketcan:vcan0", "slcan:/dev/ttyACM0", "socketcand:127.0.0.1:29536/can0"]
)
def test_run_with_plant_needs_the_pty(capsys, tmp_path, nothing_starts, channel) -> None:
    rc = main(_run(tmp_path, "--channel", channel, "--with-plant", "--quiet"))
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --with-plant: ") and "slcan-pty:" in line, line


@pytest.mark.parametrize(
    "fault", ["bogus@1:2", "nan", "nan@1", "nan@x:2", "fail@2:1", "silent@1:2", "nan@-1:2"]
)
def test_run_refuses_a_bad_fault(capsys, tmp_path, nothing_starts, fault) -> None:
    rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--fault", fault))
    assert rc == 2
    line = _error(capsys)
    assert repr(fault) in line, line
    assert not (tmp_path / "out").exists()


def test_run_bad_fault_names_the_flag(capsys, tmp_path, nothing_starts) -> None:
    assert main(_run(tmp_path, "--channel", "slcan-pty:", "--fault", "bogus@1:2")) == 2
    assert _error(capsys).startswith("ampc: error: --fault: ")


def test_plant_bad_fault_names_the_flag(capsys, tmp_path) -> None:
    rc = main(["plant", "--channel", "slcan:/nonexistent", "--scenario", SCENARIO,
               "--fault", "nan@1:2", "--out", str(tmp_path / "p")])  # fmt: skip
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --fault: ") and "'nan@1:2'" in line, line


@pytest.mark.parametrize("command", ["run", "plant", "export"])
def test_unknown_scenario(capsys, tmp_path, nothing_starts, command) -> None:
    args = {
        "run": ["run", "--channel", "slcan-pty:", "--out", str(tmp_path / "o")],
        "plant": ["plant", "--channel", "slcan:/nonexistent", "--out", str(tmp_path / "o")],
        "export": ["export", "--out", str(tmp_path / "a.zip")],
    }[command]
    rc = main([*args, "--scenario", "moon_landing"])
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --scenario: ") and "'moon_landing'" in line, line
    assert SCENARIO in line  # the choices are listed
    assert not (tmp_path / "a.zip").exists()


# -- export -------------------------------------------------------------------


def test_export_to_a_missing_directory(capsys, tmp_path) -> None:
    target = tmp_path / "no" / "such" / "dir" / "step.zip"
    rc = main(["export", "--scenario", SCENARIO, "--out", str(target)])
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --out ") and "does not exist" in line, line
    assert str(target.parent) in line
    assert not (tmp_path / "no").exists()


@pytest.fixture(scope="module")
def artefact(tmp_path_factory):
    """One ``ampc export`` of the scenario's default (float64) controller."""
    path = tmp_path_factory.mktemp("export") / "step.zip"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["export", "--scenario", SCENARIO, "--out", str(path)])
    assert rc == 0, out.getvalue()
    return path, out.getvalue()


def test_export_writes_the_artefact(artefact) -> None:
    path, out = artefact
    assert out.startswith(f"wrote {path}: local_explicit float64, config ")
    with zipfile.ZipFile(path) as z:
        assert sorted(z.namelist()) == ["manifest.json", "step.stablehlo"]
        manifest = json.loads(z.read("manifest.json"))
    assert manifest["scenario"] == SCENARIO and manifest["dtype"] == "float64"
    assert manifest["config_hash"][:12] in out


def _tampered(artefact, tmp_path) -> str:
    """The artefact with one byte of its step changed (manifest untouched)."""
    path, _ = artefact
    with zipfile.ZipFile(path) as z:
        blob = bytearray(z.read("step.stablehlo"))
        manifest = z.read("manifest.json")
    blob[100] ^= 0x10
    bad = tmp_path / "tampered.zip"
    with zipfile.ZipFile(bad, "w") as z:
        z.writestr("step.stablehlo", bytes(blob))
        z.writestr("manifest.json", manifest)
    return str(bad)


def test_run_refuses_a_tampered_artefact(capsys, tmp_path, artefact, nothing_starts) -> None:
    bad = _tampered(artefact, tmp_path)
    rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--artefact", bad, "--quiet"))
    assert rc == 2
    captured = capsys.readouterr()
    assert "controller step ready" not in captured.out  # refused before the loop
    line = [x for x in captured.err.splitlines() if x.startswith("ampc: error: ")]
    assert len(line) == 1, captured.err
    assert line[0].startswith("ampc: error: --artefact: ") and bad in line[0], line
    assert "modified after export" in line[0]


@pytest.mark.parametrize("flags", [["--float32"], ["--formulation", "integrated"]])
def test_run_refuses_an_artefact_of_another_configuration(
    capsys, tmp_path, artefact, nothing_starts, flags
) -> None:
    path, _ = artefact
    rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--artefact", str(path), *flags))
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --artefact: ")
    assert "another controller configuration" in line, line


def test_run_refuses_a_damaged_artefact_zip(capsys, tmp_path, artefact, nothing_starts) -> None:
    """Bytes flipped inside the zip's deflated step: one clean line, not zlib.error."""
    path, _ = artefact
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("step.stablehlo")
    data = bytearray(path.read_bytes())
    n, m = struct.unpack("<HH", data[info.header_offset + 26 : info.header_offset + 30])
    data[info.header_offset + 30 + n + m + 5] ^= 0xFF  # an invalid deflate stream
    bad = tmp_path / "damaged.zip"
    bad.write_bytes(bytes(data))
    rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--artefact", str(bad), "--quiet"))
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --artefact: ") and str(bad) in line, line


def test_run_on_a_missing_device_fails_before_compiling(capsys, tmp_path, monkeypatch) -> None:
    """The channel is opened first: a missing device is refused at once, naming
    --channel, not after the controller's compilation."""
    import ampc_jax.runtime.step as step

    def refuse(*args, **kwargs):
        raise AssertionError("compiled before the channel was opened")

    monkeypatch.setattr(step.RuntimeStep, "compiled", refuse)
    device = tmp_path / "no" / "ttyACM0"
    rc = main(_run(tmp_path, "--channel", f"slcan:{device}", "--quiet"))
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --channel: ") and str(device) in line, line


def test_run_refuses_what_is_not_an_artefact(capsys, tmp_path, nothing_starts) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("hello\n")
    for path in (notes, tmp_path / "absent.zip"):
        rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--artefact", str(path)))
        assert rc == 2
        line = _error(capsys)
        assert line.startswith("ampc: error: --artefact: ") and "not a readable" in line, line


# -- replay -------------------------------------------------------------------


def test_replay_of_a_directory_without_run_json(capsys, tmp_path) -> None:
    log = tmp_path / "log"
    log.mkdir()
    (log / "ticks.parquet").write_bytes(b"")  # the ticks alone are not a run
    rc = main(["replay", str(log), "--out", str(tmp_path / "replay")])
    assert rc == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: replay: ") and "run.json" in line, line
    assert str(log) in line
    rc = main(["replay", str(tmp_path / "nowhere"), "--out", str(tmp_path / "replay")])
    assert rc == 2
    assert "run.json" in _error(capsys)


@pytest.mark.parametrize("scale", ["1,x", "two"])
def test_replay_refuses_a_bad_rho_scale(capsys, tmp_path, scale) -> None:
    log = tmp_path / "log"
    log.mkdir()
    rc = main(["replay", str(log), "--rho-scale", scale, "--out", str(tmp_path / "r")])
    assert rc == 2
    line = _error(capsys)
    assert repr(scale.split(",")[-1]) in line, line


def test_replay_bad_rho_scale_names_the_flag(capsys, tmp_path) -> None:
    log = tmp_path / "log"
    log.mkdir()
    rc = main(["replay", str(log), "--rho-scale", "1,x", "--out", str(tmp_path / "r")])
    assert rc == 2
    assert _error(capsys).startswith("ampc: error: --rho-scale: ")


# -- --help -------------------------------------------------------------------


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    (sub,) = (a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: sub.choices[name] for name in COMMANDS}


def _options() -> list[tuple[str, argparse.Action]]:
    return [
        (name, action)
        for name, parser in _subparsers().items()
        for action in parser._actions
        if action.option_strings and not isinstance(action, argparse._HelpAction)
    ]


def _help_blocks(text: str) -> dict[str, str]:
    """Option string -> its help text, whitespace joined, from ``--help`` output."""
    blocks: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in text.splitlines():
        m = re.match(r"^  (-\S.*?)(?:\s{2,}(\S.*))?$", line)
        if m:
            current = [m.group(2) or ""]
            for opt in re.findall(r"(?:^|, )(--?[\w-]+)", m.group(1)):
                blocks[opt] = current
        elif current is not None and line.startswith("   ") and line.strip():
            current.append(line.strip())
        else:
            current = None
    return {k: " ".join(" ".join(v).split()) for k, v in blocks.items()}


def _default_text(action: argparse.Action) -> str | None:
    """The default as a help text writes it, or None where the text says it in words."""
    d = action.default
    if d is None or isinstance(d, bool):
        return None
    return f"{d:g}" if isinstance(d, float) else str(d)


@pytest.mark.parametrize(
    ("command", "flag"),
    [
        pytest.param(
            name,
            action.option_strings[-1],
        )
        for name, action in _options()
    ],
)
def test_help_states_each_default(capsys, monkeypatch, command, flag) -> None:
    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    blocks = _help_blocks(capsys.readouterr().out)
    action = next(a for n, a in _options() if n == command and a.option_strings[-1] == flag)
    text = blocks[flag]
    # the last parenthesis of a help text states the default, or that there is none
    assert text.endswith(")"), (command, flag, text)
    last = text[text.rindex("(") :]
    if action.required:
        assert last == "(required)", (command, flag, text)
        return
    assert "default: " in last, (command, flag, text)
    want = _default_text(action)
    if want is not None:
        assert f"default: {want})" in last, (command, flag, want, text)


def test_help_lists_every_option() -> None:
    # the parser behind the help is the one the tests above walk
    assert {name for name, _ in _options()} == set(COMMANDS)
    flags = {(n, a.option_strings[-1]) for n, a in _options()}
    assert {("run", "--channel"), ("run", "--lead-ms"), ("plant", "--cmd-timeout-ms")} <= flags
    assert {("export", "--out"), ("replay", "--rho-scale")} <= flags


# -- a forged step inside a resealed artefact ---------------------------------------


def _resealed(artefact, tmp_path, blob: bytes, name: str) -> str:
    """The artefact with ``blob`` as its step, the step's digest and the manifest's
    recomputed (what a forger who knows the format does)."""
    import hashlib

    from ampc_jax.runtime.artefact import seal_manifest

    path, _ = artefact
    with zipfile.ZipFile(path) as z:
        manifest = json.loads(z.read("manifest.json"))
    manifest["step_sha256"] = hashlib.sha256(blob).hexdigest()
    bad = tmp_path / name
    with zipfile.ZipFile(bad, "w") as z:
        z.writestr("step.stablehlo", blob)
        z.writestr("manifest.json", json.dumps(seal_manifest(manifest)))
    return str(bad)


def _step_blob(artefact) -> bytes:
    with zipfile.ZipFile(artefact[0]) as z:
        return z.read("step.stablehlo")


def _two_bytes(artefact) -> bytes:
    b = bytearray(_step_blob(artefact))
    b[30000] ^= 0x5A  # inside the MLIR bytecode, past the flatbuffer's header
    b[30001] ^= 0x33
    return bytes(b)


def _truncated(artefact) -> bytes:
    blob = _step_blob(artefact)
    return blob[: len(blob) - 1000]


def _signature(artefact, bus_size: int = 14, outputs: int = 0) -> bytes:
    """A step whose StableHLO takes a bus of ``bus_size`` (and returns ``outputs``
    extra entries of its first output) under the description of the real step
    (its in_avals and out_avals kept)."""
    import dataclasses

    import jax
    import jax.numpy as jnp
    from jax import export

    exp = export.deserialize(bytearray(_step_blob(artefact)))
    n_leaves = len(exp.in_avals) - 1

    def fake(leaves, bus):
        s = sum(jnp.sum(x).astype(jnp.float64) for x in leaves) + jnp.sum(bus)
        outs = [jnp.zeros(a.shape, a.dtype) + s.astype(a.dtype) for a in exp.out_avals]
        if outputs:
            outs[0] = jnp.zeros((a := exp.out_avals[0]).shape[0] + outputs, a.dtype)
        return jax.tree.unflatten(exp.out_tree, outs)

    leaves = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exp.in_avals[:n_leaves])
    bus = jax.ShapeDtypeStruct((bus_size,), exp.in_avals[-1].dtype)
    other = export.export(jax.jit(fake))(leaves, bus)
    forged = dataclasses.replace(other, in_avals=exp.in_avals, out_avals=exp.out_avals)
    return bytes(forged.serialize())


@pytest.fixture(scope="module")
def other_step(tmp_path_factory):
    """The step of another controller configuration (rho scaled by 2: the same
    shapes, other constants), exported once."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from ampc_jax.cli.runtime import _golden_bus
    from ampc_jax.closed_loop import config_for
    from ampc_jax.runtime.artefact import export_step
    from ampc_jax.runtime.step import RuntimeStep
    from ampc_jax.vehicle import SCENARIOS

    path = tmp_path_factory.mktemp("other") / "other.zip"
    step = RuntimeStep(config_for(SCENARIO, shadow=False, rho_scale=2.0))
    export_step(step, _golden_bus(SCENARIOS[SCENARIO]), path, scenario=SCENARIO)
    with zipfile.ZipFile(path) as z:
        return z.read("step.stablehlo")


FORGERIES = {
    "two bytes": (_two_bytes, "does not deserialize as StableHLO"),
    "truncated": (_truncated, "does not deserialize"),
    "bus of 14": (_signature, "@main takes"),
    "bus of 12": (lambda a: _signature(a, 12), "@main takes"),
    "output shape": (lambda a: _signature(a, 13, outputs=1), "@main returns"),
}


@pytest.mark.parametrize("forgery", sorted(FORGERIES))
def test_run_refuses_a_forged_step_before_the_channel_opens(
    capsys, tmp_path, artefact, nothing_starts, forgery
) -> None:
    """A step changed inside a resealed artefact (its digests recomputed) is refused
    with exit 2 and one ``--artefact`` line, before the bridge opens, without MLIR's
    diagnostics on stderr."""
    make, words = FORGERIES[forgery]
    bad = _resealed(artefact, tmp_path, make(artefact), "forged.zip")
    rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--artefact", bad, "--quiet"))
    captured = capsys.readouterr()
    assert rc == 2, captured.err
    assert captured.err.count("\n") == 1 and "loc(" not in captured.err.split(words)[0], (
        captured.err
    )
    line = captured.err.strip()
    assert line.startswith(f"ampc: error: --artefact: artefact {bad}: "), line
    assert words in line, line
    assert not (tmp_path / "out" / "bridge.log").exists()


def test_run_refuses_a_step_of_another_configuration_before_the_channel_opens(
    capsys, tmp_path, artefact, nothing_starts, other_step
) -> None:
    """Another configuration's step under this one's manifest (resealed): the same
    shapes, so only its golden pair tells, and that is checked before the bridge opens."""
    bad = _resealed(artefact, tmp_path, other_step, "other.zip")
    rc = main(_run(tmp_path, "--channel", "slcan-pty:", "--artefact", bad, "--quiet"))
    assert rc == 2
    line = _error(capsys)
    assert line.startswith(f"ampc: error: --artefact: artefact {bad}: "), line
    assert "golden pair differs" in line, line


# -- real-time scheduling by default ------------------------------------------------


@pytest.fixture
def options_seen(monkeypatch):
    """The RunOptions `ampc run` passes to the loop (which then stops the run)."""
    import ampc_jax.runtime.runner as runner

    seen = []

    def record(prepare, channel, out, options, **kwargs):
        seen.append((options, kwargs["meta"]))
        raise RuntimeError("stopped by the test")

    monkeypatch.setattr(runner, "run_controller", record)
    return seen


def _refused(monkeypatch) -> list[int]:
    import ampc_jax.runtime.runner as runner

    asked = []

    def refuse(priority):
        asked.append(priority)
        return "Operation not permitted; needs root"

    monkeypatch.setattr(runner, "fifo_refusal", refuse)
    return asked


def test_run_asks_for_real_time_scheduling_by_default(
    capsys, tmp_path, options_seen, monkeypatch
) -> None:
    import ampc_jax.runtime.runner as runner

    monkeypatch.setattr(runner, "fifo_refusal", lambda priority: None)  # allowed
    assert main(_run(tmp_path, "--channel", "slcan-pty:", "--quiet")) == 1
    options, meta = options_seen[-1]
    assert options.rt_priority == runner.RT_PRIORITY == 50
    assert meta["scheduling"] == {"rt_priority": 50, "refused": False}
    assert "ampc: warning" not in capsys.readouterr().err


def test_a_refused_default_says_so_in_one_line_and_runs(
    capsys, tmp_path, options_seen, monkeypatch
) -> None:
    asked = _refused(monkeypatch)
    assert main(_run(tmp_path, "--channel", "slcan-pty:", "--quiet")) == 1  # the fake loop's
    assert asked == [50]
    options, meta = options_seen[-1]
    assert options.rt_priority is None and meta["scheduling"]["refused"] is True
    err = capsys.readouterr().err
    warnings = [x for x in err.splitlines() if x.startswith("ampc: warning: ")]
    assert len(warnings) == 1, err
    assert "real-time scheduling refused" in warnings[0] and "p99" in warnings[0]
    assert "--rt-priority 0" in warnings[0]


def test_an_explicit_priority_refused_is_an_error(
    capsys, tmp_path, nothing_starts, monkeypatch
) -> None:
    _refused(monkeypatch)
    assert main(_run(tmp_path, "--channel", "slcan-pty:", "--rt-priority", "40")) == 2
    line = _error(capsys)
    assert line.startswith("ampc: error: --rt-priority 40: SCHED_FIFO refused"), line


def test_rt_priority_0_is_normal_scheduling(capsys, tmp_path, options_seen, monkeypatch) -> None:
    asked = _refused(monkeypatch)
    assert main(_run(tmp_path, "--channel", "slcan-pty:", "--rt-priority", "0", "--quiet")) == 1
    assert asked == []  # not even asked
    options, _ = options_seen[-1]
    assert options.rt_priority is None
    assert "ampc: warning" not in capsys.readouterr().err


@pytest.mark.parametrize("value", ["1", "100", "-1", "x"])
def test_rt_priority_out_of_range(capsys, tmp_path, nothing_starts, value) -> None:
    with pytest.raises(SystemExit) as exc:
        main(_run(tmp_path, "--channel", "slcan-pty:", "--rt-priority", value))
    assert exc.value.code == 2
    assert "--rt-priority" in _error(capsys)
