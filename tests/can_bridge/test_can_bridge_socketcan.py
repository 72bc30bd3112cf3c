"""SocketCAN: the frame conversion is unit-tested in Rust (``cargo test``,
``transport::socketcan``); here the runtime path runs where the kernel has
AF_CAN and a ``vcan0``, and otherwise must fail with a clear error."""

from __future__ import annotations

import socket

import pytest

import can_bridge

pytestmark = pytest.mark.timeout(60)


def _af_can_problem() -> str | None:
    if not hasattr(socket, "AF_CAN"):
        return "this Python has no socket.AF_CAN"
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as e:
        return f"socket(AF_CAN) failed: {e} (kernel without SocketCAN)"
    try:
        s.bind(("vcan0",))
    except OSError as e:
        return f"no vcan0 interface: {e}"
    finally:
        s.close()
    return None


PROBLEM = _af_can_problem()


@pytest.mark.skipif(
    PROBLEM is not None, reason=f"SocketCAN runtime test needs AF_CAN and vcan0: {PROBLEM}"
)
def test_socketcan_runtime_on_vcan0() -> None:
    from ampc_jax.testing.can_peers import CmdChecker

    rx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    rx.bind(("vcan0",))
    rx.settimeout(2)
    chk = CmdChecker()
    with can_bridge.Bridge("socketcan:vcan0", period_ms=20) as b:
        b.set_command((1.0, 2.0, 3.0, 4.0), seq=1)
        for _ in range(10):
            frame = rx.recv(16)
            can_id = int.from_bytes(frame[:4], "little")
            chk.add(can_id & 0x1FFFFFFF, bool(can_id & 0x80000000), frame[8 : 8 + frame[4]])
    rx.close()
    # the command reaches the bus: the frames sent while it was fresh carry it
    # (the later ones may be in Hold: the command is sent once and the default
    # hold_after is 150 ms, shorter than the 10 frames read here)
    active = [f for f in chk.frames if f["mode"] == "active"]
    assert active, chk.frames
    assert active[-1]["torques"] == (1.0, 2.0, 3.0, 4.0), chk.frames


@pytest.mark.skipif(PROBLEM is None, reason="this kernel supports SocketCAN")
def test_socketcan_without_kernel_support_is_a_clear_error() -> None:
    bridge = can_bridge.Bridge("socketcan:vcan0")
    with pytest.raises(can_bridge.TransportError, match="socketcan vcan0") as info:
        bridge.start()
    msg = str(info.value)
    assert "AF_CAN" in msg or "no such network interface" in msg
    assert not bridge.running
