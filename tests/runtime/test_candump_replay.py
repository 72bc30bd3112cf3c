"""`ampc replay --candump FILE --scenario NAME`: a drive's candump log through the
controller, its state frames decoded with cantools from the DBC (E2E-checked by
autosar-e2e) and fed at their timestamps, the commands the controller would
have framed compared bit for bit with the log's torque frames, a figure.

Two logs of the shared 10 s run (conftest's ``run_dir``): its bridge's own
candump log, as recorded, and one synthesised with python-can, cantools and
autosar-e2e from its tick log (each tick's bus vector as the five state
frames, believed by the tick's wake-up; each tick's framed torques as its
torque frame), on which every command must come out bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import can
import cantools
import e2e.p01
import numpy as np
import pyarrow.parquet as pq
import pytest

import can_bridge
from ampc_jax.cli import main
from ampc_jax.runtime.signals import BUS_FIELDS, SIGNALS

pytestmark = pytest.mark.timeout(300)

SCENARIO = "cruise_lane_change"
WHEELS = ("FL", "FR", "RL", "RR")
MODES = {"active": 0, "hold": 1, "safe": 2, "fault": 3}


def _cols(path: Path) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in pq.read_table(path).to_pydict().items()}


def _replay(capsys, log: Path, out: Path, *extra: str) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["replay", "--candump", str(log), "--scenario", SCENARIO, "--out", str(out), *extra])
    got = capsys.readouterr()
    return rc, got.out, got.err


class _Frames:
    """A candump log written with python-can, frames encoded with cantools and
    protected with autosar-e2e (Profile 1), each message with its own counter."""

    def __init__(self, path: Path) -> None:
        self.db = cantools.database.load_file(can_bridge.dbc_path())
        self.writer = can.CanutilsLogWriter(str(path), channel="can0")
        self.counters: dict[str, int] = {}

    def send(self, t: float, name: str, values: dict[str, float]) -> None:
        msg = self.db.get_message_by_name(name)
        counter = self.counters.get(name, 0)
        self.counters[name] = (counter + 1) % 15
        data = bytearray(msg.encode({"CRC": 0, "Counter": counter, **values}, strict=False))
        data_id = int(msg.dbc.attributes["E2EDataID"].value)
        e2e.p01.e2e_p01_protect(data, data_id, increment_counter=False)
        self.writer.on_message_received(
            can.Message(
                timestamp=t, arbitration_id=msg.frame_id, is_extended_id=False, data=bytes(data)
            )  # fmt: skip
        )

    def close(self) -> None:
        self.writer.stop()


def _synthesise(run_dir: Path, path: Path, lead_s: float = 0.025, drop: str | None = None) -> int:
    """The candump log of the run's ticks from its first stepped one up to the first
    that did not step after it (the stretch over which a replay's warm state is
    the run's): the bus vector 2 ms before the bridge would believe it, the
    framed torques at the tick's frame; returns the number of ticks."""
    from ampc_jax.runtime.candump import confirm_s

    c = _cols(run_dir / "ticks.parquet")
    stepped = c["stepped"].astype(bool)
    first = int(np.flatnonzero(stepped)[0])
    stop = first + int(np.argmin(stepped[first:])) if not stepped[first:].all() else len(stepped)
    frames = _Frames(path)
    confirm = confirm_s()
    for i in range(first, stop):
        t = 1000.0 + 0.05 * (i - first)  # the tick's wake-up
        for name, signals in _by_message(c, i).items():
            if name != drop:
                frames.send(t - confirm - 0.002, name, signals)
        mode = c["bridge_mode"][i] or "hold"
        torques = {f"Torque{w}": float(c[f"framed_{w}"][i]) for w in WHEELS}
        if not np.isfinite(list(torques.values())).all():
            torques = dict.fromkeys(torques, 0.0)
        frames.send(t + lead_s, "WheelTorqueCmd", {"Mode": MODES[mode], **torques})
    frames.close()
    return stop - first


def _by_message(c: dict[str, np.ndarray], i: int) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for sig in SIGNALS:
        out.setdefault(sig.message, {})[sig.signal] = float(c[f"bus_{sig.field}"][i])
    return out


def test_a_synthesised_log_of_the_run_replays_every_command_bit_for_bit(
    run_dir: Path, tmp_path: Path, capsys
) -> None:
    log = tmp_path / "drive.log"
    n = _synthesise(run_dir, log)
    rc, out, err = _replay(capsys, log, tmp_path / "out")
    assert rc == 0, err
    res = json.loads((tmp_path / "out" / "candump_replay.json").read_text())
    rep = _cols(tmp_path / "out" / "candump_replay.parquet")
    run = _cols(run_dir / "ticks.parquet")
    first = int(np.flatnonzero(run["stepped"])[0])
    rows = slice(first, first + n)
    assert res["ticks"] == n and res["stepped"] == n, res
    # the bus vectors decoded from the frames are the run's, and so is every command
    for f in BUS_FIELDS:
        np.testing.assert_array_equal(rep[f"bus_{f}"], run[f"bus_{f}"][rows], err_msg=f)
    for w in WHEELS:
        np.testing.assert_array_equal(rep[f"cmd_{w}"], run[f"cmd_{w}"][rows], err_msg=w)
    # every active frame of a command handed over on time: what the bridge framed
    on_time = (run["margin_ms"][rows] >= 0) & run["sent"][rows].astype(bool)
    compared = rep["compared"].astype(bool)
    assert compared[on_time].sum() > 0.5 * n
    assert rep["identical"][compared & on_time].all(), np.flatnonzero(
        compared & on_time & ~rep["identical"]
    )
    assert res["identical"] == int(rep["identical"].sum()) and res["identical"] > 0
    assert (tmp_path / "out" / "candump_replay.png").stat().st_size > 10_000
    assert f"compared {res['compared']} active frames: {res['identical']} identical" in out


def test_the_bridges_own_log_replays_and_each_difference_is_the_runs_timing(
    run_dir: Path, tmp_path: Path, capsys
) -> None:
    """The bridge's candump log as recorded: the state at each frame is what the
    bridge believed ``--lead-ms`` before it. A frame replays bit for bit unless the
    run's own timing differed there (its state read at another moment than the
    tick's, which also changes every later warm start, or its command late)."""
    rc, out, err = _replay(capsys, run_dir / "bridge.log", tmp_path / "out")
    assert rc == 0, err
    rep = _cols(tmp_path / "out" / "candump_replay.parquet")
    run = _cols(run_dir / "ticks.parquet")
    row_of = {int(k) - 1: i for i, k in enumerate(run["bridge_tx_frames"]) if k > 0}
    bus_rep = np.stack([rep[f"bus_{f}"] for f in BUS_FIELDS], axis=1)
    bus_run = np.stack([run[f"bus_{f}"] for f in BUS_FIELDS], axis=1)
    same_history = True
    explained = checked = 0
    for j in np.flatnonzero(rep["stepped"]):
        i = row_of.get(int(j))
        # the warm state is the run's while every step so far had the run's bus vector
        same_history &= (
            i is not None and bool(run["stepped"][i]) and np.array_equal(bus_rep[j], bus_run[i])
        )
        if not rep["compared"][j]:
            continue
        if same_history and run["sent"][i] and run["margin_ms"][i] >= 0:
            checked += 1
            cmd = np.array([rep[f"cmd_{w}"][j] for w in WHEELS])
            assert np.array_equal(cmd, [run[f"cmd_{w}"][i] for w in WHEELS]), j
            assert rep["identical"][j], (j, [rep[f"framed_{w}"][j] for w in WHEELS])
        elif not rep["identical"][j]:
            explained += 1
    assert checked > 0
    res = json.loads((tmp_path / "out" / "candump_replay.json").read_text())
    assert res["differ"] <= explained + res["compared"] - checked
    assert "identical bit for bit" in out


def test_a_log_without_a_state_message_is_refused_in_one_line(
    run_dir: Path, tmp_path: Path, capsys
) -> None:
    log = tmp_path / "no_steering.log"
    _synthesise(run_dir, log, drop="SteeringState")
    rc, _, err = _replay(capsys, log, tmp_path / "out")
    lines = [x for x in err.splitlines() if x.startswith("ampc: error: ")]
    assert rc == 2 and len(lines) == 1, err
    assert lines[0].startswith(
        f"ampc: error: replay: --candump {log}: no sound SteeringState (0x203)"
    )
    for name in ("VehicleMotion", "WheelSpeeds", "VehicleAccel", "DriverDemand"):
        assert name in lines[0]
    assert not (tmp_path / "out" / "candump_replay.json").exists()


def test_what_is_not_a_candump_log_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    for name, text in (("notes.log", "hello\n"), ("binary.log", "\x00\xff" * 40)):
        path = tmp_path / name
        path.write_text(text)
        rc, _, err = _replay(capsys, path, tmp_path / "out")
        lines = [x for x in err.splitlines() if x.startswith("ampc: error: ")]
        assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
        assert lines[0].startswith(f"ampc: error: replay: --candump {path}: "), lines[0]


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["--candump", "x.log"], "--scenario"),
        (["RUN", "--candump", "x.log", "--scenario", SCENARIO], "--candump"),
        (["--candump", "x.log", "--scenario", "moon"], "--scenario"),
        (["--candump", "x.log", "--scenario", SCENARIO, "--rho-scale", "2"], "--candump"),
        (["RUN", "--scenario", SCENARIO], "--scenario"),
        ([], "replay"),
    ],
)
def test_candump_flags_are_checked_first(tmp_path: Path, capsys, argv, flag) -> None:
    argv = [str(tmp_path / "run") if a == "RUN" else a for a in argv]
    capsys.readouterr()
    rc = main(["replay", *argv, "--out", str(tmp_path / "out")])
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("ampc: error: ")]
    assert rc == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"ampc: error: {flag}"), lines[0]
