"""Shared test configuration: float64 by default (float32 is tested explicitly).

``ampc_jax`` is imported before JAX runs anything so that its XLA:CPU
deadlock workaround (README, "Known issues") is in force for every test.
"""

import os

# Under pytest-xdist (`.ci/run` runs `-n 2`) each worker is pinned to one core
# of its own before JAX starts its thread pools, so that the two workers do
# not compete for a core and timing-window tests see a steady core, as under
# the former `taskset -c 0` run of the whole suite.
# Only when every worker gets a core (more workers than cores, or a parent
# already pinned to fewer cores: no pinning, the scheduler shares them out).
_WORKER = os.environ.get("PYTEST_XDIST_WORKER", "")
if _WORKER.startswith("gw") and hasattr(os, "sched_setaffinity"):
    _cpus = sorted(os.sched_getaffinity(0))
    _n_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if int(_WORKER[2:]) < len(_cpus) and _n_workers <= len(_cpus):
        os.sched_setaffinity(0, {_cpus[int(_WORKER[2:])]})

# One persistent XLA compilation cache for the whole run, shared by the xdist
# workers and the subprocesses the tests start (CLI, bench scripts, notebook):
# many tests compile the same control steps and closed loops, and a compile
# (2 to 6 s) costs more than most tests' runs. A fresh directory per run unless
# AMPC_TEST_JAX_CACHE names one (the results do not depend on it).
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import tempfile

    _cache = os.environ.get("AMPC_TEST_JAX_CACHE") or os.path.join(
        tempfile.gettempdir(),
        f"ampc-jax-test-cache-{os.environ.get('PYTEST_XDIST_TESTRUNUID', os.getpid())}",
    )
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

# The tests check results, not speed: XLA compiles their programs without LLVM's
# optimisation passes, which halves a compile (2 s -> 1 s for a control step)
# and keeps IEEE semantics (no fast-math either way). Benchmarks (bench/) and
# the timing figures are measured with the default level.
# AMPC_TEST_XLA_OPT=1 keeps the default level.
if os.environ.get("AMPC_TEST_XLA_OPT") != "1" and "optimization_level" not in os.environ.get(
    "XLA_FLAGS", ""
):
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
    ).strip()

import jax  # noqa: E402
import pytest  # noqa: E402

import ampc_jax  # noqa: F401, E402  (sets XLA_FLAGS before the CPU backend starts)

jax.config.update("jax_enable_x64", True)

# Timeouts and failures (ampc_jax/testing/pytest_plugin.py): every test's timeout
# is its budget, the seconds it may take on an idle 2-core machine under
# `.ci/run` (its `@pytest.mark.timeout(S)`, else pyproject.toml's `timeout`),
# times AMPC_TEST_TIMEOUT_SCALE (default 3: two busy processes beside the suite
# halve each worker's core, with a margin of 1.5); a test's own deadlines (a
# subprocess's timeout, a wait for output) use ampc_jax.testing.budget.budget(S).
# A failure is printed with its reason as it happens, not only at the end.
pytest_plugins = ["ampc_jax.testing.pytest_plugin", "pytester"]


# Tests that time things (the can_bridge bridge's tick and watchdog windows)
# or use both cores on purpose (the subprocesses of test_batch.py's sharding
# and deadlock tests) run in one xdist group, one after another on one worker
# (`.ci/run` passes --dist loadgroup), so that neither disturbs the other.
SERIAL_GROUP = "timing_and_both_cores"


# A module- or session-scoped fixture of the suite (a closed loop, a sweep, an
# `ampc run`: 10 to 60 s each) is computed once per worker that needs it: the
# tests that use one share an xdist group, so that one worker computes it once
# (with the timing group where a test of that group uses it too).
_TESTS_DIR = os.path.dirname(os.path.abspath(__file__))


def _shared_fixtures(item) -> list[str]:
    """The suite's own module- and session-scoped fixtures that ``item`` uses."""
    import inspect

    keys = []
    info = getattr(item, "_fixtureinfo", None)
    for name, defs in info.name2fixturedefs.items() if info else ():
        fixturedef = defs[-1]
        if fixturedef.scope not in ("module", "package", "session"):
            continue
        try:
            source = inspect.getsourcefile(fixturedef.func) or ""
        except TypeError:
            continue
        if os.path.abspath(source).startswith(_TESTS_DIR + os.sep):
            keys.append(f"{os.path.relpath(source, _TESTS_DIR)}::{name}")
    return sorted(keys)


@pytest.hookimpl(tryfirst=True)  # before xdist's worker reads the groups into node ids
def pytest_collection_modifyitems(config, items):
    serial: set[str] = set()
    for item in items:
        if "tests/can_bridge/" in item.nodeid or item.get_closest_marker("both_cores"):
            item.add_marker(pytest.mark.xdist_group(SERIAL_GROUP))
            serial.update(_shared_fixtures(item))
    # fixtures used by one test together are one group (union-find over their keys)
    parent: dict[str, str] = {}

    def root(k: str) -> str:
        while parent.setdefault(k, k) != k:
            k = parent[k]
        return k

    todo = []
    for item in items:
        if item.get_closest_marker("xdist_group"):
            continue
        keys = _shared_fixtures(item)
        if keys:
            todo.append((item, keys))
            for k in keys[1:]:
                parent[root(k)] = root(keys[0])
    joined = {root(k) for k in serial}
    for item, keys in todo:
        group = root(keys[0])
        item.add_marker(pytest.mark.xdist_group(SERIAL_GROUP if group in joined else group))
