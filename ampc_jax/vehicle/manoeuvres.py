"""Drivers, paths and the test manoeuvres of section "Experimental Studies".

* Paths are lateral offsets ``Y = y(X)`` built from up to ``MAX_STEPS`` smooth
  (quintic, C^2) lane-change steps, so every path -- straight, single lane
  change, ISO 3888-1 double lane change, or a sequence -- has the same array
  shapes and scenarios can be stacked and vmapped.
* The steering driver is pure pursuit from the rear axle with a speed-dependent
  look-ahead, then angle- and rate-limited.
* The longitudinal driver gives the driver torque T_DTR (rear axle) as a
  feed-forward torque profile plus a speed PI on the target-speed profile.
  For the cruise example T_DTR is zero (the MPC's DTR agent tracks v_ref); for
  the stability examples T_DTR is the disturbance.
* ``SCENARIOS`` maps a name to a :class:`ScenarioSpec`: static data (example,
  duration, focus window) plus a :class:`Scenario` of arrays.

Dtypes: paths and scenarios hold *NumPy float64* arrays, whatever JAX's x64
setting was when they were built (``SCENARIOS`` is built at import time,
typically before x64 is enabled). A run casts them to its own dtype
(``closed_loop.run_closed_loop``); JAX functions given them directly convert
them to JAX's default float dtype. So 0.3 stays 0.3 in float64 runs, and no
float32 array is frozen into the registry.

ISO 3888-1 double lane change (section lengths 15/30/25/25/15/30 m): lane 1
(entry) X in [0, 15], transition [15, 45], lane 3 (side lane) [45, 70],
transition [70, 95], lane 5 (exit) [95, 110], run-out [110, 140].  The
reference centre line moves by the nominal lateral offset (3.5 m) with a
quintic over each transition.  The standard sets the lane widths from the
vehicle width w (1.1 w + 0.25, 1.2 w + 0.25 for the side lane, 1.3 w + 0.25)
and the 3.5 m offset between cone lines, not between centre lines.  Read as
Project Chrono's ISO 3888-1 demo reads it (the side lane's near cone line
3.5 m from the entry lane's centre line), the side lane's centre is at
3.5 + (1.2 w + 0.25) / 2, about 4.8 m for w = 1.9 m, so the bare 3.5 m used
here is the milder manoeuvre; the exit lane shares the entry lane's right
cone line, about 0.1 w off its centre.  ``offset`` is a parameter.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from .params import CONTROL_DT, VehicleParams
from .plant import PlantState, initial_state

__all__ = [
    "DLC_SECTIONS",
    "MAX_STEPS",
    "SCENARIOS",
    "DriverParams",
    "DriverState",
    "Path",
    "Scenario",
    "ScenarioSpec",
    "double_lane_change",
    "driver_step",
    "initial_driver_state",
    "initial_plant_state",
    "join_paths",
    "make_scenario",
    "path_y",
    "path_slope",
    "register_scenario",
    "scenario",
    "single_lane_change",
    "stack_scenarios",
    "straight",
]

MAX_STEPS = 4
"""Number of lane-change steps every Path holds (unused ones have zero offset)."""

N_KNOTS = 8
"""Number of knots of every speed/torque profile (padded)."""

DLC_SECTIONS = (15.0, 30.0, 25.0, 25.0, 15.0, 30.0)
"""ISO 3888-1 section lengths (m): entry, transition, side lane, transition, exit, run-out."""


# --------------------------------------------------------------------------- paths
class Path(NamedTuple):
    """Centre line ``y(X) = sum_k dy_k q((X - x0_k)/(x1_k - x0_k))``, q the quintic step.

    Fields are arrays of shape (MAX_STEPS,) (or (batch, MAX_STEPS)).
    """

    x0: Array  # m, start of each transition
    x1: Array  # m, end of each transition
    dy: Array  # m, lateral change of each transition (left positive)


def _pad(x0: list[float], x1: list[float], dy: list[float]) -> Path:
    n = len(x0)
    if n > MAX_STEPS:
        raise ValueError(f"a path holds at most {MAX_STEPS} lane-change steps, got {n}")
    fill = MAX_STEPS - n
    return Path(
        np.array(list(x0) + [1e6] * fill, dtype=np.float64),
        np.array(list(x1) + [1e6 + 1.0] * fill, dtype=np.float64),
        np.array(list(dy) + [0.0] * fill, dtype=np.float64),
    )


def straight() -> Path:
    """A straight line ``y = 0``."""
    return _pad([], [], [])


def single_lane_change(x_start: float, length: float, offset: float = 3.5) -> Path:
    """One lane change by ``offset`` (m, left positive) over ``[x_start, x_start + length]``."""
    return _pad([x_start], [x_start + length], [offset])


def double_lane_change(x_start: float = 0.0, offset: float = 3.5) -> Path:
    """ISO 3888-1 double lane change starting (entry lane) at ``x_start``; see module doc."""
    s = DLC_SECTIONS
    a = x_start + s[0]
    b = a + s[1]
    c = b + s[2]
    d = c + s[3]
    return _pad([a, c], [b, d], [offset, -offset])


def join_paths(*paths: Path) -> Path:
    """Concatenate the lane-change steps of several paths (at most MAX_STEPS in total)."""
    keep = [
        (float(x0), float(x1), float(dy))
        for p in paths
        for x0, x1, dy in zip(p.x0, p.x1, p.dy, strict=True)
        if dy != 0.0
    ]
    return _pad([k[0] for k in keep], [k[1] for k in keep], [k[2] for k in keep])


def _quintic(u: Array) -> tuple[Array, Array]:
    u = jnp.clip(u, 0.0, 1.0)
    q = u**3 * (10.0 - 15.0 * u + 6.0 * u**2)
    dq = 30.0 * u**2 * (1.0 - u) ** 2
    return q, dq


def path_y(path: Path, X: Array) -> Array:
    """Lateral position of the centre line at longitudinal position X (m), shape of X."""
    X = jnp.asarray(X)
    u = (X[..., None] - path.x0) / (path.x1 - path.x0)
    q, _ = _quintic(u)
    return jnp.sum(path.dy * q, axis=-1)


def path_slope(path: Path, X: Array) -> Array:
    """dY/dX of the centre line at X."""
    X = jnp.asarray(X)
    L = path.x1 - path.x0
    _, dq = _quintic((X[..., None] - path.x0) / L)
    return jnp.sum(path.dy * dq / L, axis=-1)


# --------------------------------------------------------------------------- scenarios
class Scenario(NamedTuple):
    """Array data of one manoeuvre (shapes for one scenario; stackable for vmap)."""

    mu: Array  # () road friction
    v0: Array  # () m/s initial speed
    Y0: Array  # () m initial lateral position (a perturbation for straight runs)
    path: Path  # (MAX_STEPS,) each
    speed_t: Array  # (N_KNOTS,) s, knots of the target-speed profile v_ref(t)
    speed_v: Array  # (N_KNOTS,) m/s
    torque_t: Array  # (N_KNOTS,) s, knots of the driver's feed-forward torque
    torque_v: Array  # (N_KNOTS,) Nm (rear axle)
    speed_kp: Array  # () Nm/(m/s), driver speed feedback (0: open-loop torque)
    speed_ki: Array  # () Nm/m
    torque_min: Array  # () Nm, driver torque limits
    torque_max: Array  # ()


def _knots(t: list[float], v: list[float]) -> tuple[Array, Array]:
    if len(t) > N_KNOTS:
        raise ValueError(f"at most {N_KNOTS} knots")
    fill = N_KNOTS - len(t)
    tt = list(t) + [t[-1] + 1.0 + k for k in range(fill)]
    vv = list(v) + [v[-1]] * fill
    return np.array(tt, dtype=np.float64), np.array(vv, dtype=np.float64)


def make_scenario(
    mu: float,
    v0: float,
    path: Path,
    speed: tuple[list[float], list[float]],
    torque: tuple[list[float], list[float]] = ([0.0], [0.0]),
    speed_kp: float = 0.0,
    speed_ki: float = 0.0,
    torque_limits: tuple[float, float] = (-3000.0, 4000.0),
    Y0: float = 0.0,
) -> Scenario:
    """Build a :class:`Scenario` from lists (knots are padded to N_KNOTS); NumPy float64."""
    st, sv = _knots(*speed)
    tt, tv = _knots(*torque)
    f = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
    return Scenario(
        f(mu),
        f(v0),
        f(Y0),
        path,
        st,
        sv,
        tt,
        tv,
        f(speed_kp),
        f(speed_ki),
        f(torque_limits[0]),
        f(torque_limits[1]),
    )


class ScenarioSpec(NamedTuple):
    """A registered manoeuvre: static description plus its array data."""

    name: str
    example: str  # the name of a registered vehicle example (vehicle.EXAMPLES)
    duration: float  # s
    focus: tuple[float, float]  # s, window where both objectives are active
    description: str
    scenario: Scenario

    @property
    def n_steps(self) -> int:
        """Number of control steps at CONTROL_DT."""
        return int(round(self.duration / CONTROL_DT))


def stack_scenarios(specs: list[ScenarioSpec] | tuple[ScenarioSpec, ...]) -> Scenario:
    """Stack the array data of several scenarios along a new leading axis (for vmap).

    NumPy arrays in, NumPy arrays out (dtype kept; see the module docstring).
    """
    return jax.tree.map(
        lambda *x: np.stack([np.asarray(a) for a in x]), *[s.scenario for s in specs]
    )


def _cruise_lane_change() -> ScenarioSpec:
    # v_ref: 18 m/s, decelerate to 11 m/s (t 1..4.5 s), hold, accelerate to 17 m/s (t 6..12 s).
    # SLC (+3.5 m over X 25..55 m) during the deceleration; ISO DLC (-3.5 m, entry at X = 85 m,
    # transitions X 100..130 and 155..180 m, about t 7..9.5 s and 11.3..13 s) while accelerating.
    # Peak path curvature demands ~0.75 g at 15 m/s: aggressive but feasible on mu = 1.
    path = join_paths(single_lane_change(25.0, 30.0, 3.5), double_lane_change(85.0, -3.5))
    sc = make_scenario(
        1.0, 18.0, path, ([0.0, 1.0, 4.5, 6.0, 12.0], [18.0, 18.0, 11.0, 11.0, 17.0])
    )
    return ScenarioSpec(
        "cruise_lane_change",
        "cruise",
        16.0,
        (7.0, 13.0),
        "mu=1: SLC while decelerating 18->11 m/s, then ISO DLC while "
        "accelerating 11->17 m/s; v_ref is the LST target (driver torque 0).",
        sc,
    )


def _stability_launch_brake() -> ScenarioSpec:
    sc = make_scenario(
        0.3,
        2.0,
        straight(),
        ([0.0], [2.0]),
        torque=([0.0, 0.5, 3.5, 4.0, 7.0, 7.5], [0.0, 1500.0, 1500.0, -1800.0, -1800.0, 0.0]),
        Y0=0.3,
    )
    return ScenarioSpec(
        "stability_launch_brake",
        "stability",
        9.0,
        (0.5, 7.5),
        "mu=0.3: straight launch with 1500 Nm rear torque (rear wheels spin), "
        "then 1800 Nm rear braking (rear wheels lock); starts 0.3 m off the line.",
        sc,
    )


def _stability_dlc() -> ScenarioSpec:
    path = double_lane_change(20.0, 3.5)
    sc = make_scenario(
        1.0,
        10.0,
        path,
        ([0.0], [10.0]),
        torque=([0.0, 0.5, 1.0, 5.0, 5.5], [0.0, 0.0, 2800.0, 2800.0, 0.0]),
    )
    return ScenarioSpec(
        "stability_dlc",
        "stability",
        9.0,
        (1.5, 6.0),
        "mu=1: ISO DLC while accelerating hard from 10 m/s with 2800 Nm "
        "driver torque on the rear axle (t 1..5 s).",
        sc,
    )


SCENARIOS: dict[str, ScenarioSpec] = {
    s.name: s for s in (_cruise_lane_change(), _stability_launch_brake(), _stability_dlc())
}
"""Registry: name -> ScenarioSpec (:func:`register_scenario` adds one)."""


def scenario(name: str | ScenarioSpec) -> ScenarioSpec:
    """The registered scenario ``name`` (ValueError naming ``scenario`` otherwise)."""
    if isinstance(name, ScenarioSpec):
        return name
    if name not in SCENARIOS:
        raise ValueError(f"scenario: expected one of {sorted(SCENARIOS)}, got {name!r}")
    return SCENARIOS[name]


def register_scenario(spec: ScenarioSpec) -> ScenarioSpec:
    """Add ``spec`` to :data:`SCENARIOS` (ValueError if another one has its name)."""
    if spec.name in SCENARIOS and SCENARIOS[spec.name] is not spec:
        raise ValueError(f"scenario: {spec.name!r} is already registered")
    SCENARIOS[spec.name] = spec
    return spec


# --------------------------------------------------------------------------- drivers
class DriverParams(NamedTuple):
    """Driver model settings (road-wheel angles)."""

    lookahead_min: float = 5.0  # m
    lookahead_time: float = 0.45  # s, look-ahead = max(min, time * v_x)
    steer_max: float = 0.5  # rad, road-wheel angle limit
    steer_rate_max: float = 0.8  # rad/s, road-wheel rate limit
    dt: float = CONTROL_DT  # s, driver update period
    wheelbase: float = 2.85  # m (pure pursuit geometry)
    b: float = 1.43  # m, CG to rear axle (pure pursuit reference point)
    int_limit: float = 20.0  # m, anti-windup bound on the speed-error integral


class DriverState(NamedTuple):
    """Driver memory: last steering command (rad) and speed-error integral (m)."""

    steer: Array
    speed_int: Array


def initial_driver_state(dtype=None) -> DriverState:
    """Zero steering and zero integral."""
    z = jnp.zeros((), dtype or jnp.result_type(float))
    return DriverState(z, z)


def initial_plant_state(scenario: Scenario, params: VehicleParams, dtype=None) -> PlantState:
    """Plant state at t = 0: speed v0, on the path's start (Y0), heading 0."""
    return initial_state(scenario.v0, params, Y0=scenario.Y0, dtype=dtype)


def pure_pursuit(state: PlantState, path: Path, params: DriverParams) -> Array:
    """Unlimited pure-pursuit road-wheel angle (rad) towards the path."""
    d = params
    c, s = jnp.cos(state.psi), jnp.sin(state.psi)
    xr = state.X - d.b * c
    yr = state.Y - d.b * s
    ld = jnp.maximum(d.lookahead_min, d.lookahead_time * state.v_x)
    xt = xr + ld
    yt = path_y(path, xt).astype(state.Y.dtype)
    dx = (xt - xr) * c + (yt - yr) * s
    dy = -(xt - xr) * s + (yt - yr) * c
    return jnp.arctan(2.0 * d.wheelbase * dy / (dx**2 + dy**2))


def driver_step(
    driver_state: DriverState,
    plant_state: PlantState,
    t: Array,
    scenario: Scenario,
    params: DriverParams,
) -> tuple[DriverState, Array, Array, Array]:
    """One driver update (every control period).

    Parameters
    ----------
    driver_state : DriverState
    plant_state : PlantState
    t : Array, shape ()
        Time since the start of the manoeuvre (s).
    scenario : Scenario
    params : DriverParams

    Returns
    -------
    (driver_state, steer, driver_torque, v_ref)
        New driver state; front road-wheel angle (rad, rate/angle limited);
        driver torque T_DTR on the rear axle (Nm; feed-forward profile + speed
        PI, clipped); target speed v_ref(t) (m/s, the LST reference).
    """
    d = params
    dtype = plant_state.v_x.dtype
    sc = scenario
    target = pure_pursuit(plant_state, sc.path, d)
    step = d.steer_rate_max * d.dt
    steer = driver_state.steer + jnp.clip(target - driver_state.steer, -step, step)
    steer = jnp.clip(steer, -d.steer_max, d.steer_max).astype(dtype)

    t = jnp.asarray(t, dtype)
    v_ref = jnp.interp(t, sc.speed_t, sc.speed_v).astype(dtype)
    err = v_ref - plant_state.v_x
    integ = jnp.clip(driver_state.speed_int + d.dt * err, -d.int_limit, d.int_limit)
    torque = jnp.interp(t, sc.torque_t, sc.torque_v) + sc.speed_kp * err + sc.speed_ki * integ
    torque = jnp.clip(torque, sc.torque_min, sc.torque_max).astype(dtype)
    return DriverState(steer, integ.astype(dtype)), steer, torque, v_ref
