"""The suite's own pytest plugin (ampc_jax/testing/pytest_plugin.py), run on small
test files in a pytest subprocess: a failure is printed with its reason when it
happens, before the tests after it run (also under pytest-xdist), and every
timeout is the test's budget times AMPC_TEST_TIMEOUT_SCALE."""

from __future__ import annotations

import pytest

from ampc_jax.testing.budget import DEFAULT_SCALE, SCALE_ENV, budget, timeout_scale
from ampc_jax.testing.pytest_plugin import scaled_timeout_marker

pytestmark = pytest.mark.timeout(60)

PLUGIN = "ampc_jax.testing.pytest_plugin"

FILE = """
import time

import pytest

def test_first_fails():
    assert 1 == 2, "one is not two"

@pytest.mark.timeout(1)
def test_needs_1_2_seconds():
    time.sleep(1.2)

@pytest.mark.timeout(0.3)
def test_needs_1_second():
    time.sleep(1.0)

def test_last():
    pass
"""
"""At AMPC_TEST_TIMEOUT_SCALE=2: the 1 s budget is a 2 s timeout (passes), the 0.3 s
one 0.6 s (times out)."""


def _check(lines: list[str]) -> None:
    summary = next(i for i, line in enumerate(lines) if "short test summary info" in line)
    for now in (
        "FAILED test_demo.py::test_first_fails - AssertionError: one is not two",
        "FAILED test_demo.py::test_needs_1_second - Failed: Timeout (>0.6s) from pytest-timeout",
    ):
        assert any(line.startswith(now) for line in lines[:summary]), (now, lines)


def test_a_failure_is_printed_as_it_happens_and_timeouts_are_scaled(pytester, monkeypatch):
    monkeypatch.setenv(SCALE_ENV, "2")
    pytester.makepyfile(test_demo=FILE)
    r = pytester.runpytest_inprocess("-p", PLUGIN, "-p", "no:cacheprovider", "-q")
    r.assert_outcomes(failed=2, passed=2)
    _check(r.outlines)


def test_under_xdist_the_controller_prints_a_failure_as_it_happens(pytester, monkeypatch):
    monkeypatch.setenv(SCALE_ENV, "2")
    pytester.makepyfile(test_demo=FILE)
    r = pytester.runpytest_subprocess("-p", PLUGIN, "-p", "no:cacheprovider", "-n", "2")
    r.assert_outcomes(failed=2, passed=2)
    _check(r.outlines)


def test_markers_and_the_default_are_scaled():
    m = pytest.mark.timeout(10, method="thread").mark
    assert scaled_timeout_marker(m, 300.0, 3.0).mark.args == (30.0,)
    assert scaled_timeout_marker(m, 300.0, 3.0).mark.kwargs == {"method": "thread"}
    assert scaled_timeout_marker(pytest.mark.timeout(timeout=5).mark, None, 2.0).mark.args == (
        10.0,
    )
    assert scaled_timeout_marker(None, 300.0, 3.0).mark.args == (900.0,)
    assert scaled_timeout_marker(None, None, 3.0) is None
    assert scaled_timeout_marker(pytest.mark.timeout(0).mark, 300.0, 3.0).mark.args == (0.0,)


def test_the_scale_is_read_from_the_environment(monkeypatch):
    monkeypatch.delenv(SCALE_ENV, raising=False)
    assert timeout_scale() == DEFAULT_SCALE
    monkeypatch.setenv(SCALE_ENV, "10")
    assert budget(6) == 60
    for bad in ("fast", "0.5", "nan"):
        monkeypatch.setenv(SCALE_ENV, bad)
        with pytest.raises(ValueError, match=SCALE_ENV):
            timeout_scale()
