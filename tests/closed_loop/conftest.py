"""Closed-loop runs shared by the tests in tests/closed_loop/ (compiled once per process)."""

import pytest

from ampc_jax.closed_loop import simulate

SHORT = 2.0
"""s simulated in the shared closed-loop runs (40 control steps)."""


@pytest.fixture(scope="session")
def cruise_run():
    """The cruise lane change's first 2 s at the defaults (shadow on)."""
    return simulate("cruise_lane_change", duration=SHORT)


@pytest.fixture(scope="session")
def stability_run():
    """The stability launch/brake's first 2 s at the defaults (shadow on)."""
    return simulate("stability_launch_brake", duration=SHORT)
