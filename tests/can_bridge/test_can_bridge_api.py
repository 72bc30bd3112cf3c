"""Python API surface: configuration errors, exception classes, life cycle
(the stubs against the compiled module: test_can_bridge_stub.py)."""

from __future__ import annotations

import pathlib
import time

import pytest

import can_bridge

pytestmark = pytest.mark.timeout(60)


def test_exception_hierarchy() -> None:
    assert issubclass(can_bridge.ConfigError, ValueError)
    assert issubclass(can_bridge.CommandError, ValueError)
    assert issubclass(can_bridge.TransportError, OSError)
    assert issubclass(can_bridge.StateError, RuntimeError)
    for cls in (
        can_bridge.ConfigError,
        can_bridge.CommandError,
        can_bridge.TransportError,
        can_bridge.StateError,
    ):
        assert issubclass(cls, can_bridge.CanBridgeError)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"channel": "vcan0"}, "unknown transport"),
        ({"channel": "socketcand:localhost/can0"}, "PORT"),
        ({"channel": "slcan-pty:", "period_ms": 0}, "period_ms"),
        ({"channel": "slcan-pty:", "period_ms": float("nan")}, "period_ms"),
        ({"channel": "slcan-pty:", "torque_max_nm": 5000.0}, "DBC"),
        ({"channel": "slcan-pty:", "torque_max_nm": (1.0, 2.0)}, "exactly 4"),
        ({"channel": "slcan-pty:", "rise_nm_per_s": -1.0}, "rise_nm_per_s"),
        ({"channel": "slcan-pty:", "hold_after_ms": 600.0}, "hold_after"),
        ({"channel": "slcan:/dev/ttyX@12345"}, "serial speed"),
    ],
)
def test_config_errors(kwargs: dict, match: str) -> None:
    with pytest.raises(can_bridge.ConfigError, match=match):
        can_bridge.Bridge(**kwargs)


def test_lifecycle_and_context_manager() -> None:
    b = can_bridge.Bridge("slcan-pty:", period_ms=10)
    assert b.pty_path is None and not b.running
    with b as same:
        assert same is b and b.running
        assert pathlib.Path(b.pty_path).exists()
        with pytest.raises(can_bridge.StateError, match="already running"):
            b.start()
        time.sleep(0.1)
        s = b.stats()
        assert s["ticks"] >= 5 and s["tx_not_open"] >= 5  # no peer opened the channel
        # nothing reached the wire: no peer opened the channel
        assert s["safety_state"] == "not_open" and s["tx_mode"] == "safe"
    assert not b.running
    b.stop()  # idempotent
    assert "slcan-pty:" in repr(b) and b.channel == "slcan-pty:" and b.period_ms == 10.0
    # Restartable, with fresh counters.
    b.start()
    b.stop()
    assert b.stats()["ticks"] < 10


def test_gil_is_not_needed_by_the_tick_thread() -> None:
    """While the main thread holds the GIL in a pure-Python loop, the ticks go on."""
    b = can_bridge.Bridge("slcan-pty:", period_ms=10)
    with b:
        time.sleep(0.05)
        before = b.stats()["ticks"]
        end = time.perf_counter() + 0.5
        x = 0
        while time.perf_counter() < end:  # never releases the GIL voluntarily
            x += 1
        after = b.stats()["ticks"]
    # a tick thread that needed the GIL would make no tick at all while it is held
    # (its punctuality under load is bench/bench_can_bridge.py's)
    assert after - before >= 10
