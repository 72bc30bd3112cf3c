"""Fixtures shared by the vehicle tests (tests/vehicle/)."""

import jax.numpy as jnp
import pytest

from ampc_jax.vehicle import Measurement, VehicleParams


@pytest.fixture(scope="session")
def make_meas():
    """A factory of hand-made :class:`Measurement` s (default: a mild left turn at 15 m/s)."""
    P = VehicleParams()

    def make(v_x=15.0, v_y=0.3, r=0.2, omega=None, F_x=None, F_y=None, dtype=jnp.float64):
        f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
        omega = omega if omega is not None else [v_x / P.R_w] * 4
        F_x = F_x if F_x is not None else [0.0, 0.0, 300.0, 350.0]
        F_y = F_y if F_y is not None else [3000.0, 2500.0, 2800.0, 2600.0]
        z4 = jnp.zeros(4, dtype)
        return Measurement(
            f(v_x), f(v_y), f(r), f(omega), f(F_x), f(F_y), z4, z4, z4, f(0.0), f(0.0)
        )

    return make
