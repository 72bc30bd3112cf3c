"""Exception hierarchy of can_bridge, declared once.

Each Rust error kind maps to exactly one class here (the one
``From<Error> for PyErr`` in ``can_bridge/src/python/mod.rs``).
Every class also derives from the built-in exception users already catch.
"""

from __future__ import annotations

__all__ = [
    "CanBridgeError",
    "CommandError",
    "ConfigError",
    "StateError",
    "TransportError",
]


class CanBridgeError(Exception):
    """Base class of every error raised by can_bridge."""


class ConfigError(CanBridgeError, ValueError):
    """An invalid setting or channel string."""


class CommandError(CanBridgeError, ValueError):
    """A command refused by ``Bridge.set_command`` (NaN/inf, wrong length, stale seq)."""


class TransportError(CanBridgeError, OSError):
    """Opening, reading or writing the CAN transport failed."""


class StateError(CanBridgeError, RuntimeError):
    """A call that does not fit the bridge's life cycle (e.g. ``start`` twice)."""
