"""End to end over a pseudo-terminal: the bridge plays an SLCAN adapter,
python-can's ``slcan`` interface is the peer, cantools decodes, autosar-e2e
checks every CRC and counter."""

from __future__ import annotations

import math
import threading
import time

import can
import e2e.p01
import pytest

import can_bridge
from ampc_jax.testing.can_peers import (
    DRIVER,
    MOTION,
    STEER,
    CmdChecker,
    db,
    recv_cmds,
    recv_until,
    send_sensors,
    slcan_peer,
    state_message,
)

pytestmark = pytest.mark.timeout(60)


def test_frames_are_valid_and_follow_the_command() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=20)
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        bridge.set_command((-10.0, -20.5, 30.25, 0.0), seq=1)
        seq = 1
        frames = []
        for _ in range(30):
            seq += 1
            bridge.set_command((-10.0, -20.5, 30.25, 0.0), seq=seq)
            frames += recv_cmds(bus, chk, 1)
        active = [f for f in frames if f["mode"] == "active"]
        assert len(active) >= 25
        # Sent at the DBC's 2 Nm resolution (round half to even): -20.5 -> -20, 30.25 -> 30.
        assert all(f["torques"] == (-10.0, -20.0, 30.0, 0.0) for f in active)
        # The peer can read a frame before the transmit thread has counted it
        # (the counter follows the write): let the tick finish before reading stats.
        time.sleep(0.05)
        s = bridge.stats()
        assert s["tx_frames"] >= 30 and s["tx_errors"] == 0
        assert s["safety_state"] == "active"
        assert abs(s["mean_period_ms"] - 20.0) < 2.0  # precision is the bench's job


def test_clamping_to_actuator_limits_and_rate_limit() -> None:
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=20,
        torque_min_nm=(-100.0, -100.0, -50.0, -50.0),
        torque_max_nm=(100.0, 100.0, 50.0, 50.0),
        rise_nm_per_s=500.0,  # 10 Nm per 20 ms tick
        release_nm_per_s=500.0,
        hold_after_ms=1000,
        safe_after_ms=3000,
        fault_after_ms=4000,
    )
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        bridge.set_command((500.0, -500.0, 30.0, -1000.0), seq=1)
        frames = recv_until(bus, chk, lambda f: f["torques"] == (100.0, -100.0, 30.0, -50.0))
        active = [f for f in frames if f["mode"] == "active"]
        assert len(active) >= 5  # 10 ticks of ramp; a loaded peer may miss a few (age rule)
        for a, b in zip(active, active[1:], strict=False):
            assert all(abs(y - x) <= 10.0 for x, y in zip(a["torques"], b["torques"], strict=False))
        for f in frames:
            assert (
                abs(f["torques"][0]) <= 100
                and abs(f["torques"][2]) <= 50
                and abs(f["torques"][3]) <= 50
            )


def test_nan_and_inf_are_refused_and_never_reach_a_frame() -> None:
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=20,
        hold_after_ms=1000,
        safe_after_ms=3000,
        fault_after_ms=4000,
    )
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        bridge.set_command((-6.0, -6.0, 6.0, 6.0), seq=1)
        for seq, bad in enumerate(
            [
                (math.nan, 0, 0, 0),
                (0, math.inf, 0, 0),
                (0, 0, -math.inf, 0),
                (0, 0, 0, float("nan")),
            ],
            start=2,
        ):
            with pytest.raises(can_bridge.CommandError, match="not finite"):
                bridge.set_command(bad, seq=seq)
        with pytest.raises(ValueError, match="exactly 4"):
            bridge.set_command((1.0, 2.0, 3.0), seq=10)
        with pytest.raises(ValueError, match="not a string"):
            bridge.set_command("1234", seq=11)
        with pytest.raises(can_bridge.CommandError, match="not newer"):
            bridge.set_command((1.0,) * 4, seq=1)
        with pytest.raises(can_bridge.CommandError, match="seq must be an integer"):
            bridge.set_command((1.0,) * 4, seq=-1)
        frames = recv_cmds(bus, chk, 15)
        assert frames[-1]["torques"] == (-6.0, -6.0, 6.0, 6.0) and frames[-1]["mode"] == "active"
        # Decoded torques are raw integers times 0.5 Nm: always finite, so a
        # refused value that leaked would show as another number (a saturating
        # NaN -> 0 cast, or +-1000 for inf). Every frame carries the one accepted
        # command, or zeros in Safe before it arrived.
        for f in frames:
            want = (-6.0, -6.0, 6.0, 6.0) if f["mode"] == "active" else (0.0,) * 4
            assert f["mode"] in ("active", "safe") and f["torques"] == want, frames


def test_watchdog_hold_safe_latched_fault_and_reset() -> None:
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=20,
        hold_after_ms=70,
        safe_after_ms=150,
        fault_after_ms=400,
    )
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        seq = 0
        for _ in range(8):  # a live controller
            seq += 1
            bridge.set_command((-40.0, -40.0, 20.0, 20.0), seq=seq)
            recv_cmds(bus, chk, 1)
        # Silence: hold, then safe, then fault.
        frames = recv_until(bus, chk, lambda f: f["mode"] == "fault")
        modes = [f["mode"] for f in frames]
        first = {m: modes.index(m) for m in ("hold", "safe", "fault")}
        assert first["hold"] < first["safe"] < first["fault"]
        for f in frames[first["hold"] : first["safe"]]:
            assert f["mode"] == "hold" and f["torques"] == (-40.0, -40.0, 20.0, 20.0)
        # Released at the safe rate (8000 Nm/s: 160 Nm per tick, here one tick).
        for f in frames[first["safe"] :]:
            assert f["torques"] == (0.0, 0.0, 0.0, 0.0)
        # Safe lasted about (400 - 150) ms of ticks.
        assert 8 <= first["fault"] - first["safe"] <= 16
        # Latched: a fresh command does not clear it ...
        seq += 1
        bridge.set_command((-40.0, -40.0, 20.0, 20.0), seq=seq)
        assert all(f["mode"] == "fault" for f in recv_cmds(bus, chk, 5))
        assert bridge.stats()["safety_state"] == "fault"
        # ... only reset_fault does; then Safe until a newer command, then Active.
        bridge.reset_fault()
        recv_until(bus, chk, lambda f: f["mode"] == "safe")
        seq += 1
        bridge.set_command((-40.0, -40.0, 20.0, 20.0), seq=seq)
        f = recv_until(bus, chk, lambda f: f["mode"] == "active")[-1]
        assert f["torques"] == (-40.0, -40.0, 20.0, 20.0)


def test_received_state_checks_crc_counter_and_timeout() -> None:
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=20, state_timeout_ms=200)
    with slcan_peer(bridge) as bus:
        st = bridge.latest_state()
        assert st["valid"] is False and st["long_speed_mps"] is None
        for c in range(3):
            send_sensors(bus, c)
            time.sleep(0.02)
        time.sleep(0.1)
        st = bridge.latest_state()
        assert st["valid"] is True
        assert st["long_speed_mps"] == pytest.approx(12.34)
        assert st["lat_speed_mps"] == pytest.approx(-0.56)
        assert st["yaw_rate_radps"] == pytest.approx(0.123)
        assert st["steering_angle_rad"] == pytest.approx(0.0456)
        assert st["wheel_speeds_radps"] == pytest.approx((35.1, 35.2, 39.9, 40.3))
        assert st["long_accel_mps2"] == pytest.approx(-3.21)
        assert st["road_friction"] == pytest.approx(0.35)
        # Bad CRC: rejected and counted, value unchanged.
        bus.send(state_message("VehicleMotion", {**MOTION, "LongSpeed": 89.0}, 3, corrupt=True))
        # Counter 2 again with other data (a second sender): rejected and counted.
        bus.send(state_message("VehicleMotion", {**MOTION, "LongSpeed": 88.0}, 2))
        # Counter 15 is invalid in Profile 1.
        bus.send(state_message("VehicleMotion", {**MOTION, "LongSpeed": 87.0}, 15))
        time.sleep(0.15)
        s = bridge.stats()
        assert s["rx_crc_errors"] == 1
        assert s["rx_counter_errors"] == 2
        assert bridge.latest_state()["long_speed_mps"] == pytest.approx(12.34)
        # Good frame with the next counter is accepted (10 m/s: within the speed's
        # 20 m/s^2 of the last believed 12.34 over the quarter second since it).
        bus.send(state_message("VehicleMotion", {**MOTION, "LongSpeed": 10.0}, 3))
        time.sleep(0.1)
        assert bridge.latest_state()["long_speed_mps"] == pytest.approx(10.0)
        # It stops arriving: invalid.
        time.sleep(0.3)
        st = bridge.latest_state()
        assert st["valid"] is False and st["age_ms"] > 200
        assert bridge.stats()["state_valid"] is False


def _e2e_frame(name: str, values: dict[str, float], counter: int) -> can.Message:
    """Framed by cantools from the DBC at ``can_bridge.dbc_path()`` (ampc_jax.testing.can_peers.db)
    and protected by autosar-e2e (E2E Profile 1 CRC over the Data ID, the
    counter in the low nibble of byte 1)."""
    msg = db().get_message_by_name(name)
    data = bytearray(msg.encode({"CRC": 0, "Counter": counter, **values}))
    did = int(msg.dbc.attributes["E2EDataID"].value)
    e2e.p01.e2e_p01_protect(data, did, increment_counter=False)
    assert e2e.p01.e2e_p01_check(data, did)
    return can.Message(arbitration_id=msg.frame_id, is_extended_id=False, data=data)


def test_accel_and_driver_demand_are_received_and_required() -> None:
    """VehicleAccel and DriverDemand, encoded by cantools from
    ``can_bridge.dbc_path()`` and E2E-protected by autosar-e2e, come out of
    ``latest_state()`` decoded; the state is valid only with both sound."""
    accel = {"LongAccel": -3.21, "LatAccel": 7.5}
    driver = {"DriverTorque": -1234.5, "SetSpeed": 17.25, "RoadFriction": 0.35}
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=20, state_timeout_ms=200)
    with slcan_peer(bridge) as bus:
        # Everything but DriverDemand: invalid, and the reason says which.
        for c in range(3):
            send_sensors(bus, c, skip=("VehicleAccel", "DriverDemand"))
            bus.send(_e2e_frame("VehicleAccel", accel, c))
            time.sleep(0.02)
        time.sleep(0.05)
        st = bridge.latest_state()
        assert st["valid"] is False
        assert st["reason"] == "DriverDemand: no data"
        assert st["status"]["DriverDemand"] == "no data"
        assert st["status"]["VehicleAccel"] == "ok"
        assert st["driver_torque_nm"] is None and st["age_ms"] is None
        assert st["long_accel_mps2"] == pytest.approx(-3.21)
        assert st["lat_accel_mps2"] == pytest.approx(7.5)
        # All five: valid, with the new values decoded.
        for c in range(3, 7):
            send_sensors(bus, c, skip=("VehicleAccel", "DriverDemand"))
            bus.send(_e2e_frame("VehicleAccel", accel, c))
            bus.send(_e2e_frame("DriverDemand", driver, c))
            time.sleep(0.02)
        time.sleep(0.05)
        st = bridge.latest_state()
        assert st["valid"] is True, st
        assert st["reason"] is None
        assert set(st["status"]) == {
            "VehicleMotion",
            "WheelSpeeds",
            "SteeringState",
            "VehicleAccel",
            "DriverDemand",
        }
        assert st["long_accel_mps2"] == pytest.approx(-3.21)
        assert st["lat_accel_mps2"] == pytest.approx(7.5)
        assert st["driver_torque_nm"] == pytest.approx(-1234.5)
        assert st["set_speed_mps"] == pytest.approx(17.25)
        assert st["road_friction"] == pytest.approx(0.35)
        # A corrupt VehicleAccel (CRC broken): not used; one error in the
        # state machine's window is tolerated, the second is not.
        for c in (7, 8):
            bad = _e2e_frame("VehicleAccel", {"LongAccel": 9.0, "LatAccel": 9.0}, c)
            bad.data[3] ^= 0x40
            send_sensors(bus, c, skip=("VehicleAccel",))
            bus.send(bad)
            time.sleep(0.05)
            st = bridge.latest_state()
            assert st["valid"] is (c == 7), st
            assert st["long_accel_mps2"] == pytest.approx(-3.21)
        assert st["reason"] == "VehicleAccel: wrong crc"
        assert bridge.stats()["rx_crc_errors"] == 2
        # A RoadFriction outside the DBC's [0.05|2]: implausible, not used.
        for c in (9, 10):
            send_sensors(bus, c, skip=("DriverDemand",))
            bus.send(
                state_message("DriverDemand", {**DRIVER, "RoadFriction": 0.02}, c, strict=False)
            )
            time.sleep(0.05)
        st = bridge.latest_state()
        assert st["valid"] is False
        assert "DriverDemand: implausible" in st["reason"], st
        assert st["road_friction"] == pytest.approx(0.35)
        assert "RoadFriction" in bridge.stats()["last_rx_error"]


def test_stop_sends_safe_frames_before_closing() -> None:
    bridge = can_bridge.Bridge(
        "slcan-pty:",
        period_ms=20,
        stop_safe_frames=3,
        hold_after_ms=1000,
        safe_after_ms=3000,
        fault_after_ms=4000,
    )
    chk = CmdChecker()
    bridge.start()
    bus = can.Bus(interface="slcan", channel=bridge.pty_path, sleep_after_open=0, bitrate=500000)
    try:
        bridge.set_command((-60.0, -60.0, 60.0, 60.0), seq=1)
        recv_until(bus, chk, lambda f: f["mode"] == "active")
        stopper = threading.Thread(target=bridge.stop)
        stopper.start()
        tail = []
        end = time.monotonic() + 5
        while time.monotonic() < end and len(tail) < 60:
            try:
                m = bus.recv(timeout=0.2)
            except can.CanError:
                break
            if m is None:
                if not stopper.is_alive():
                    break
                continue
            tail.append(chk.add(m.arbitration_id, m.is_extended_id, bytes(m.data)))
        stopper.join(5)
        assert not stopper.is_alive()
    finally:
        # The pty is gone once the bridge has stopped: python-can's closing "C" fails.
        try:
            bus.shutdown()
        except can.CanError:
            pass
    assert not bridge.running
    assert len(tail) >= 3
    assert [f["mode"] for f in tail[-3:]] == ["safe"] * 3
    assert all(f["torques"] == (0.0,) * 4 for f in tail[-3:])
    assert all(f["mode"] == "active" for f in tail[:-3])
    # Stats stay readable after stop; a second stop is a no-op.
    assert bridge.stats()["running"] is False
    bridge.stop()


def test_candump_log_is_readable_by_python_can(tmp_path) -> None:
    log = tmp_path / "bridge.log"
    bridge = can_bridge.Bridge("slcan-pty:", period_ms=20, log_path=log)
    chk = CmdChecker()
    with slcan_peer(bridge) as bus:
        bridge.set_command((1.0, 2.0, 3.0, 4.0), seq=1)
        recv_cmds(bus, chk, 5)
        bus.send(state_message("SteeringState", STEER, 0))
        time.sleep(0.1)
    msgs = list(can.CanutilsLogReader(str(log)))
    tx = [m for m in msgs if not m.is_rx]
    rx = [m for m in msgs if m.is_rx]
    assert len(tx) >= 5
    assert [bytes(m.data) for m in tx[: len(chk.raw)]] == chk.raw[: len(tx)]
    logged = CmdChecker()
    for m in tx:
        logged.add(m.arbitration_id, m.is_extended_id, bytes(m.data))
    assert len(rx) == 1 and rx[0].arbitration_id == 0x203
    assert bytes(rx[0].data) == bytes(state_message("SteeringState", STEER, 0).data)
    assert abs(msgs[0].timestamp - time.time()) < 60
