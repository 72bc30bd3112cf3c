"""``slcan:PATH`` (host role, raw termios) against a pty standing in for a
serial SLCAN adapter: the test reads and writes the adapter's side itself."""

from __future__ import annotations

import os
import select
import time

import pytest

import can_bridge
from ampc_jax.testing.budget import budget
from ampc_jax.testing.can_fault_peers import SerialAdapter
from ampc_jax.testing.can_peers import STEER, CmdChecker, protect

pytestmark = pytest.mark.timeout(60)


class LineReader:
    """CR-terminated lines from the adapter side of the pty."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buf = b""

    def lines(self, n: int, timeout: float = 5.0) -> list[bytes]:
        end = time.monotonic() + timeout
        while self.buf.count(b"\r") < n and time.monotonic() < end:
            r, _, _ = select.select([self.fd], [], [], 0.05)
            if r:
                try:
                    self.buf += os.read(self.fd, 4096)
                except OSError:
                    break
        parts = self.buf.split(b"\r")
        out, rest = parts[: min(n, len(parts) - 1)], parts[min(n, len(parts) - 1) :]
        self.buf = b"\r".join(rest)
        return out


def _parse_slcan(line: bytes) -> tuple[int, bool, bytes]:
    """The adapter side's own SLCAN parsing (no code shared with the bridge)."""
    text = line.decode("ascii")
    ext = text[0] == "T"
    n = 8 if ext else 3
    can_id = int(text[1 : 1 + n], 16)
    dlc = int(text[1 + n])
    data = bytes.fromhex(text[2 + n : 2 + n + 2 * dlc])
    assert len(text) == 2 + n + 2 * dlc
    return can_id, ext, data


def test_serial_adapter_init_frames_and_receive() -> None:
    adapter = SerialAdapter()
    try:
        bridge = can_bridge.Bridge(f"slcan:{adapter.path}@115200", period_ms=20, bitrate=250000)
        bridge.start()
        try:
            # Handshake: a CR ending any half line, close, version query, bit rate, open.
            assert adapter.commands[:5] == [b"", b"C", b"V", b"S5", b"O"], adapter.commands
            bridge.set_command((-8.0, 0.0, -8.0, 100.0), seq=1)
            time.sleep(0.2)
            chk = CmdChecker()
            frames = [chk.add(*_parse_slcan(line)) for _, line in adapter.lines]
            active = [f for f in frames if f["mode"] == "active"]
            assert active and active[-1]["torques"] == (-8.0, 0.0, -8.0, 100.0)
            # The adapter reports a received frame (lower-case hex, with a Z1 timestamp).
            # one frame per 20 ms cycle (faster ones are a fault: the pace rule)
            for c in range(3):
                data = protect("SteeringState", STEER, c)
                adapter.send_line(b"t2034" + data.hex().encode() + b"1A2B\r")
                time.sleep(0.02)
            end = time.monotonic() + budget(2)
            while bridge.latest_state()["steering_angle_rad"] is None and time.monotonic() < end:
                time.sleep(0.02)
            assert bridge.latest_state()["steering_angle_rad"] == pytest.approx(0.0456)
            # Garbage from the adapter is counted, never fatal.
            adapter.send_line(b"\x00\xffnot slcan\rt12\r")
            time.sleep(0.1)
            assert bridge.stats()["rx_malformed"] >= 2
        finally:
            bridge.stop()
        time.sleep(0.1)
        assert adapter.commands[-1] == b"C"  # closes the adapter's channel on stop
        last = CmdChecker()
        tail = [last.add(*_parse_slcan(x))["mode"] for _, x in adapter.lines[-3:]]
        assert tail == ["safe"] * 3
    finally:
        adapter.close()


def test_missing_serial_device_is_a_transport_error() -> None:
    bridge = can_bridge.Bridge("slcan:/dev/does-not-exist-can@115200")
    with pytest.raises(can_bridge.TransportError, match="does-not-exist-can") as info:
        bridge.start()
    assert isinstance(info.value, OSError)
    assert not bridge.running
