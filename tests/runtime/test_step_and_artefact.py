"""The runtime's controller step and its exported artefact.

* ``command_problem``: the rule of what may be sent (a usable solve, finite
  torques, agent inputs within their bounds) and nothing else is refused;
  ``clamp_to_limits`` clamps a wheel torque to its actuator's range.
* ``RuntimeStep``: the compiled step is ``Controller.step`` on the estimator's
  measurement; float32 commands stay within one bus torque step of float64.
* ``export_step`` / ``load_artefact``: a round trip runs the same step bit for
  bit; a tampered, foreign or unreadable artefact is refused, naming why.
"""

from __future__ import annotations

import hashlib
import json
import struct
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import export

from ampc_jax.closed_loop import config_for, controller_for
from ampc_jax.results import USABLE_STATUS, Status
from ampc_jax.runtime.artefact import ARTEFACT_FORMAT, ArtefactError, export_step, load_artefact
from ampc_jax.runtime.signals import BUS_FIELDS, bus_measurement, bus_vector
from ampc_jax.runtime.step import (
    BOUND_TOL_NM,
    RuntimeStep,
    StepReport,
    clamp_to_limits,
    command_problem,
)
from ampc_jax.vehicle.actuators import ACTUATORS, TORQUE_STEP_NM
from ampc_jax.vehicle.manoeuvres import (
    DriverParams,
    driver_step,
    initial_driver_state,
    initial_plant_state,
    scenario,
)
from ampc_jax.vehicle.params import CONTROL_DT
from ampc_jax.vehicle.plant import plant_step

pytestmark = pytest.mark.timeout(180)

SCENARIO = "cruise_lane_change"
TICKS = 6
WHEELS = ("FL", "FR", "RL", "RR")


def _report(
    status: int = Status.SOLVED, fallback: bool = False, violation: float = 0.0
) -> StepReport:
    return StepReport(np.int32(7), np.int32(status), np.bool_(fallback), 1e-6, 1e-6, violation)


# -- command_problem --------------------------------------------------------------


def test_command_problem_accepts_a_good_command() -> None:
    assert command_problem(np.array([-120.0, -80.0, 350.0, -40.0]), _report()) is None
    # max_iter_reached is usable: its inputs are applied (USABLE_STATUS)
    assert command_problem(np.zeros(4), _report(status=Status.MAX_ITER_REACHED)) is None
    # each range's ends are inside it
    lo = np.array([w.min_nm for w in ACTUATORS.wheels])
    hi = np.array([w.max_nm for w in ACTUATORS.wheels])
    assert command_problem(lo, _report()) is None
    assert command_problem(hi, _report()) is None
    # float32 torques as a float32 step returns them
    assert command_problem(np.array([-1.5, 0.0, 2.0, 3.0], np.float32), _report()) is None


def test_command_problem_refuses_a_fallback() -> None:
    why = command_problem(np.zeros(4), _report(fallback=True))
    assert why is not None and "fallback True" in why


@pytest.mark.parametrize("status", [s for s in (2, 3, 4, 5, -1, 99) if s not in USABLE_STATUS])
def test_command_problem_refuses_an_unusable_status(status: int) -> None:
    # the bus applies what the controller's guard applies (USABLE_STATUS), nothing else
    why = command_problem(np.zeros(4), _report(status=status))
    assert why is not None and f"status {status}" in why


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("wheel", range(4))
def test_command_problem_refuses_non_finite(wheel: int, bad: float) -> None:
    t = np.array([-10.0, -10.0, 10.0, 10.0])
    t[wheel] = bad
    why = command_problem(t, _report())
    assert why is not None and "non-finite" in why


def test_command_problem_refuses_a_wrong_shape() -> None:
    assert command_problem(np.zeros(3), _report()) is not None
    assert command_problem(np.zeros((1, 4)), _report()) is not None


def test_command_problem_refuses_inputs_beyond_their_bounds() -> None:
    assert command_problem(np.zeros(4), _report(violation=0.5)) is None  # within the tolerance
    why = command_problem(np.zeros(4), _report(violation=BOUND_TOL_NM + 0.5))
    assert why is not None and "leaves its bounds" in why
    assert command_problem(np.zeros(4), _report(violation=np.nan)) is not None


@pytest.mark.parametrize("wheel", range(4))
def test_out_of_range_wheel_torques_are_clamped_and_named(wheel: int) -> None:
    w = ACTUATORS.wheels[wheel]
    for x, edge in ((w.min_nm - 1.0, w.min_nm), (w.max_nm + 1.0, w.max_nm)):
        t = np.zeros(4)
        t[wheel] = x
        out, note = clamp_to_limits(t)
        assert out[wheel] == edge and note is not None and WHEELS[wheel] in note
        assert np.all(np.delete(out, wheel) == 0.0)
    out, note = clamp_to_limits(np.zeros(4))
    assert note is None and np.all(out == 0.0)


def test_clamp_uses_the_limits_given() -> None:
    tight = ACTUATORS._replace(
        wheels=tuple(w._replace(min_nm=-100.0, max_nm=100.0) for w in ACTUATORS.wheels)
    )
    t = np.array([-150.0, 0.0, 0.0, 0.0])
    assert clamp_to_limits(t)[1] is None
    out, note = clamp_to_limits(t, tight)
    assert out[0] == -100.0 and "FL" in note


# -- RuntimeStep ----------------------------------------------------------------


@pytest.fixture(scope="module")
def cfg():
    return config_for(SCENARIO, shadow=False)


def test_runtime_step_refuses_no_controller() -> None:
    none = config_for(SCENARIO, shadow=False, formulation="none")
    with pytest.raises(ValueError, match="^formulation: .*'none'"):
        RuntimeStep(none)


@pytest.mark.parametrize("dtype", ["float16", "f64", "bfloat16", ""])
def test_runtime_step_refuses_a_bad_dtype(cfg, dtype: str) -> None:
    with pytest.raises(ValueError, match=f"^dtype: .*{dtype!r}"):
        RuntimeStep(cfg, dtype)


def test_config_hash_tells_configurations_apart(cfg) -> None:
    h = RuntimeStep(cfg).config_hash()
    assert h == RuntimeStep(config_for(SCENARIO, shadow=False)).config_hash()
    assert h != RuntimeStep(cfg, "float32").config_hash()
    assert h != RuntimeStep(config_for(SCENARIO, shadow=False, rho_scale=2.0)).config_hash()
    assert (
        h != RuntimeStep(config_for(SCENARIO, shadow=False, formulation="integrated")).config_hash()
    )


@pytest.fixture(scope="module")
def step64(cfg):
    step = RuntimeStep(cfg)
    return step, step.compiled()


@pytest.fixture(scope="module")
def drive(cfg, step64):
    """TICKS ticks of the scenario's start with the compiled step in the loop:
    the bus vectors and each tick's outputs (torques, leaves, report)."""
    step, fn = step64
    spec = scenario(SCENARIO)
    sc, vehicle = spec.scenario, cfg.vehicle
    advance = jax.jit(lambda s, d, t: plant_step(s, d, t, sc.mu, vehicle))
    ps = initial_plant_state(sc, vehicle, jnp.float64)
    ds = initial_driver_state(jnp.float64)
    leaves = step.init_leaves()
    buses, outs = [], []
    for k in range(TICKS):
        ds, steer, T, v_ref = driver_step(ds, ps, k * CONTROL_DT, sc, DriverParams())
        bus = bus_vector(ps, steer, T, v_ref, float(sc.mu))
        torques, leaves, report = fn(leaves, jnp.asarray(bus))
        buses.append(bus)
        outs.append((np.asarray(torques), leaves, tuple(np.asarray(r) for r in report)))
        ps = advance(ps, steer, torques)
    return np.stack(buses), outs


def test_compiled_step_signature(step64, drive) -> None:
    step, _ = step64
    buses, outs = drive
    assert buses.shape == (TICKS, len(BUS_FIELDS))
    torques, leaves, report = outs[0]
    assert torques.shape == (4,) and torques.dtype == np.float64
    assert len(leaves) == len(step.init_leaves())
    assert len(report) == len(StepReport._fields)
    assert report[0].dtype == np.int32 and report[1].dtype == np.int32
    assert report[2].dtype == np.bool_
    for torques, _, report in outs:
        assert command_problem(torques, StepReport(*report)) is None
    # the scenario's driver asks for torque: the commands are not all zero
    assert np.max(np.abs(outs[-1][0])) > 1.0


def test_compiled_step_is_the_controllers_step(cfg, drive) -> None:
    """The compiled step = Controller.step on bus_measurement's measurement, the
    configuration's controller and parameters, warm state carried along."""
    buses, outs = drive
    ctrl = controller_for(cfg)
    params = cfg.loop_params(jnp.float64).controller
    direct = jax.jit(lambda s, m, d: ctrl.step(s, params, m, d))
    state = ctrl.init(jnp.float64)
    for k, (bus, (torques, leaves, report)) in enumerate(zip(buses, outs, strict=True)):
        meas, driver = bus_measurement(jnp.asarray(bus), cfg.vehicle)
        T, state, info = direct(state, meas, driver)
        # one program compiled twice (parameters folded in as constants, or passed
        # in): the same iterations, and torques equal to round-off of the solve
        assert int(info.iterations) == int(report[0]), k
        assert int(info.status) == int(report[1]) and bool(info.fallback) == bool(report[2])
        np.testing.assert_allclose(np.asarray(T), torques, rtol=1e-9, atol=1e-9, err_msg=str(k))
        np.testing.assert_allclose(float(info.primal_residual), report[3], rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(float(info.dual_residual), report[4], rtol=1e-6, atol=1e-12)
        ref = jax.tree.leaves(state)
        assert len(ref) == len(leaves)
        for a, b in zip(ref, leaves, strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)


# float32 vs float64 on the same bus vectors: each step's solve stops at its
# tolerance either way, so the commands differ by the solve's residual, not
# by float32's rounding alone; the bound is what the bus can tell apart at
# all: one step of the torque signal (TORQUE_STEP_NM, 2 Nm; seen: under 0.2 Nm).
FLOAT32_TOL_NM = TORQUE_STEP_NM


def test_float32_step_within_one_torque_step_of_float64(cfg, drive) -> None:
    buses, outs = drive
    step = RuntimeStep(cfg, "float32")
    fn = step.compiled()
    leaves = step.init_leaves()
    assert all(np.asarray(x).dtype != np.float64 for x in leaves)
    for k, (bus, (torques64, _, _)) in enumerate(zip(buses, outs, strict=True)):
        torques, leaves, report = fn(leaves, jnp.asarray(bus, jnp.float32))
        assert np.asarray(torques).dtype == np.float32
        t32 = np.asarray(torques, np.float64)
        assert command_problem(t32, StepReport(*report)) is None, k
        assert np.max(np.abs(t32 - torques64)) <= FLOAT32_TOL_NM, (k, t32, torques64)


# -- artefact -------------------------------------------------------------------


@pytest.fixture(scope="module")
def artefact(tmp_path_factory, step64, drive):
    """One export of the float64 step (the golden input: the first tick's bus)."""
    step, _ = step64
    buses, _ = drive
    path = tmp_path_factory.mktemp("artefact") / "step.zip"
    manifest = export_step(step, buses[0], path, scenario=SCENARIO)
    return path, manifest


def _read(path: Path) -> tuple[bytes, dict]:
    with zipfile.ZipFile(path) as z:
        return z.read("step.stablehlo"), json.loads(z.read("manifest.json"))


def _write(path: Path, blob: bytes, manifest: dict, *, reseal: bool = True) -> Path:
    """The artefact with ``manifest``: resealed (its hash recomputed, as a forger
    who knows the format would) unless ``reseal`` is False (a naive edit)."""
    if reseal:
        from ampc_jax.runtime.artefact import seal_manifest

        manifest = seal_manifest(manifest)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("step.stablehlo", blob)
        z.writestr("manifest.json", json.dumps(manifest, indent=1))
    return path


def test_export_writes_step_and_manifest(artefact, step64, drive) -> None:
    path, manifest = artefact
    step, _ = step64
    blob, written = _read(path)
    assert written == manifest
    assert manifest["format"] == ARTEFACT_FORMAT
    assert manifest["step_sha256"] == hashlib.sha256(blob).hexdigest()
    assert manifest["config_hash"] == step.config_hash()
    assert manifest["scenario"] == SCENARIO and manifest["dtype"] == "float64"
    assert manifest["formulation"] == step.config.formulation
    assert manifest["example"] == step.config.example
    assert manifest["jax"] == jax.__version__
    ccv = manifest["calling_convention_version"]
    lo = export.minimum_supported_calling_convention_version
    assert lo <= ccv <= export.maximum_supported_calling_convention_version
    assert manifest["inputs"]["bus"] == {"shape": [len(BUS_FIELDS)], "dtype": "float64"}
    assert len(manifest["inputs"]["leaves"]) == len(step.init_leaves())
    # the golden output is what the in-process step gives on the golden input
    buses, outs = drive
    golden = manifest["golden"]
    np.testing.assert_array_equal(golden["bus"]["data"], buses[0])
    np.testing.assert_array_equal(golden["outputs"][0]["data"], outs[0][0])
    assert len(manifest["outputs"]) == len(golden["outputs"])


def test_artefact_round_trip_runs_the_same_step(artefact, step64, drive) -> None:
    path, manifest = artefact
    step, _ = step64
    art = load_artefact(path, step.config_hash())
    assert art.manifest == manifest
    for a, b in zip(art.init_leaves(), step.init_leaves(), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    fn = art.compiled()
    buses, outs = drive
    leaves = art.init_leaves()
    for k, (bus, (torques, ref_leaves, report)) in enumerate(zip(buses, outs, strict=True)):
        got_t, leaves, got_r = fn(leaves, jnp.asarray(bus))
        # the serialized StableHLO of the same function: bit for bit, warm state too
        np.testing.assert_array_equal(np.asarray(got_t), torques, err_msg=str(k))
        for a, b in zip(got_r, report, strict=True):
            np.testing.assert_array_equal(np.asarray(a), b)
        for a, b in zip(leaves, ref_leaves, strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True), k


def test_refuses_tampered_step_bytes(artefact, tmp_path) -> None:
    path, _ = artefact
    blob, manifest = _read(path)
    b = bytearray(blob)
    b[len(b) // 2] ^= 0x01
    bad = _write(tmp_path / "tampered.zip", bytes(b), manifest)
    with pytest.raises(ArtefactError, match="step.stablehlo hashes to .*modified after export"):
        load_artefact(bad)


def test_refuses_tampered_golden_output(artefact, tmp_path) -> None:
    path, _ = artefact
    blob, manifest = _read(path)
    # the step's hash still matches: only running the golden input shows it
    manifest["golden"]["outputs"][0]["data"][2] += 0.5
    bad = _write(tmp_path / "golden.zip", blob, manifest)
    with pytest.raises(ArtefactError, match=r"output 0 of the golden pair differs") as exc:
        load_artefact(bad)
    assert str(bad) in str(exc.value)


def test_refuses_another_configuration(artefact, cfg) -> None:
    path, _ = artefact
    for other in (
        RuntimeStep(cfg, "float32"),
        RuntimeStep(config_for(SCENARIO, shadow=False, rho_scale=2.0)),
    ):
        with pytest.raises(ArtefactError, match="made for another controller configuration"):
            load_artefact(path, other.config_hash())


@pytest.mark.parametrize(
    "ccv",
    [
        export.maximum_supported_calling_convention_version + 1,
        export.minimum_supported_calling_convention_version - 1,
        None,
        "9",
    ],
)
def test_refuses_unsupported_calling_convention(artefact, tmp_path, ccv) -> None:
    path, _ = artefact
    blob, manifest = _read(path)
    manifest["calling_convention_version"] = ccv
    bad = _write(tmp_path / "ccv.zip", blob, manifest)
    with pytest.raises(ArtefactError, match=f"calling convention version {ccv!r}"):
        load_artefact(bad)


def test_refuses_another_format(artefact, tmp_path) -> None:
    path, _ = artefact
    blob, manifest = _read(path)
    manifest["format"] = ARTEFACT_FORMAT + 1
    with pytest.raises(ArtefactError, match=f"format {ARTEFACT_FORMAT + 1}, expected"):
        load_artefact(_write(tmp_path / "format.zip", blob, manifest))


def test_refuses_what_is_not_an_artefact(artefact, tmp_path) -> None:
    text = tmp_path / "notes.zip"
    text.write_text("not a zip file\n")
    with pytest.raises(ArtefactError, match="not a readable artefact"):
        load_artefact(text)
    with pytest.raises(ArtefactError, match="not a readable artefact"):
        load_artefact(tmp_path / "absent.zip")
    # a zip without a manifest, and one whose manifest is not JSON
    blob, _ = _read(artefact[0])
    with zipfile.ZipFile(tmp_path / "bare.zip", "w") as z:
        z.writestr("step.stablehlo", blob)
    with pytest.raises(ArtefactError, match="not a readable artefact"):
        load_artefact(tmp_path / "bare.zip")
    with zipfile.ZipFile(tmp_path / "json.zip", "w") as z:
        z.writestr("step.stablehlo", blob)
        z.writestr("manifest.json", "{not json")
    with pytest.raises(ArtefactError, match="not a readable artefact"):
        load_artefact(tmp_path / "json.zip")


# -- artefact: edits, damage, hostile manifests (issue: manifest edits accepted) --

MANIFEST_EDITS = {
    "jax": lambda m: m.update(jax="0.4.1"),
    "jaxlib": lambda m: m.update(jaxlib="0.4.1"),
    "platforms": lambda m: m.update(platforms=["cuda"]),
    "scenario": lambda m: m.update(scenario="stability_dlc"),
    "formulation": lambda m: m.update(formulation="integrated"),
    "example": lambda m: m.update(example="stability"),
    "outputs": lambda m: m["outputs"][0].update(shape=[5]),
    "golden": lambda m: m["golden"]["outputs"][0]["data"].__setitem__(0, 1.0),
    "extra key": lambda m: m.update(note="hello"),
}


@pytest.mark.parametrize("field", sorted(MANIFEST_EDITS))
def test_refuses_any_manifest_edit(artefact, tmp_path, field) -> None:
    path, _ = artefact
    blob, manifest = _read(path)
    MANIFEST_EDITS[field](manifest)
    bad = _write(tmp_path / "edited.zip", blob, manifest, reseal=False)
    with pytest.raises(ArtefactError, match=r"manifest.json .*modified after export") as exc:
        load_artefact(bad)
    assert str(bad) in str(exc.value)


@pytest.mark.parametrize(
    ("field", "words"),
    [
        ("platforms", "platforms"),
        ("scenario", "scenario"),
        ("formulation", "formulation"),
        ("outputs", "outputs"),
    ],
)
def test_refuses_a_resealed_manifest_that_disagrees_with_its_step(
    artefact, step64, tmp_path, field, words
) -> None:
    """A forger who reseals the manifest: its fields must still agree with the
    serialized step (platforms, output shapes) and with what this run builds."""
    path, _ = artefact
    step, _ = step64
    blob, manifest = _read(path)
    MANIFEST_EDITS[field](manifest)
    bad = _write(tmp_path / "resealed.zip", blob, manifest)
    with pytest.raises(ArtefactError, match=words):
        load_artefact(bad, step.config_hash(), step=step, scenario=SCENARIO)


def test_flipped_bytes_anywhere_in_the_zip_are_refused_cleanly(artefact, tmp_path) -> None:
    """A byte flipped anywhere in the file: refused with ArtefactError (never
    zlib.error or another exception), or, where the byte held no content (a
    header's timestamp), the very same step and manifest read back."""
    from ampc_jax.runtime.artefact import read_artefact

    path, manifest = artefact
    data = path.read_bytes()
    rng = np.random.default_rng(0)
    positions = sorted(set(rng.integers(0, len(data), 120).tolist()) | {0, 1, len(data) - 1})
    refused = 0
    for pos in positions:
        bad = bytearray(data)
        bad[pos] ^= 0xA5
        p = tmp_path / "flipped.zip"
        p.write_bytes(bytes(bad))
        try:
            art = read_artefact(p)
        except ArtefactError as exc:
            assert str(p) in str(exc)
            refused += 1
            continue
        assert art.manifest == manifest, pos
    assert refused > len(positions) // 2


def test_a_flipped_byte_in_the_compressed_step_is_refused(artefact, tmp_path) -> None:
    path, _ = artefact
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("step.stablehlo")
    data = bytearray(path.read_bytes())
    # inside the deflated data: after the local header (30 bytes, name, extra)
    n, m = struct.unpack("<HH", data[info.header_offset + 26 : info.header_offset + 30])
    data[info.header_offset + 30 + n + m + 5] ^= 0xFF  # an invalid deflate stream
    bad = tmp_path / "flipped.zip"
    bad.write_bytes(bytes(data))
    with pytest.raises(ArtefactError, match="not a readable artefact"):
        load_artefact(bad)


@pytest.mark.parametrize(
    "text",
    [
        "[" * 100_000 + "]" * 100_000,
        '{"format": 2, "golden": ' + '{"a": ' * 50_000 + "1" + "}" * 50_001,
        '{"format": 2, "x": 1e999999}',
        b"\xff\xfe{" * 10,
    ],
    ids=["nested list", "nested object", "huge number", "bad unicode"],
)
def test_refuses_a_hostile_manifest_cleanly(artefact, tmp_path, text) -> None:
    path, _ = artefact
    blob, _ = _read(path)
    bad = tmp_path / "hostile.zip"
    with zipfile.ZipFile(bad, "w") as z:
        z.writestr("step.stablehlo", blob)
        z.writestr("manifest.json", text)
    with pytest.raises(ArtefactError, match="manifest.json"):
        load_artefact(bad)
