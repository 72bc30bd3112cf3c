"""The test suite's pytest plugin (``tests/conftest.py`` loads it).

* Timeouts from one budget: every test's timeout, its ``@pytest.mark.timeout(S)``
  marker or else pytest's ``timeout`` setting (pyproject.toml, ``--timeout``,
  ``PYTEST_TIMEOUT``), is multiplied by :func:`~.budget.timeout_scale`
  (``AMPC_TEST_TIMEOUT_SCALE``, default 3; :mod:`~.budget` says why).
* Failures as they happen: a failed or erroring test is reported at once, as
  ``FAILED <node id> - <reason>`` on a line of its own, not only in the summary
  at the end, so that a slow run stopped half way still says what failed.
  Under pytest-xdist the controller prints it when the worker's report arrives.
"""

from __future__ import annotations

import os

import pytest

from .budget import DEFAULT_SCALE, SCALE_ENV, timeout_scale

_REASON_CHARS = 300


def _configured_timeout(config: pytest.Config) -> float | None:
    """The timeout of a test without a marker, as pytest-timeout reads it."""
    for raw in (
        config.getoption("timeout", None),
        os.environ.get("PYTEST_TIMEOUT"),
        config.getini("timeout"),
    ):
        if raw not in (None, ""):
            return float(raw)
    return None


def scaled_timeout_marker(
    marker: pytest.Mark | None, default: float | None, scale: float
) -> pytest.MarkDecorator | None:
    """The ``timeout`` marker a test runs under: its own (else ``default``) times ``scale``.

    ``None`` where the test has no timeout at all; 0 (no timeout) stays 0.
    """
    kwargs = dict(marker.kwargs) if marker is not None else {}
    if marker is not None and marker.args:
        base = marker.args[0]
    else:
        base = kwargs.get("timeout", default)
    kwargs.pop("timeout", None)
    if base is None:
        return None
    base = float(base)
    return pytest.mark.timeout(base * scale if base > 0 else 0.0, **kwargs)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if not config.pluginmanager.hasplugin("timeout"):
        return
    scale = timeout_scale()
    default = _configured_timeout(config)
    for item in items:
        new = scaled_timeout_marker(item.get_closest_marker("timeout"), default, scale)
        if new is not None:
            item.add_marker(new, append=False)  # the closest marker, the one pytest-timeout reads


def pytest_report_header(config: pytest.Config) -> str | None:
    if not config.pluginmanager.hasplugin("timeout"):
        return None
    return (
        f"timeouts: each test's own (else the one above) x {timeout_scale():g} "
        f"({SCALE_ENV}, default {DEFAULT_SCALE:g}; ampc_jax.testing.budget)"
    )


def failure_line(report: pytest.TestReport) -> str:
    """``FAILED <node id> - <reason>`` (``ERROR ... (setup)`` outside the test's call)."""
    longrepr = report.longrepr
    crash = getattr(longrepr, "reprcrash", None)
    if crash is not None:
        reason = crash.message
    elif isinstance(longrepr, tuple):  # (path, line, message)
        reason = str(longrepr[2])
    else:
        text = str(longrepr or "").strip()
        reason = text.splitlines()[-1] if text else ""
    reason = " ".join(reason.split())
    if len(reason) > _REASON_CHARS:
        reason = reason[: _REASON_CHARS - 3] + "..."
    what = "FAILED" if report.when == "call" else f"ERROR ({report.when})"
    return f"{what} {report.nodeid} - {reason}"


class _FailurePrinter:
    """Prints each failed report of one pytest run (its ``config``) as it arrives."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        if not report.failed:
            return
        reporter = self.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is None:
            return
        reporter.ensure_newline()  # after a file's path and its letters (default verbosity)
        writer = getattr(reporter, "_tw", None)
        if writer is not None and writer.width_of_current_line:  # after -q's letters
            reporter.write("\n")
        reporter.write_line(failure_line(report), red=True, bold=True)
        reporter.flush()


def pytest_configure(config: pytest.Config) -> None:
    if not hasattr(config, "workerinput"):  # an xdist worker: the controller prints
        config.pluginmanager.register(_FailurePrinter(config), "ampc-failure-printer")
