"""The checks every setting of the package goes through, written once.

Each ``check_*`` takes the value and the name of its field (or flag), returns
the value in its canonical type, and otherwise raises a ValueError that starts
with that name: ``name: expected ..., got ...`` (the CLI replaces a field's
name by its flag, :func:`ampc_jax.cli.args.flag_error`). NumPy scalars count
as numbers; booleans are never numbers. Traced values (inside ``jit``) are not
checked. This module imports nothing of the package.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

import numpy as np

__all__ = [
    "check_choice",
    "check_count",
    "check_finite",
    "check_flag",
    "check_non_negative",
    "check_positive",
    "check_relaxation",
    "check_values",
    "is_number",
]


def is_number(value: Any) -> bool:
    """A real number: Python's or NumPy's (a 0-d array of a real dtype too), never a bool."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (int, float, np.integer, np.floating)):
        return True
    kind = getattr(getattr(value, "dtype", None), "kind", None)
    return getattr(value, "shape", None) == () and kind in ("i", "u", "f")


def check_count(value: Any, name: str = "iterations", low: int = 1) -> int:
    """A static count (iterations, cases, steps): an integer >= ``low``."""
    if (
        isinstance(value, (bool, np.bool_))
        or not isinstance(value, (int, np.integer))
        or value < low
    ):
        raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
    return int(value)


def check_finite(value: Any, name: str) -> float:
    """A finite real number."""
    if not is_number(value) or not np.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return float(value)


def check_positive(value: Any, name: str) -> float:
    """A positive finite number (a tolerance, a learning rate, a scale)."""
    if not is_number(value) or not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected a positive finite number, got {value!r}")
    return float(value)


def check_non_negative(value: Any, name: str) -> float:
    """A finite number >= 0 (a weight that may switch its term off)."""
    if not is_number(value) or not (np.isfinite(value) and value >= 0):
        raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")
    return float(value)


def check_relaxation(value: Any, name: str = "relaxation") -> float:
    """An over-relaxation alpha in the open interval (0, 2) (1 is the paper's iteration)."""
    if not is_number(value) or not 0.0 < float(value) < 2.0:
        raise ValueError(f"{name}: expected a value in (0, 2), got {value!r}")
    return float(value)


def check_values(value: Any, name: str, low: float, high: float, *, open_low: bool = True) -> None:
    """Numbers (a scalar or an array, checked elementwise), finite, above ``low``
    (or at it, ``open_low=False``) and below ``high`` (where finite)."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers, got {value!r:.80}") from None
    if isinstance(value, bool) or a.dtype == bool:
        raise ValueError(f"{name}: expected numbers, got {value!r}")
    ok = np.isfinite(a) & (a < high) & ((a > low) if open_low else (a >= low))
    if not np.all(ok):
        side = ">" if open_low else ">="
        top = f" and < {high:g}" if np.isfinite(high) else ""
        raise ValueError(f"{name}: expected finite values {side} {low:g}{top}, got {value!r:.80}")


def check_flag(value: Any, name: str) -> bool:
    """True or False (NumPy's bool too)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, got {value!r}")
    return bool(value)


def check_choice(value: Any, name: str, choices: Collection[Any]) -> Any:
    """One of ``choices`` (listed in the message)."""
    try:
        ok = value in choices
    except TypeError:  # an unhashable value against a set
        ok = False
    if not ok:
        raise ValueError(f"{name}: expected one of {list(choices)}, got {value!r}")
    return value
