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

from ..validation import check_count, check_non_negative, check_positive, check_relaxation

__all__ = [
    "enable_x64",
    "ANDERSON_MEMORIES",
    "PARAMS_HELP",
    "Parser",
    "add_output_flags",
    "add_params_flag",
    "add_solver_flags",
    "arg_type",
    "at_least_one",
    "fail",
    "flag_error",
    "non_negative_finite",
    "output_dir",
    "over_relaxation",
    "positive_finite",
    "progress_disabled",
    "with_params_file",
    "warnings_as_lines",
]


def enable_x64() -> None:
    """float64 for what the command computes (JAX's x64 mode), set before any array."""
    import jax

    jax.config.update("jax_enable_x64", True)


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
    """A flag's positive finite number (:func:`ampc_jax.validation.check_positive`)."""
    check_positive(value, "value")


def non_negative_finite(value: float) -> None:
    """A flag's finite number >= 0 (:func:`ampc_jax.validation.check_non_negative`)."""
    check_non_negative(value, "value")


def over_relaxation(value: float) -> None:
    """A flag's over-relaxation in (0, 2) (:func:`ampc_jax.validation.check_relaxation`)."""
    check_relaxation(value)


def at_least_one(value: int) -> None:
    """A flag's integer >= 1 (:func:`ampc_jax.validation.check_count`)."""
    check_count(value, "value")


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


# -- flag groups: the blocks every command that solves, or writes, repeats --------------
ANDERSON_MEMORIES = (0, 1, 2, 3)
"""The Anderson memories ``--anderson`` takes (:data:`~ampc_jax.admm.acceleration.ANDERSON_MAX`)."""


def add_solver_flags(
    p: argparse.ArgumentParser,
    *,
    relaxation: str | None = None,
    anderson: str | None = None,
    max_iter: str | None = None,
    max_iter_default: int | None = None,
) -> None:
    """``--relaxation`` (in (0, 2)), ``--anderson`` (0 to 3) and ``--max-iter`` (>= 1),
    each added when its help text is given (the command's own words and default;
    ``None`` as the parsed default means the command resolves it)."""
    if relaxation is not None:
        p.add_argument(
            "--relaxation", type=arg_type(over_relaxation), default=None, help=relaxation
        )
    if anderson is not None:
        p.add_argument(
            "--anderson", type=int, choices=ANDERSON_MEMORIES, default=None, help=anderson
        )
    if max_iter is not None:
        p.add_argument(
            "--max-iter", type=arg_type(at_least_one, int), default=max_iter_default, help=max_iter
        )


def add_params_flag(p: argparse.ArgumentParser, help: str = PARAMS_HELP) -> None:
    """``--params FILE``, a tuned-parameters file (:mod:`ampc_jax.io.params_file`)."""
    p.add_argument("--params", metavar="FILE", default=None, help=help)


def add_output_flags(
    p: argparse.ArgumentParser,
    *,
    float32: str | None = None,
    quiet: str | None = None,
    out: str | None = None,
    out_required: bool = False,
    out_help: str = "output directory",
) -> None:
    """``--float32`` (``float32``: what runs in float32), ``--quiet`` (its help) and
    ``--out`` (``out``: its default, or ``out_required``), each where given."""
    if float32 is not None:
        p.add_argument(
            "--float32",
            action="store_true",
            help=f"{float32} in float32 instead of float64 (default: float64)",
        )
    if quiet is not None:
        p.add_argument("--quiet", action="store_true", help=quiet)
    if out_required:
        p.add_argument("--out", required=True, help=f"{out_help} (required)")
    elif out is not None:
        p.add_argument("--out", default=out, help=f"{out_help} (default: {out})")
