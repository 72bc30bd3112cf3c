"""The test suite's time budget: one factor scales every timeout a test sets.

Every test states its budget in seconds, the time it may take on an idle
2-core machine with the suite on two workers (``.ci/run``): a
``@pytest.mark.timeout(S)`` marker, else pytest's ``timeout`` setting in
pyproject.toml. ``tests/conftest.py`` multiplies each by :func:`timeout_scale`,
and a test's own deadlines (a subprocess's ``timeout=``, a wait for a line of
output) go through :func:`budget`, so that one number, ``AMPC_TEST_TIMEOUT_SCALE``
(default :data:`DEFAULT_SCALE`), stretches all of them on a busy machine.

The default covers two busy processes beside the suite on 2 cores (each
worker gets half a core: twice as slow) with a margin of 1.5; on a machine
shared with more work set, e.g., ``AMPC_TEST_TIMEOUT_SCALE=10``. A timeout
still catches a hang, only later. A deadline that is the behaviour under
test (a bridge's watchdog, a state timeout) is not a budget and is not scaled.
"""

from __future__ import annotations

import os

SCALE_ENV = "AMPC_TEST_TIMEOUT_SCALE"
"""The environment variable that sets the factor."""

DEFAULT_SCALE = 3.0
"""The factor when ``AMPC_TEST_TIMEOUT_SCALE`` is unset."""


def timeout_scale() -> float:
    """``AMPC_TEST_TIMEOUT_SCALE`` as a number >= 1 (default :data:`DEFAULT_SCALE`)."""
    raw = os.environ.get(SCALE_ENV, "").strip()
    if not raw:
        return DEFAULT_SCALE
    try:
        scale = float(raw)
    except ValueError:
        raise ValueError(f"{SCALE_ENV}={raw!r} must be a number >= 1") from None
    if not scale >= 1.0:
        raise ValueError(f"{SCALE_ENV}={raw!r} must be a number >= 1")
    return scale


def budget(seconds: float) -> float:
    """A deadline of ``seconds`` on an idle machine, stretched by :func:`timeout_scale`."""
    return seconds * timeout_scale()
