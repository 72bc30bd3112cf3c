"""What every ``ampc`` command shares: argument types, one error format, warnings as lines.

Rule: a bad flag is reported once, as ``ampc: error: --flag: what was expected``
(exit code 2), whether argparse or the library found it; the library's field
names are translated to the flag's (:func:`flag_error`). Library warnings are
printed as ``ampc: warning: ...`` on one line, never with a source line.
"""

from __future__ import annotations

import argparse
import re
import sys
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

__all__ = [
    "PARAMS_HELP",
    "Parser",
    "arg_type",
    "at_least_one",
    "fail",
    "flag_error",
    "output_dir",
    "over_relaxation",
    "positive_finite",
    "progress_disabled",
    "with_params_file",
    "warnings_as_lines",
]


def fail(msg: str, code: int = 2) -> int:
    """Print ``ampc: error: msg`` on stderr, on one line (a message of several
    lines, e.g. a file reader's, is joined); return ``code`` (2: bad input)."""
    one = " ".join(line.strip() for line in str(msg).splitlines() if line.strip())
    print(f"ampc: error: {one}", file=sys.stderr)
    return code


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose usage errors read ``ampc: error: --flag: message``."""

    def error(self, message: str) -> NoReturn:
        m = re.match(r"argument ([^:]+): (.*)", message, re.S)
        if m:
            flag = m.group(1).split("/")[-1]
            message = f"{flag}: {m.group(2)}"
        self.print_usage(sys.stderr)
        self.exit(2, f"ampc: error: {message}\n")


def arg_type(check: Callable[[Any], Any], kind: type = float) -> Callable[[str], Any]:
    """An argparse ``type``: parse with ``kind``, then ``check`` (its ValueError,
    minus the field name it starts with, becomes the usage error)."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an integer' if kind is int else 'a number'}, got {text!r}"
            ) from None
        try:
            check(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[-1]) from None
        return value

    parse.__name__ = kind.__name__  # argparse's "invalid <name> value" fallback
    return parse


def positive_finite(value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"value: expected a positive finite number, got {value!r}")


def over_relaxation(value: float) -> None:
    if not (np.isfinite(value) and 0.0 < value < 2.0):
        raise ValueError(f"relaxation: expected a value in (0, 2), got {value!r}")


def at_least_one(value: int) -> None:
    if value < 1:
        raise ValueError(f"value: expected an integer >= 1, got {value!r}")


def flag_error(exc: Exception, flags: Mapping[str, str]) -> str:
    """The message of a library error that starts with a field name (``rho_scale: ...``),
    with the field replaced by its flag (``--rho-scale: ...``); any other message
    as it is (``ampc: error: message``, never a flag made up from its first word)."""
    text = str(exc)
    field, sep, rest = text.partition(": ")
    if sep and field in flags:
        return f"{flags[field]}: {rest}"
    return text


def output_dir(text: str) -> str | None:
    """Create the output directory ``text``; an error message if that fails (else None)."""
    import os

    out = Path(text)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"--out {text}: cannot create the output directory ({exc.strerror or exc})"
    if not os.access(out, os.W_OK | os.X_OK):
        return f"--out {text}: the output directory is not writable"
    return None


def progress_disabled(quiet: bool) -> bool | None:
    """tqdm's ``disable``: off with ``--quiet``; otherwise None, which shows the
    bars on a terminal only (redirected output gets no carriage-return debris)."""
    return True if quiet else None


@contextmanager
def warnings_as_lines() -> Iterator[None]:
    """Library warnings inside the block printed as ``ampc: warning: ...`` lines."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    seen = set()
    for w in caught:
        text = str(w.message)
        if text not in seen:
            seen.add(text)
            print(f"ampc: warning: {text}", file=sys.stderr)


def with_params_file(config: Any, path: str | None, keep: tuple[str, ...] = ()) -> Any:
    """``config`` with a tuned-parameters file's numbers applied (``--params``; none:
    ``config`` itself); ``keep``: the options given by explicit flags, which win.
    ValueError ``--params PATH: field: message`` on a bad file."""
    if path is None:
        return config
    from ..io.params_file import apply_params, read_params

    try:
        return apply_params(config, read_params(path), keep=keep)
    except ValueError as exc:
        raise ValueError(f"--params {path}: {exc}") from None


PARAMS_HELP = (
    "a tuned-parameters file (ampc tune's params.json): its solver.rho_scale, "
    "solver.relaxation and settings are applied first, then the explicit flags, which "
    "win over it (default: none)"
)
"""The help of ``--params`` for the closed-loop commands."""
