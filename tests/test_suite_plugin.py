"""The suite's own pytest plugin (ampc_jax/testing/pytest_plugin.py), run on small
test files in a pytest subprocess: a failure is printed with its reason when it
happens, before the tests after it run (also under pytest-xdist), and every
timeout is the test's budget times AMPC_TEST_TIMEOUT_SCALE."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from ampc_jax.testing.budget import DEFAULT_SCALE, SCALE_ENV, budget, timeout_scale
from ampc_jax.testing.pytest_plugin import scaled_timeout_marker

pytestmark = pytest.mark.timeout(60)

PLUGIN = "ampc_jax.testing.pytest_plugin"
TESTS = Path(__file__).resolve().parent

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


def _clock_call(node) -> bool:
    """``time.monotonic()``, ``time.perf_counter()``, ``time.time()`` (and their _ns)."""
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id == "time"
        and node.func.attr.removesuffix("_ns") in ("monotonic", "perf_counter", "time")
    )


def _wall_clock_asserts(tree: ast.AST) -> list[str]:
    """Asserts that bound a measured duration from above: ``elapsed < 0.5`` where
    ``elapsed = time.perf_counter() - t0``, or ``time.monotonic() - t0 < 10``."""
    durations = {
        target.id
        for node in ast.walk(tree)
        if isinstance(node, ast.Assign)
        and isinstance(node.value, ast.BinOp)
        and isinstance(node.value.op, ast.Sub)
        and any(_clock_call(side) for side in (node.value.left, node.value.right))
        for target in node.targets
        if isinstance(target, ast.Name)
    }
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Assert):
            continue
        for cmp in ast.walk(node.test):
            if not isinstance(cmp, ast.Compare) or not isinstance(cmp.ops[0], (ast.Lt, ast.LtE)):
                continue
            left = cmp.left
            measured = (isinstance(left, ast.Name) and left.id in durations) or (
                isinstance(left, ast.BinOp)
                and isinstance(left.op, ast.Sub)
                and any(_clock_call(side) for side in (left.left, left.right))
            )
            if measured:
                found.append(f"line {node.lineno}: {ast.unparse(node.test)}")
    return found


def test_tests_assert_results_never_wall_clock_speed():
    """No test bounds a measured duration from above (a loaded machine makes any
    bound fail; speed is bench/'s): a hang is the test's timeout's to catch."""
    assert _wall_clock_asserts(
        ast.parse(
            "t0 = time.perf_counter()\nelapsed = time.perf_counter() - t0\nassert elapsed < 0.5"
        )
    ) == ["line 3: elapsed < 0.5"]
    assert _wall_clock_asserts(ast.parse("assert time.monotonic() - t0 < 10.0")) != []
    found = {
        str(path.relative_to(TESTS)): hits
        for path in sorted(TESTS.rglob("*.py"))
        if (hits := _wall_clock_asserts(ast.parse(path.read_text())))
    }
    assert not found, found


def test_every_test_has_a_timeout_from_the_budget(pytestconfig):
    """pyproject.toml's ``timeout`` gives every test without a marker its budget,
    and the plugin that scales it is loaded (tests/conftest.py)."""
    assert float(pytestconfig.getini("timeout")) > 0
    assert pytestconfig.pluginmanager.hasplugin("timeout")
    assert pytestconfig.pluginmanager.hasplugin(PLUGIN)
