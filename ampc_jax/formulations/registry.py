"""The registry of formulations: one place where every formulation is known by name.

Each formulation class declares what it is (``info``, a
:class:`~ampc_jax.admm.core.FormulationInfo`: its number of rho, the rho
rule's basis, decomposed or not, its batched KKT form, whether it serves
closed loops, a learned start and a warm-start file) and is registered with
one line, ``register_formulation(Cls)``. Every list of formulations and every
choice between them elsewhere in the package (the closed loop's controllers,
a sweep's formulations, the CLI's ``--formulation`` choices, the tuned
parameters file) is read from here (:func:`formulation_names`,
:func:`formulation_info`), so a new formulation is its own file plus that
line.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

from ..admm.core import ADMMSolver, FormulationInfo
from ..problem.topology import Topology

__all__ = [
    "DEFAULT_FORMULATION",
    "FORMULATIONS",
    "FormulationInfo",
    "check_formulation",
    "formulation",
    "formulation_info",
    "formulation_names",
    "formulation_options",
    "register_formulation",
    "unregister_formulation",
]

DEFAULT_FORMULATION = "local_explicit"
"""The formulation every command and configuration uses unless told otherwise."""

_CLASSES: dict[str, type] = {}

FORMULATIONS = MappingProxyType(_CLASSES)
"""Name -> formulation class, in registration order (read-only; it follows
:func:`register_formulation`)."""


def register_formulation(cls: type, *, replace: bool = False) -> type:
    """Register ``cls`` under ``cls.info.name`` and return it (usable as a decorator).

    ``cls`` must be an :class:`~ampc_jax.admm.core.ADMMSolver` with a
    :class:`~ampc_jax.admm.core.FormulationInfo` as ``info`` and accept
    ``(topology, max_iter=..., anderson=...)``. A name already taken by another
    class is refused unless ``replace`` (ValueError naming ``formulation``)."""
    if not (isinstance(cls, type) and issubclass(cls, ADMMSolver)):
        raise TypeError(f"formulation: expected an ADMMSolver subclass, got {cls!r}")
    info = cls.__dict__.get("info")
    if not isinstance(info, FormulationInfo):
        raise TypeError(
            f"formulation: {cls.__name__} declares no FormulationInfo of its own as 'info'"
        )
    held = _CLASSES.get(info.name)
    if held is not None and held is not cls and not replace:
        raise ValueError(
            f"formulation: {info.name!r} is taken by {held.__name__}; pass replace=True "
            f"to replace it"
        )
    _CLASSES[info.name] = cls
    return cls


def unregister_formulation(name: str) -> None:
    """Remove ``name`` from the registry (KeyError if it is not there)."""
    del _CLASSES[name]


def formulation_info(which: Any) -> FormulationInfo:
    """The :class:`FormulationInfo` of a registered name, a formulation class or
    an instance (a wrapper such as ``LearnedStart``: its inner formulation's).
    ValueError naming ``formulation`` for an unknown name."""
    if isinstance(which, str):
        return check_formulation(which)
    inner = getattr(which, "inner", None)
    info = getattr(which, "info", None)
    if info is None and inner is not None:
        return formulation_info(inner)
    if not isinstance(info, FormulationInfo):
        raise TypeError(f"formulation: {which!r} declares no FormulationInfo")
    return info


def formulation_names(**traits: Any) -> tuple[str, ...]:
    """The registered names, in registration order, whose info has every given
    trait (``formulation_names(decomposed=True, closed_loop=True)``); a trait
    is a :class:`FormulationInfo` field."""
    fields = set(FormulationInfo.__dataclass_fields__)
    unknown = sorted(set(traits) - fields)
    if unknown:
        raise TypeError(
            f"formulation_names: unknown trait {unknown[0]!r}; expected some of {sorted(fields)}"
        )
    return tuple(
        name
        for name, cls in _CLASSES.items()
        if all(getattr(cls.info, k) == v for k, v in traits.items())
    )


def check_formulation(name: Any, *, field: str = "formulation", **traits: Any) -> FormulationInfo:
    """The info of the registered formulation ``name`` having ``traits``, or a
    ValueError naming ``field`` and the names that fit."""
    names = formulation_names(**traits)
    if not isinstance(name, str) or name not in names:
        raise ValueError(f"{field}: expected one of {list(names)}, got {name!r}")
    return _CLASSES[name].info


def formulation_options(name: str) -> tuple[str, ...]:
    """The static options the formulation ``name`` takes (its dataclass fields but
    ``topology``; ValueError naming ``formulation`` for an unknown name): what a
    caller may pass to :func:`formulation` for it (``"finish"`` only where it has
    an exact finish)."""
    check_formulation(name)
    fields = getattr(_CLASSES[name], "__dataclass_fields__", {})
    return tuple(f for f in fields if f != "topology")


def formulation(name: str, topology: Topology, **options: Any) -> ADMMSolver:
    """The formulation ``name`` for ``topology`` with its static ``options``
    (ValueError naming ``formulation`` for an unknown name)."""
    check_formulation(name)
    return _CLASSES[name](topology, **options)
