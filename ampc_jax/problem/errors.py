"""The problem model's error and warning types."""

from __future__ import annotations

__all__ = ["ProblemError", "ProblemWarning"]


class ProblemError(ValueError):
    """Invalid problem description; the message names the field and what was expected."""


class ProblemWarning(UserWarning):
    """A valid problem whose decomposition loses something (the message says what).

    Raised through :mod:`warnings`; the command line prints it as one line."""
