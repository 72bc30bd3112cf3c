"""can_bridge: controller commands framed on CAN at a deterministic rate.

A Rust core (pyo3) runs a transmit thread on absolute monotonic deadlines
that sends the latest wheel-torque command every tick, AUTOSAR E2E Profile 1
protected, clamped, rate-limited and guarded by a command watchdog. Python
only hands over commands; the threads never take the GIL.

Example::

    import can_bridge

    with can_bridge.Bridge("slcan-pty:", period_ms=50) as bridge:
        print("peer connects to", bridge.pty_path)
        bridge.set_command((-10.0, -10.0, 12.0, 12.0), seq=1)
        state = bridge.latest_state()
"""

from __future__ import annotations

import os
from importlib import resources as _resources
from typing import Any

from ._can_bridge import (
    DEFAULT_CONFIG_TOML,
    Bridge,
    __version__,
    e2e_p01_crc,
    encode_message,
)
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
    "DEFAULT_CONFIG_TOML",
    "dbc_path",
    "default_config_path",
    "load_config",
    "e2e_p01_crc",
    "encode_message",
]


def dbc_path() -> str:
    """Return the installed path of the DBC file that describes every frame."""
    return str(_resources.files(__name__).joinpath("can_bridge.dbc"))


def default_config_path() -> str:
    """Return the installed path of ``vehicle.toml``: the actuator limits and
    timing the bridge uses by default, documented key by key."""
    return str(_resources.files(__name__).joinpath("vehicle.toml"))


def load_config(path: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Read a bridge configuration file (TOML) as the controller side sees it.

    ``None`` reads the shipped default. Keys missing from the file are *not*
    filled in here; pass the same file to ``Bridge(channel, config=path)`` to
    run the bridge with it (which also checks every value).
    """
    import tomllib

    with open(default_config_path() if path is None else path, "rb") as fh:
        return tomllib.load(fh)
