"""The rule of every command that writes an output directory or file (``--out``).

Rule: a command refuses an ``--out`` that exists and is not empty (a file
``--out`` that exists, for ``ampc export``) unless ``--force`` is given, with
exit 2 before anything compiles or opens; ``--force`` writes into it,
replacing the files of the names the command writes (``ampc run`` first
removes an earlier run's logs there, so that a run killed early leaves none
passing for its own). Reason: ``--out run`` given twice overwrote the first
run without a word. A sweep's directory is the exception: a rerun of the same
sweep resumes it, and the sweep itself refuses one of another sweep
(``docs/sweeps.md``).

Rule: a command that fails (a non-zero exit or an exception) removes what it
created and left empty: the empty files under the directories it created,
and those directories once empty; in an ``--out`` that existed before, only
the empty files at its top level that it wrote (new, or changed since it
claimed the directory), the directory itself kept. Reason: failed commands left empty
directories behind, and ``ampc run`` on a device that would not open a
0-byte ``bridge.log``.

``ampc`` calls :func:`begin` and :func:`finish` around each command
(:func:`~ampc_jax.cli.main`); the commands call :func:`claim_dir` or
:func:`claim_file` where they used to create their ``--out``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .args import output_dir

__all__ = ["FORCE_HELP", "add_force", "begin", "claim_dir", "claim_file", "finish"]

FORCE_HELP = (
    "write into an --out that exists and is not empty, replacing the files of the "
    "names this command writes (default: refuse it)"
)

_created: list[Path] = []
"""The directories the running command created, outermost first."""
_kept: list[tuple[Path, dict[str, tuple[int, int]]]] = []
"""The output directories it was given that existed before, each with its
top-level files' (size, mtime in ns) when it was claimed."""


def add_force(parser: Any, help: str = FORCE_HELP) -> None:
    """Add ``--force`` (store_true) to a command's parser."""
    parser.add_argument("--force", action="store_true", help=help)


def begin() -> None:
    """A command starts: it has created nothing yet."""
    _created.clear()
    _kept.clear()


def _entries(path: Path) -> list[str]:
    try:
        return sorted(os.listdir(path))
    except OSError:
        return []


def claim_dir(
    text: str,
    force: bool = False,
    *,
    flag: str = "--out",
    resumes: Callable[[Path], bool] | None = None,
) -> str | None:
    """Create the output directory ``text`` (and its missing parents, noted for
    :func:`finish`), or accept it: empty, ``force``, or holding what this
    command resumes (``resumes(path)`` true). Returns the error message, or None."""
    out = Path(text)
    if out.exists() and not out.is_dir():
        return f"{flag} {text}: exists and is not a directory"
    names = _entries(out) if out.is_dir() else []
    if names and not force and not (resumes is not None and resumes(out)):
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        return (
            f"{flag} {text}: the directory is not empty (it holds {shown}); choose another "
            f"{flag}, or give --force to write into it"
        )
    if out.is_dir():
        _kept.append((out, {n: _stamp(out / n) for n in names}))
    missing = []
    p = out.absolute()
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    problem = output_dir(text)
    if problem:
        return problem
    _created.extend(reversed(missing))
    return None


def claim_file(text: str, force: bool = False, *, flag: str = "--out") -> str | None:
    """Accept the output file ``text``: its directory exists, and the file does
    not or ``force``. Returns the error message, or None."""
    path = Path(text)
    if path.is_dir():
        return f"{flag} {text}: is a directory, expected a file to write"
    if path.parent and not path.parent.exists():
        return f"{flag} {text}: the directory {path.parent} does not exist"
    if path.exists() and not force:
        return (
            f"{flag} {text}: the file exists; choose another {flag}, or give --force to replace it"
        )
    return None


def finish(code: int) -> None:
    """A command ended with exit code ``code``: when it failed (non-zero), remove
    the empty files under the directories it created and those directories
    once empty, innermost first. Errors while removing are ignored (what
    cannot be removed stays)."""
    created, _created[:] = list(_created), []
    kept, _kept[:] = list(_kept), []
    if code == 0:
        return
    for d, before in kept:
        for name in _entries(d):
            if before.get(name) != _stamp(d / name):  # this command's
                _remove_if_empty(d / name)
    for top in reversed(created):
        if not top.is_dir():
            continue
        for root, _dirs, files in os.walk(top, topdown=False):
            for name in files:
                _remove_if_empty(Path(root) / name)
            try:
                os.rmdir(root)  # only when empty
            except OSError:
                pass


def _stamp(f: Path) -> tuple[int, int]:
    """(size, mtime in ns) of ``f`` without following a link; (-1, -1) if absent."""
    try:
        st = f.lstat()
    except OSError:
        return (-1, -1)
    return (st.st_size, st.st_mtime_ns)


def _remove_if_empty(f: Path) -> None:
    """Remove ``f`` if it is an empty regular file (not a link)."""
    try:
        if not f.is_symlink() and f.is_file() and f.lstat().st_size == 0:
            f.unlink()
    except OSError:
        pass
