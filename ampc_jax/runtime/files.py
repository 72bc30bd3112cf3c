"""I/O errors that name their file.

Rule: every I/O error the runtime and its command line report names the file
it happened on (and what was being done to it); reason: an error such as
``[Errno 27] File too large`` from a write to an open file, or from pyarrow,
names none, and a full disk then stops a run without saying which of its logs
could not be written. :func:`named` wraps an operation on one file and
re-raises any ``OSError`` as :class:`FileError`.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from typing import Any

__all__ = ["FileError", "named"]


class FileError(OSError):
    """An ``OSError`` on one file: ``str()`` is ``PATH: cannot DOING (reason)``.

    ``errno``, ``strerror`` and ``filename`` are the original error's (a
    ``FileError`` is an ``OSError``: callers that catch those still do)."""

    def __init__(self, path: str | os.PathLike[str], doing: str, exc: BaseException) -> None:
        errno = getattr(exc, "errno", None)
        strerror = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        super().__init__(errno, strerror, os.fspath(path))
        self.doing = doing

    def __str__(self) -> str:
        return f"{self.filename}: cannot {self.doing} ({self.strerror})"

    def __reduce__(self) -> Any:  # picklable across processes
        return (_rebuild, (self.filename, self.doing, self.errno, self.strerror))


def _rebuild(path: str, doing: str, errno: int | None, strerror: str) -> FileError:
    return FileError(path, doing, OSError(errno, strerror))


@contextlib.contextmanager
def named(path: str | os.PathLike[str], doing: str = "write") -> Iterator[None]:
    """Run the block; an ``OSError`` (pyarrow's I/O errors included) raised in it
    becomes a :class:`FileError` naming ``path`` (one already naming its file
    passes unchanged)."""
    try:
        yield
    except FileError:
        raise
    except OSError as exc:
        raise FileError(path, doing, exc) from exc
