"""The optional modules of the deployment commands, checked before anything compiles.

Rule: ``ampc run``, ``plant``, ``export`` and ``replay`` import every optional
module they will need before anything else (no JAX compile, no channel, no
output directory) and, where one is missing, exit 2 naming each missing
module and the one install command, run from the repository root, that
brings them all; reason: without the runtime extra ``ampc run --with-plant``
compiled for 80 s before the plant died on a ``ModuleNotFoundError``
traceback, ``ampc export`` ended in an uncaught ``ImportError``, and the
extra alone does not bring the bridge (a Rust extension built from
``./can_bridge``; pip cannot name a local path in an extra).
"""

from __future__ import annotations

import importlib

__all__ = ["BRIDGE", "BUS", "EXPORT", "PLANT", "missing_message", "missing_modules"]

RUNTIME_EXTRA = "-e '.[runtime]'"
"""pip's argument for pyproject.toml's ``runtime`` extra (python-can, cantools,
autosar-e2e, pyserial, flatbuffers) with the package itself, editable."""

BRIDGE_DIR = "./can_bridge"
"""pip's argument for the bridge (maturin builds it; needs a Rust toolchain)."""

WHAT = {
    "can_bridge": "the CAN bridge, built from ./can_bridge",
    "can": "python-can",
    "cantools": "the DBC codec",
    "e2e": "autosar-e2e",
    "serial": "pyserial",
    "flatbuffers": "jax.export's serialization",
}
"""Module -> what it is, or the distribution that installs it."""

BRIDGE = ("can_bridge",)
BUS = ("can_bridge", "can", "cantools", "e2e")
"""What reading a bus log needs (``ampc replay``): the bridge's DBC, python-can's
candump reader, cantools, autosar-e2e."""
PLANT = (*BUS, "serial")
"""``ampc plant`` (and ``ampc run --with-plant``): also python-can's SLCAN over pyserial."""
EXPORT = ("flatbuffers",)
"""``ampc export`` and ``ampc run --artefact``: jax.export's serialization."""


def missing_modules(modules: tuple[str, ...]) -> list[str]:
    """The modules of ``modules`` that do not import (in order, once each)."""
    out = []
    for name in dict.fromkeys(modules):
        try:
            importlib.import_module(name)
        except ImportError:
            out.append(name)
    return out


def missing_message(command: str, modules: tuple[str, ...]) -> str | None:
    """``None`` when every module of ``modules`` imports; else the error line of
    ``ampc COMMAND``: the missing modules and the one pip command that installs
    them from the repository root."""
    gone = missing_modules(modules)
    if not gone:
        return None
    args = ([BRIDGE_DIR] if "can_bridge" in gone else []) + (
        [RUNTIME_EXTRA] if any(m != "can_bridge" for m in gone) else []
    )
    names = ", ".join(f"{m} ({WHAT.get(m, m)})" for m in gone)
    rust = (
        "; can_bridge builds with a Rust toolchain (https://rustup.rs)"
        if "can_bridge" in gone
        else ""
    )
    return (
        f"{command}: missing module{'s' if len(gone) > 1 else ''} {names}; from the repository "
        f"root run: python -m pip install {' '.join(args)}{rust}"
    )
