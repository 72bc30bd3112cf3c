"""One actuator contract: the examples, the bridge's vehicle.toml and the DBC agree
with ampc_jax.vehicle.actuators, and the simulated limiter is the bridge's."""

from __future__ import annotations

import itertools

import cantools
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import can_bridge
from ampc_jax.vehicle import EXAMPLES
from ampc_jax.vehicle.actuators import (
    ACTUATORS,
    TORQUE_STEP_NM,
    bridge_actuators,
    bridge_kwargs,
    load_limits,
)

pytestmark = pytest.mark.timeout(120)


def test_the_bridges_shipped_vehicle_toml_is_the_contract() -> None:
    assert load_limits(can_bridge.default_config_path()) == ACTUATORS
    cfg = can_bridge.load_config()
    assert float(cfg["period_ms"]) == ACTUATORS.period_ms


def test_the_dbc_torque_signals_hold_every_limit_on_their_grid() -> None:
    db = cantools.database.load_file(can_bridge.dbc_path())
    msg = db.get_message_by_name("WheelTorqueCmd")
    for w, lim in zip(("FL", "FR", "RL", "RR"), ACTUATORS.wheels, strict=True):
        sig = msg.get_signal_by_name(f"Torque{w}")
        assert sig.scale == TORQUE_STEP_NM
        assert sig.minimum <= lim.min_nm and lim.max_nm <= sig.maximum
        assert lim.min_nm % TORQUE_STEP_NM == 0 and lim.max_nm % TORQUE_STEP_NM == 0


@pytest.mark.parametrize(
    ("name", "driver_torque"), [("cruise", 0.0), ("stability", 0.0), ("stability", 2000.0)]
)
def test_every_corner_of_an_examples_agent_bounds_is_within_the_wheels(
    name: str, driver_torque: float
) -> None:
    """The controller never plans a torque the bridge would clamp, and the front
    brakes' bound is the actuators' range. (The stability example adds the
    driver's torque: above 2000 Nm on the rear axle the bridge clamps it, and
    ``SimConfig(actuators="bridge")`` models that.)"""
    from ampc_jax.vehicle.cruise import cruise_bounds
    from ampc_jax.vehicle.stability import stability_bounds

    ex = EXAMPLES[name]
    s = ex.settings_type()
    T_drv = jnp.asarray(driver_torque)
    lb, ub = cruise_bounds(s) if name == "cruise" else stability_bounds(T_drv, s)
    lo = np.concatenate([np.asarray(x) for x in lb])
    hi = np.concatenate([np.asarray(x) for x in ub])
    reached = np.zeros(4, bool)
    for corner in itertools.product(*zip(lo, hi, strict=True)):
        T = np.asarray(ex.wheel_torques(jnp.asarray(corner), T_drv))
        for j, lim in enumerate(ACTUATORS.wheels):
            assert lim.min_nm - 1e-9 <= T[j] <= lim.max_nm + 1e-9, (name, corner, T)
            reached[j] |= np.isclose(T[j], lim.min_nm) or np.isclose(T[j], lim.max_nm)
    assert reached[:2].all(), "the front brakes' bound is inside the actuators' range"
    if name == "cruise":
        assert reached.all(), "|DTR/2| + |RTV| does not fill the rear wheels' range"


def test_bridge_kwargs_are_accepted_by_the_bridge() -> None:
    b = can_bridge.Bridge("slcan-pty:", **bridge_kwargs())
    assert b.period_ms == ACTUATORS.period_ms


def _rust_like(prev, target, lim):
    """The limiter written out per wheel in Python (safety.rs, Limiter::follow)."""
    out = []
    dt = lim.period_ms * 1e-3
    for y, t, w in zip(prev, target, lim.wheels, strict=True):
        gmin = int(np.ceil(w.min_nm / 2)) if w.min_nm < 0 else int(w.min_nm // 2)
        gmax = int(np.floor(w.max_nm / 2))
        rise = max(1, int(np.floor(w.rise_nm_per_s * dt / 2)))
        rel = max(1, int(np.floor(w.release_nm_per_s * dt / 2)))
        want = min(max(int(np.round(t / 2)), gmin), gmax)
        up, down = {1: (rise, rel), -1: (rel, rise), 0: (rise, rise)}[int(np.sign(y))]
        n = y + min(max(want - y, -down), up)
        if (y > 0 and n < 0) or (y < 0 and n > 0):
            n = 0
        out.append(min(max(n, gmin), gmax))
    return out


def test_the_simulated_limiter_follows_the_bridges_rules() -> None:
    rng = np.random.default_rng(0)
    f = jax.jit(bridge_actuators)
    prev = np.zeros(4, np.int32)
    for _ in range(400):
        target = rng.uniform(-3000, 3000, 4)
        steps, torques = f(jnp.asarray(prev), jnp.asarray(target))
        want = _rust_like(prev.tolist(), target.tolist(), ACTUATORS)
        assert np.asarray(steps).tolist() == want
        np.testing.assert_array_equal(np.asarray(torques), 2.0 * np.asarray(want))
        prev = np.asarray(steps)
    # a non-finite target holds the output (the bridge refuses the command)
    steps, _ = f(jnp.asarray(prev), jnp.full(4, jnp.nan))
    np.testing.assert_array_equal(np.asarray(steps), prev)


def test_load_limits_names_the_bad_key(tmp_path) -> None:
    p = tmp_path / "v.toml"
    p.write_text('[wheels.FL]\nmin_nm = "a lot"\n')
    with pytest.raises(ValueError, match=r"wheels\.FL\.min_nm"):
        load_limits(p)
    p.write_text("[wheels.XX]\nmin_nm = -1.0\n")
    with pytest.raises(ValueError, match="unknown wheel"):
        load_limits(p)
