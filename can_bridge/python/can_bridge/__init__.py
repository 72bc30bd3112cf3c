"""can_bridge: controller commands framed on CAN at a deterministic rate.

A Rust core (pyo3) runs a transmit thread on absolute monotonic deadlines
that sends the latest wheel-torque command every tick, AUTOSAR E2E Profile 1
protected, clamped, rate-limited and guarded by a command watchdog. Python
only hands over commands; the threads never take the GIL.

Example::

    import can_bridge

    with can_bridge.Bridge("slcan-pty:", period_ms=50) as bridge:
        print("peer connects to", bridge.pty_path)
        bridge.set_command((10.0, 10.0, 12.0, 12.0), seq=1)
        state = bridge.latest_state()
"""

from __future__ import annotations

from importlib import resources as _resources

from ._can_bridge import Bridge, __version__, e2e_p01_crc, encode_message
from ._errors import (
    CanBridgeError,
    CommandError,
    ConfigError,
    StateError,
    TransportError,
)

__all__ = [
    "Bridge",
    "CanBridgeError",
    "CommandError",
    "ConfigError",
    "StateError",
    "TransportError",
    "__version__",
    "dbc_path",
    "e2e_p01_crc",
    "encode_message",
]


def dbc_path() -> str:
    """Return the installed path of the DBC file that describes every frame."""
    return str(_resources.files(__name__).joinpath("can_bridge.dbc"))
