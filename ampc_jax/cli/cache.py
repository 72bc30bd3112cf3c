"""Whether a compilation cache directory may be trusted.

Rule: ``ampc`` uses a persistent compilation cache only in a directory that no
one else can write, as ssh treats its keys (``StrictModes``): the directory
owned by this user (or root) and writable by no one else, and every directory
above it (of the path as given and of the one it resolves to, symlinks
followed) owned by this user or root and writable by no one else, unless it
is sticky (``/tmp``: others may not rename or remove what is ours there).
Reason: JAX loads compiled executables from the cache, and loading one may run
arbitrary code; whoever can write the directory (or swap it for another) can
put an executable there for this user to load. A cache that fails the rule is
turned off with one warning line (every program is then compiled afresh).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

__all__ = ["cache_problem"]


def _owner_ok(st: os.stat_result, me: int) -> bool:
    return st.st_uid in (me, 0)


def _describe(path: Path, st: os.stat_result, what: str) -> str:
    return f"{path} {what} (mode {stat.S_IMODE(st.st_mode):04o}, owner uid {st.st_uid})"


def cache_problem(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` must not hold a compilation cache, or None (see the module
    docstring). ``path`` exists (created by the caller)."""
    me = os.geteuid()
    given = Path(os.path.abspath(path))
    real = Path(os.path.realpath(path))
    try:
        st = os.stat(real)
    except OSError as exc:
        return f"{path}: cannot be read ({exc.strerror})"
    if not stat.S_ISDIR(st.st_mode):
        return f"{path} is not a directory"
    if st.st_uid != me:
        return _describe(real, st, "is owned by another user")
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return _describe(real, st, "is writable by others")
    # the directories above, as given (a symlink's own directory) and as resolved
    for parent in dict.fromkeys([*given.parents, *real.parents]):
        try:
            pst = os.stat(parent)
        except OSError as exc:
            return f"{parent}: cannot be read ({exc.strerror})"
        if not _owner_ok(pst, me):
            return _describe(parent, pst, "(above the cache) is owned by another user")
        sticky = bool(pst.st_mode & stat.S_ISVTX)
        if pst.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not sticky:
            return _describe(parent, pst, "(above the cache) is writable by others")
    return None
