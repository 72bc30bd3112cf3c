"""Scenario families: seeded, reproducible sets of cases a sweep or a tuning run is over.

A family draws ``n`` cases from a seed. Two kinds:

* ``"step"`` -- single control steps: one :class:`~ampc_jax.problem.ProblemData`
  per case, all of one :class:`~ampc_jax.problem.Topology` (stacked on a leading
  axis), and the sampled operating point of each case as columns
  (:class:`StepCases`). The vehicle families linearise the example's model
  (eq.CC_system / eq.VSC_system) at a plant state drawn over the example's
  envelope (speed, friction, steering, driver torque, yaw rate, side slip,
  wheel slip), exactly as :meth:`Controller.problem_data` does in closed loop;
  the generated family perturbs one random problem's initial state and
  references (:func:`~ampc_jax.generate.random_problem`).
* ``"loop"`` -- whole closed-loop manoeuvres: a registered scenario with its
  friction, speed profile and steering amplitude (the lateral offset of its
  lane changes) drawn per case (:class:`LoopCases`).

Case ``i`` of a family depends only on (seed, i): drawing 100 cases and then
1,000 gives the same first 100, so a sweep can be split in chunks, resumed
and sharded over processes without changing any case. ``register_family``
adds one from Python (``docs/sweeps.md``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..formulations.registry import DEFAULT_FORMULATION
from ..validation import check_count

__all__ = [
    "FAMILIES",
    "Family",
    "LoopCases",
    "StepCases",
    "family",
    "register_family",
]


class StepCases(NamedTuple):
    """Single-step cases: the solver structure, the stacked data and each case's draw.

    ``config``: the :class:`~ampc_jax.closed_loop.SimConfig` the cases come
    from (``None`` for generated problems); ``topology`` the static structure;
    ``data`` a :class:`ProblemData` with a leading case axis; ``columns``
    name -> (n,) array of the sampled operating point (with ``case``, the
    case's index in the family).
    """

    config: Any
    topology: Any
    data: Any
    columns: dict[str, np.ndarray]


class LoopCases(NamedTuple):
    """Closed-loop cases: the run's configuration, the stacked scenarios, their draw."""

    config: Any
    scenarios: Any  # Scenario with a leading case axis (NumPy float64)
    n_steps: int
    columns: dict[str, np.ndarray]


@dataclass(frozen=True)
class Family:
    """A named, seeded source of cases.

    ``sample(n, seed, start, **options)`` returns cases ``start .. start + n - 1``
    (:class:`StepCases` for ``kind="step"``, :class:`LoopCases` for ``"loop"``),
    each a function of (seed, index) alone.
    """

    name: str
    kind: str
    description: str
    sampler: Callable[..., Any] = field(repr=False, compare=False)
    options: tuple[str, ...] = ()
    example: str | None = None
    """The vehicle example whose cases these are (its ``solver_defaults`` are a
    sweep's defaults), known without sampling; None for generated problems."""

    def sample(self, n: int, seed: int = 0, start: int = 0, **options: Any) -> Any:
        """Cases ``start`` .. ``start + n - 1`` of this family under ``seed``."""
        check_count(n, "cases")
        check_count(seed, "seed", 0)
        check_count(start, "start", 0)
        unknown = sorted(set(options) - set(self.options))
        if unknown:
            raise ValueError(
                f"{unknown[0]}: not an option of family {self.name!r} "
                f"(options: {', '.join(self.options) or 'none'})"
            )
        return self.sampler(int(n), int(seed), int(start), **options)


FAMILIES: dict[str, Family] = {}
"""Registry: name -> :class:`Family` (:func:`register_family` adds one)."""


def register_family(fam: Family) -> Family:
    """Add ``fam`` to :data:`FAMILIES` (ValueError if the name is taken or the kind unknown)."""
    if fam.kind not in ("step", "loop"):
        raise ValueError(f"kind: expected 'step' or 'loop', got {fam.kind!r}")
    if fam.name in FAMILIES:
        raise ValueError(f"family: {fam.name!r} is already registered")
    FAMILIES[fam.name] = fam
    return fam


def family(name: str | Family) -> Family:
    """The registered family ``name`` (ValueError listing them otherwise)."""
    if isinstance(name, Family):
        return name
    if name not in FAMILIES:
        raise ValueError(f"family: expected one of {sorted(FAMILIES)}, got {name!r}")
    return FAMILIES[name]


def case_rng(seed: int, index: int, stream: int = 0) -> np.random.Generator:
    """The generator of case ``index`` under ``seed`` (independent of the other cases)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(stream), int(index)]))


def _uniform(rngs: list[np.random.Generator], low: float, high: float) -> np.ndarray:
    return np.array([r.uniform(low, high) for r in rngs])


# ------------------------------------------------------------------ single control steps
ENVELOPES: dict[str, dict[str, tuple[float, float]]] = {
    # speed (m/s), friction, road-wheel angle (rad, scaled down with speed so the
    # lateral demand stays within mu g), driver torque (Nm), yaw-rate error on
    # the steady-state reference (rad/s), side slip (rad), rear-wheel slip ratio
    "cruise": {
        "v_x": (6.0, 30.0),
        "mu": (0.3, 1.0),
        "steer_g": (-0.8, 0.8),
        "driver_torque": (0.0, 0.0),
        "yaw_error": (-0.15, 0.15),
        "beta": (-0.04, 0.04),
        "slip": (-0.03, 0.05),
        "v_ref_offset": (-4.0, 4.0),
    },
    "stability": {
        "v_x": (2.0, 20.0),
        "mu": (0.2, 1.0),
        "steer_g": (-0.8, 0.8),
        "driver_torque": (-2000.0, 3000.0),
        "yaw_error": (-0.2, 0.2),
        "beta": (-0.05, 0.05),
        "slip": (-0.25, 0.35),
        "v_ref_offset": (0.0, 0.0),
    },
}
"""Ranges each vehicle family draws its operating point from (uniform).
``steer_g``: the lateral acceleration the steering alone would ask, in units
of mu g (kinematic: delta = steer_g mu g L / v^2, capped at the driver's 0.5 rad)."""


SHIFTED_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "cruise": {"v_x": (26.0, 34.0), "mu": (0.2, 0.45)},
    "stability": {"v_x": (14.0, 24.0), "mu": (0.12, 0.35)},
}
"""Another friction and speed range per vehicle family (option ``ranges``): faster
and on lower friction than most of :data:`ENVELOPES`, partly outside it; the
held-out set a learned start must also carry to (``docs/tuning.md``)."""


def check_ranges(example_name: str, ranges: Any) -> dict[str, tuple[float, float]]:
    """``ranges`` (name -> (low, high)) checked against :data:`ENVELOPES`' names:
    finite, low <= high, and a positive speed and friction (ValueError naming
    ``ranges``)."""
    env = ENVELOPES[example_name]
    if ranges is None:
        return {}
    if isinstance(ranges, str):
        if ranges != "shifted":
            raise ValueError(f"ranges: expected 'shifted' or a mapping, got {ranges!r}")
        ranges = SHIFTED_RANGES[example_name]
    if not hasattr(ranges, "items"):
        raise ValueError(f"ranges: expected a mapping name -> (low, high), got {ranges!r}")
    out: dict[str, tuple[float, float]] = {}
    for key, value in ranges.items():
        if key not in env:
            raise ValueError(f"ranges: {key!r} is not one of {sorted(env)}")
        try:
            lo, hi = (float(x) for x in value)
        except (TypeError, ValueError):
            raise ValueError(f"ranges.{key}: expected (low, high), got {value!r}") from None
        if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi):
            raise ValueError(f"ranges.{key}: expected finite low <= high, got {value!r}")
        if key in ("v_x", "mu") and lo <= 0:
            raise ValueError(f"ranges.{key}: expected positive values, got {value!r}")
        out[key] = (lo, hi)
    return out


def _vehicle_steps(
    example_name: str,
    n: int,
    seed: int,
    start: int,
    *,
    horizon: int | None = None,
    formulation: str = DEFAULT_FORMULATION,
    groups: str = "paper",
    ranges: Any = None,
    dtype: Any = None,
) -> StepCases:
    from ..closed_loop.config import SimConfig
    from ..closed_loop.controller import DriverInputs, controller_for
    from ..vehicle.examples import example
    from ..vehicle.plant import PlantState, measure

    settings = example(example_name).settings_type()
    if horizon is not None:
        settings = settings.replace(horizon=int(horizon))
    cfg = SimConfig(example=example_name, formulation=formulation, settings=settings)
    ctrl = controller_for(cfg)
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    params = cfg.loop_params(dt).controller
    vp = cfg.vehicle
    env = {**ENVELOPES[example_name], **check_ranges(example_name, ranges)}
    rngs = [case_rng(seed, start + i) for i in range(n)]
    cols = {k: _uniform(rngs, *env[k]) for k in env}
    g, L = 9.81, vp.a + vp.b
    v = cols["v_x"]
    steer = np.clip(cols["steer_g"] * cols["mu"] * g * L / v**2, -0.5, 0.5)
    r_ss = v * steer / (L * (1.0 + (v / 25.0) ** 2))  # steady yaw rate with understeer
    r = r_ss + cols["yaw_error"]
    v_y = v * np.tan(cols["beta"])
    omega = np.stack([v, v, v * (1 + cols["slip"]), v * (1 + cols["slip"])], axis=1) / vp.R_w
    v_ref = v + cols["v_ref_offset"]
    cols = {"case": np.arange(start, start + n), **cols, "steer": steer, "yaw_rate": r}

    def one(v_i, vy_i, r_i, om_i, st_i, mu_i, td_i, vr_i):
        ps = PlantState(0.0 * v_i, 0.0 * v_i, 0.0 * v_i, v_i, vy_i, r_i, om_i, 0.0 * v_i, v_i * r_i)
        meas = measure(ps, st_i, jnp.zeros(4, v_i.dtype), mu_i, vp)
        seen = ctrl.example.driver_torque_seen(td_i, mpc=True)
        return ctrl.problem_data(params, meas, DriverInputs(st_i, seen, vr_i, mu_i))

    arrs = [
        jnp.asarray(a, dt)
        for a in (v, v_y, r, omega, steer, cols["mu"], cols["driver_torque"], v_ref)
    ]
    data = jax.jit(jax.vmap(one))(*arrs)
    return StepCases(cfg, _with_groups(ctrl.topology, groups), data, cols)


GROUPS = ("paper", "full")
"""Agent groups of the vehicle step families: the example's own (the paper's,
what the closed loop runs), or every agent in every objective's group."""


def _with_groups(topology: Any, groups: str) -> Any:
    """``topology`` with the paper's groups, or with every agent in every group.

    The paper's cruise groups drop RTV's weak coupling to v_x when cornering
    (docs/known-issues.md): Local Explicit's fixed point is then not the
    integrated optimum, and e_sub holds several Nm of that by design. With
    ``"full"`` groups the decomposition is exact (the data are the same: rows
    and inputs keep their order).
    """
    from ..problem.topology import Topology

    if groups not in GROUPS:
        raise ValueError(f"groups: expected one of {GROUPS}, got {groups!r}")
    if groups == "paper":
        return topology
    T = topology
    full = Topology.build(
        n_x=T.n_x,
        horizon=T.horizon,
        agent_names=T.agent_names,
        agent_sizes=T.agent_sizes,
        objective_names=T.objective_names,
        output_sizes=T.output_sizes,
        groups=[tuple(range(len(T.agent_names)))] * T.n_objectives,
    )
    if full.n_c != T.n_c or full.box_rows != T.box_rows:
        raise ValueError("groups: the full groups change the constraint rows of this example")
    return full


def _generated_steps(
    n: int,
    seed: int,
    start: int,
    *,
    n_objectives: int = 2,
    horizon: int = 10,
    structure_seed: int = 0,
    dtype: Any = None,
) -> StepCases:
    from ..generate import random_problem

    prob = random_problem(int(structure_seed), int(n_objectives), horizon=int(horizon))
    T, base = prob.topology, prob.data()
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    rngs = [case_rng(seed, start + i, stream=1) for i in range(n)]
    x_scale = _uniform(rngs, 0.0, 2.0)
    ref_scale = _uniform(rngs, 0.2, 1.5)
    x0 = np.stack([x_scale[i] * rngs[i].standard_normal(T.n_x) for i in range(n)])
    data = jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a, dt), (n, *np.shape(a))), base)
    data = data._replace(
        x0=jnp.asarray(x0, dt),
        ref=tuple(jnp.asarray(ref_scale, dt)[:, None, None] * r for r in data.ref),
    )
    cols = {"case": np.arange(start, start + n), "x0_scale": x_scale, "ref_scale": ref_scale}
    return StepCases(None, T, data, cols)


# ------------------------------------------------------------------ closed-loop manoeuvres
LATERAL_DEMAND_MAX = 0.95
"""The largest lateral acceleration a drawn lane change asks of the road, as a
fraction of mu g (:func:`lateral_demand`): the paper's cruise lane change asks
9.34 m/s^2 on mu = 1, 0.95 mu g. Rule: a case drawing more has its lane offset
scaled down to this; reason: a path asking more than the road gives cannot be
followed by any controller: the car spins out, slows to a crawl, and a rear
wheel given full torque spins up (the 32 cases of seed 0 drew up to 1.56 mu g;
every case over 1.25 spun, the rear slip ratio, divided by the 1 m/s floor
of a stopped car, reaching 600), which a weight tuner's loss then chases.
With the cap, seed 0's 32 cases at the cruise example's default weights
(``tuning.weights.evaluate_settings``, 2026-12-04): rear slip median 0.059,
5 cases over 0.15, the worst 11.6 (mu 0.53, at the cap: YRT's yaw moment
takes the friction the path leaves); LST alone at most 0.115 -- what the
weight tuner's slip term is for."""


def lateral_demand(scenario: Any, dt: float = 0.01) -> float:
    """The peak lateral acceleration (m/s^2) the path of a speed-tracking
    ``scenario`` asks at its reference speed: max over t of |y''(X(t))| v(t)^2,
    with X(t) the distance covered at the reference speed v(t) from X = 0 and
    y the sum of quintic lane-change steps (:func:`~ampc_jax.vehicle.manoeuvres.path_y`:
    y''(X) = sum_k dy_k 60 u (1 - u)(1 - 2u) / L_k^2, u = (X - x0_k) / L_k)."""
    st, sv = np.asarray(scenario.speed_t, float), np.asarray(scenario.speed_v, float)
    t = np.arange(0.0, float(st.max()) + 60.0, dt)
    v = np.interp(t, st, sv)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    p = scenario.path
    x0, x1, dy = (np.asarray(a, float) for a in (p.x0, p.x1, p.dy))
    keep = dy != 0.0
    x0, x1, dy = x0[keep], x1[keep], dy[keep]
    L = x1 - x0
    u = np.clip((x[:, None] - x0) / L, 0.0, 1.0)
    ypp = np.sum(dy * 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u) / L**2, axis=1)
    return float(np.max(np.abs(ypp) * v**2))


def _cruise_manoeuvres(n: int, seed: int, start: int, *, dtype: Any = None) -> LoopCases:
    """The cruise lane change with friction, speed profile and lane offset drawn per case;
    a lane offset asking more than :data:`LATERAL_DEMAND_MAX` mu g is scaled down to it."""
    from ..closed_loop.config import config_for
    from ..vehicle.manoeuvres import (
        double_lane_change,
        join_paths,
        make_scenario,
        scenario,
        single_lane_change,
    )

    spec = scenario("cruise_lane_change")
    rngs = [case_rng(seed, start + i, stream=2) for i in range(n)]
    mu = _uniform(rngs, 0.5, 1.0)
    speed = _uniform(rngs, 0.7, 1.15)  # factor on the profile's speeds
    drawn = _uniform(rngs, 1.5, 3.5)  # m, both lane changes (the steering amplitude)
    offset = drawn.copy()
    demand = np.zeros(n)
    config = config_for(spec)
    g = config.vehicle.g

    def case(i: int, off: float) -> Any:
        path = join_paths(single_lane_change(25.0, 30.0, off), double_lane_change(85.0, -off))
        v = [18.0, 18.0, 11.0, 11.0, 17.0]
        return make_scenario(
            mu[i],
            18.0 * speed[i],
            path,
            ([0.0, 1.0, 4.5, 6.0, 12.0], [s * speed[i] for s in v]),
        )

    scs = []
    for i in range(n):
        sc = case(i, drawn[i])
        ratio = lateral_demand(sc) / (mu[i] * g)  # linear in the offset
        if ratio > LATERAL_DEMAND_MAX:
            offset[i] = drawn[i] * LATERAL_DEMAND_MAX / ratio
            sc = case(i, offset[i])
        demand[i] = min(ratio, LATERAL_DEMAND_MAX)
        scs.append(sc)
    stacked = jax.tree.map(lambda *x: np.stack(x), *scs)
    cols = {
        "case": np.arange(start, start + n),
        "mu": mu,
        "speed_scale": speed,
        "offset": offset,
        "offset_drawn": drawn,
        "lateral_demand_mu_g": demand,
    }
    return LoopCases(config, stacked, spec.n_steps, cols)


def _stability_manoeuvres(n: int, seed: int, start: int, *, dtype: Any = None) -> LoopCases:
    """The stability example's two manoeuvres, drawn per case: the launch and brake on
    low friction (friction, torques, lateral start offset drawn) or the double lane
    change while accelerating on high friction (friction, speed, offset, torque drawn)."""
    from ..closed_loop.config import config_for
    from ..vehicle.manoeuvres import double_lane_change, make_scenario, scenario, straight

    spec = scenario("stability_launch_brake")
    rngs = [case_rng(seed, start + i, stream=3) for i in range(n)]
    dlc = np.array([r.uniform() < 0.5 for r in rngs])
    mu = np.array(
        [r.uniform(0.6, 1.0) if d else r.uniform(0.2, 0.5) for r, d in zip(rngs, dlc, strict=True)]
    )
    scale = _uniform(rngs, 0.7, 1.15)  # factor on the manoeuvre's driver torques
    speed = _uniform(rngs, 8.0, 12.0)  # m/s, the double lane change's entry speed
    offset = _uniform(rngs, 0.0, 3.5)  # m: DLC lateral offset, or launch start offset / 7
    scs = []
    for i in range(n):
        if dlc[i]:
            sc = make_scenario(
                mu[i],
                speed[i],
                double_lane_change(20.0, offset[i]),
                ([0.0], [speed[i]]),
                torque=(
                    [0.0, 0.5, 1.0, 5.0, 5.5],
                    [0.0, 0.0, 2800.0 * scale[i], 2800.0 * scale[i], 0.0],
                ),
            )
        else:
            t1, t2 = 1500.0 * scale[i], -1800.0 * scale[i]
            sc = make_scenario(
                mu[i],
                2.0,
                straight(),
                ([0.0], [2.0]),
                torque=([0.0, 0.5, 3.5, 4.0, 7.0, 7.5], [0.0, t1, t1, t2, t2, 0.0]),
                Y0=offset[i] / 7.0,
            )
        scs.append(sc)
    stacked = jax.tree.map(lambda *x: np.stack(x), *scs)
    cols = {
        "case": np.arange(start, start + n),
        "dlc": dlc,
        "mu": mu,
        "torque_scale": scale,
        "speed": speed,
        "offset": offset,
    }
    return LoopCases(config_for(spec), stacked, spec.n_steps, cols)


for _name, _objectives in (("cruise", "LST + YRT"), ("stability", "VSC + WSC")):
    register_family(
        Family(
            f"{_name}_step",
            "step",
            f"single control steps of the {_name} example ({_objectives}) at operating "
            f"points over its envelope (ENVELOPES[{_name!r}])",
            functools.partial(_vehicle_steps, _name),
            ("horizon", "formulation", "groups", "ranges", "dtype"),
            _name,
        )
    )
register_family(
    Family(
        "generated",
        "step",
        "a random two-objective problem (generate.random_problem) with its initial "
        "state and references drawn per case",
        _generated_steps,
        ("n_objectives", "horizon", "structure_seed", "dtype"),
    )
)
register_family(
    Family(
        "cruise_lane_change",
        "loop",
        "the cruise lane change (16 s) with friction 0.5..1, speeds x0.7..1.15 and "
        "lane offsets 1.5..3.5 m drawn per case (an offset asking over 0.95 mu g of "
        "lateral acceleration scaled down to it)",
        _cruise_manoeuvres,
        ("dtype",),
        "cruise",
    )
)
register_family(
    Family(
        "stability_manoeuvres",
        "loop",
        "the stability example's launch and brake (friction 0.2..0.5, torques x0.7..1.15) "
        "or double lane change (friction 0.6..1, 8..12 m/s), 9 s, drawn per case",
        _stability_manoeuvres,
        ("dtype",),
        "stability",
    )
)
