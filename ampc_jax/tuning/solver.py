"""Gradient tuning of the solver's speed: rho scales and over-relaxation by unrolled ADMM.

The numbers tuned are Local Explicit's :class:`~ampc_jax.admm.params.SolverParams`
(``rho``: a factor on eq.opt_ro's rho_j* per objective; ``relaxation``: the
over-relaxation alpha), parametrised so that every value of the parameters
is admissible::

    rho_j = exp(theta_j)            (theta_j = log rho scale, j = 1..J)
    alpha = 2 sigmoid(theta_alpha)  (alpha in (0, 2); theta_alpha = 0 is alpha = 1)

The loss is the normalised error of K unrolled iterations from a cold start
(:meth:`LocalExplicit.solve_fixed`, ``lax.scan``, K static) against the
integrated optimum U* (Clarabel on the condensed QP, :func:`solve_reference`),
averaged over a training batch of a scenario family::

    L(theta) = 1/n sum_i ||U_K,i(theta) - U*_i||^2 / (||U*_i||^2 + s)

with U the whole horizon's inputs (N_p x n_u) and s (``scale``, default
N_p n_u, i.e. one unit per input and step) keeping small optima from
dominating. Minimised with Adam (optax) by the tuners' one loop
(:func:`~ampc_jax.tuning.fit.fit`); the update step is jitted and the cases
vmapped. Fewer unrolled iterations to land close is what fewer
iterations to tolerance means for the while-loop runner: the result is then
evaluated on held-out cases (another seed, optionally another horizon) by
iterations to eq.Convergence's tolerance (:func:`evaluate_points`), beside
eq.opt_ro's defaults (rho scale 1, alpha 1) and the best point of a grid of
common rho scales, with each point's worst first-step error against Clarabel.
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..admm.params import SolverParams
from ..formulations import PAPER_ITERATION, formulation
from ..problem.data import ProblemData
from ..problem.topology import Topology
from ..reference import reference_inputs as batch_reference
from ..validation import check_count
from ..vehicle.examples import example
from .fit import FitSpec, fit

__all__ = [
    "GRID_SCALES",
    "LOSSES",
    "SolverTuning",
    "Theta",
    "batch_params",
    "evaluate_points",
    "evaluation_verdicts",
    "pairs_program",
    "point_row",
    "reference_inputs",
    "residual_loss",
    "theta_of",
    "tune_solver",
    "unpack",
    "unrolled_loss",
]

LOSSES = ("error", "log", "residual")
"""Forms of the unrolled loss (:func:`unrolled_loss`)."""

GRID_SCALES = tuple(float(x) for x in np.geomspace(0.03, 30.0, 13))
"""The common rho scales of the grid baseline (every objective the same factor, alpha 1)."""


class Theta(NamedTuple):
    """The unconstrained tuning variables: log rho scale per objective, relaxation logit."""

    log_rho: Any  # (J,)
    relaxation_logit: Any  # ()


class SolverTuning(NamedTuple):
    """What :func:`tune_solver` found.

    rho_scale : tuned factor on eq.opt_ro's rho_j*, one per objective.
    relaxation : tuned over-relaxation alpha in (0, 2).
    history : one dict per Adam step (``step``, ``loss``, ``rho_scale``, ``relaxation``).
    evaluation : held-out evaluation (:func:`evaluate_points`), per held-out set.
    settings : how the run was made (family, cases, steps, iterations, lr, seeds, ...).
    """

    rho_scale: tuple[float, ...]
    relaxation: float
    history: list[dict[str, Any]]
    evaluation: dict[str, Any]
    settings: dict[str, Any]


def unpack(theta: Theta) -> tuple[Any, Any]:
    """(rho scale, alpha) = (exp(theta_rho), 2 sigmoid(theta_alpha))."""
    return jnp.exp(theta.log_rho), 2.0 * jax.nn.sigmoid(theta.relaxation_logit)


def theta_of(rho_scale: Any, relaxation: float, n_objectives: int, dtype: Any = None) -> Theta:
    """The :class:`Theta` of a rho scale (float or one per objective) and alpha in (0, 2)."""
    dt = jnp.result_type(float) if dtype is None else dtype
    r = np.broadcast_to(np.asarray(rho_scale, float), (int(n_objectives),))
    a = float(relaxation) / 2.0
    return Theta(jnp.asarray(np.log(r), dt), jnp.asarray(np.log(a / (1.0 - a)), dt))


def reference_inputs(topology: Topology, data: ProblemData) -> np.ndarray:
    """U* (n, N_p, n_u): the integrated optimum of each case (Clarabel), float64
    (:func:`ampc_jax.reference.reference_inputs`).

    ValueError when a case has no usable reference (infeasible or failed)."""
    out = batch_reference(topology, data)
    bad = np.flatnonzero(~np.all(np.isfinite(out), axis=(1, 2)))
    if bad.size:
        raise ValueError(f"cases: case {int(bad[0])} has no reference optimum")
    return out


def unrolled_loss(
    solver: Any,
    theta: Theta,
    data: ProblemData,
    u_star: Any,
    iterations: int,
    scale: float,
    loss: str = "error",
    tol: float = 1.0,
) -> Any:
    """L(theta) = mean_i e_i, e_i = ||U_K,i - U*_i||^2 / (||U*_i||^2 + s), K = ``iterations``.

    ``loss="log"``: mean_i log(e_i + 1e-12) instead, the geometric mean of the
    errors (every case's convergence rate counts alike, however close it lands);
    ``loss="residual"``: :func:`residual_loss` at tolerance ``tol`` (``u_star``
    and ``scale`` unused).
    ``data`` and ``u_star`` (n, N_p, n_u) carry the cases on axis 0; each case is
    solved from a cold start by K iterations of ``solver.solve_fixed``.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    if loss == "residual":
        return residual_loss(solver, theta, data, iterations, tol)
    rho, alpha = unpack(theta)
    dt = u_star.dtype
    zero = jnp.zeros((), dt)
    params = SolverParams(rho, alpha, zero, zero, zero)

    def one(d: ProblemData, us: Any) -> Any:
        u = solver.solve_fixed(d, iterations, params).u
        return jnp.sum((u - us) ** 2) / (jnp.sum(us**2) + scale)

    e = jax.vmap(one)(data, u_star)
    return jnp.mean(jnp.log(e + 1e-12)) if loss == "log" else jnp.mean(e)


def residual_loss(
    solver: Any,
    theta: Theta,
    data: ProblemData,
    iterations: int,
    tol: float,
    temperature: float = 2.0,
) -> Any:
    """A smooth count of the iterations that have not met eq.Convergence, per iteration:

        L = 1/(n K) sum_i sum_k sigmoid(log(m_ik) / tau),
        m_ik = max_j max(||r_j||^2, ||s_j||^2)_ik / tol

    (tau = ``temperature``), i.e. the fraction of the K unrolled iterations still
    above the tolerance, what the while loop's iteration count is. Plain ADMM only.
    """
    if solver.anderson:
        raise ValueError("loss: 'residual' unrolls plain ADMM; use anderson 0")
    rho, alpha = unpack(theta)
    dt = rho.dtype
    zero = jnp.zeros((), dt)
    params = SolverParams(rho, alpha, zero, zero, zero)

    def one(d: ProblemData) -> Any:
        setup = solver.setup(d, params)

        def body(st: Any, _: Any) -> tuple[Any, Any]:
            st = solver.step(setup, st)
            m = jnp.maximum(jnp.max(st.primal), jnp.max(st.dual)) / tol
            return st, jax.nn.sigmoid(jnp.log(m + 1e-30) / temperature)

        _, seen = jax.lax.scan(body, solver.init(setup), None, length=int(iterations))
        return jnp.mean(seen)

    return jnp.mean(jax.vmap(one)(data))


def batch_params(n: int, J: int, rho: Any, alpha: float, tol: float, dt: Any) -> SolverParams:
    """n copies of one parameter point: rho scales (a float or (J,)), alpha, eps_r = eps_s."""
    r = jnp.broadcast_to(jnp.asarray(np.broadcast_to(np.asarray(rho, float), (J,)), dt), (n, J))
    full = lambda v: jnp.full((n,), v, dt)  # noqa: E731
    return SolverParams(r, full(alpha), full(tol), full(tol), full(0.0))


def point_row(
    name: str, out: Any, u0_star: np.ndarray, rho_scale: Any, relaxation: float
) -> dict[str, Any]:
    """One evaluation row of a point solved on every case (``out``: the pairs'
    result): iterations to tolerance (median, p95, max), the share converged,
    and the worst first-step error max_i ||u0_i - u0*_i|| (``u0_error``) and
    max_i ||u0_i - u0*_i|| / (||u0*_i|| + 1) (``u0_rel_error``)."""
    it = np.asarray(out.iterations)
    err = np.linalg.norm(np.asarray(out.u0, float) - u0_star, axis=1)
    return {
        "name": name,
        "rho_scale": [float(x) for x in rho_scale],
        "relaxation": float(relaxation),
        "median": float(np.median(it)),
        "p95": float(np.percentile(it, 95)),
        "max": int(np.max(it)),
        "converged": float(np.mean(np.asarray(out.converged))),
        "u0_error": float(np.max(err)),
        "u0_rel_error": float(np.max(err / (np.linalg.norm(u0_star, axis=1) + 1.0))),
    }


def pairs_program(solver: Any) -> Any:
    """One compiled program solving (case, point) pairs with ``solver`` to
    tolerance (:func:`~ampc_jax.sweep.engine.solve_pairs`): ``f(data, params)``."""
    from ..sweep.engine import solve_pairs

    return jax.jit(lambda d, p: solve_pairs(solver, d, p)[0])


def evaluate_points(
    solver: Any,
    data: ProblemData,
    u_star: np.ndarray,
    points: dict[str, tuple[Any, float]],
    *,
    tol: float = 1.0,
    grid: tuple[float, ...] | None = GRID_SCALES,
) -> dict[str, Any]:
    """Iterations to tolerance on the cases ``data`` for each named (rho scale, alpha).

    Every point is solved by ``solver`` (its while loop, cold start, eq.Convergence
    with eps_r = eps_s = ``tol``) on every case (:func:`~ampc_jax.sweep.solve_pairs`).
    With ``grid`` the common rho scales of the grid (alpha 1) are solved too and
    the one of lowest median iterations is added as ``"grid best"``. Returns
    ``{"rows": [{name, rho_scale, relaxation, median, p95, max, converged,
    u0_error, u0_rel_error}, ...], "grid": [...]}``; ``u0_error`` is the worst
    first-step error max_i ||u0_i - u0*_i|| over the cases, ``u0_rel_error``
    the worst of ||u0_i - u0*_i|| / (||u0*_i|| + 1).
    """
    J = solver.topology.n_objectives
    n = int(u_star.shape[0])
    dt = jax.tree.leaves(data)[0].dtype
    run = pairs_program(solver)
    u0_star = np.asarray(u_star)[:, 0, :]

    def measure(name: str, rho: Any, alpha: float) -> dict[str, Any]:
        r = np.broadcast_to(np.asarray(rho, float), (J,))
        return point_row(name, run(data, batch_params(n, J, r, alpha, tol, dt)), u0_star, r, alpha)

    rows = [measure(name, rho, alpha) for name, (rho, alpha) in points.items()]
    grid_rows = []
    if grid:
        grid_rows = [measure(f"grid {s:.3g}", s, 1.0) for s in grid]
        best = min(grid_rows, key=lambda r: (r["median"], r["p95"]))
        rows.insert(1 if rows else 0, {**best, "name": "grid best"})
    return {"cases": n, "tol": float(tol), "rows": rows, "grid": grid_rows}


def tune_solver(
    family_name: str = "cruise_step",
    *,
    cases: int = 32,
    steps: int = 100,
    iterations: int = 20,
    lr: float = 0.05,
    seed: int = 0,
    heldout_seed: int = 1,
    heldout_cases: int = 64,
    heldout_horizon: int | None = None,
    horizon: int | None = None,
    anderson: int = 0,
    scale: float | None = None,
    loss: str = "error",
    init_rho_scale: Any = 1.0,
    init_relaxation: float = 1.0,
    tol: float = 1.0,
    max_iter: int = 1000,
    dtype: Any = None,
    evaluate: bool = True,
    progress: bool | None = None,
) -> SolverTuning:
    """Tune Local Explicit's rho scales and alpha on a step family by unrolled ADMM.

    ``cases`` training cases of ``family_name`` under ``seed`` (option
    ``horizon``), ``steps`` Adam steps of learning rate ``lr`` on
    :func:`unrolled_loss` with K = ``iterations``, from (``init_rho_scale``,
    ``init_relaxation``) (default eq.opt_ro's choice, alpha 1). ``anderson``:
    the Anderson memory of the solver tuned (and evaluated); ``scale``: s of the
    loss (default N_p n_u); ``loss``: ``"error"`` or ``"log"`` (:func:`unrolled_loss`). With ``evaluate``, ``heldout_cases`` cases under
    ``heldout_seed`` (and, if given, as many at horizon ``heldout_horizon``)
    are solved to tolerance ``tol`` (cap ``max_iter``) at eq.opt_ro's defaults,
    the grid's best common scale and the tuned point (:func:`evaluate_points`).
    ``progress``: tqdm's ``disable`` negated (None: on a terminal only).
    """
    from ..sweep.families import family

    fam = family(family_name)
    if fam.kind != "step":
        raise ValueError(f"family: {fam.name!r} is a {fam.kind} family; expected a step family")
    for name, v in (("steps", steps), ("iterations", iterations), ("cases", cases)):
        check_count(v, name)
    # the unrolled step's compile is most of a tuning run's time, its run is not
    # (bench/bench_compile.py, "tune solver"): a closed loop's compiler options
    from ..closed_loop.compile import loop_compiler_options

    spec = FitSpec(
        int(steps),
        lr,
        desc="tune",
        progress=progress,
        compiler_options=loop_compiler_options() or None,
    )
    opts: dict[str, Any] = {} if horizon is None else {"horizon": int(horizon)}
    if dtype is not None:
        opts["dtype"] = dtype
    t0 = time.perf_counter()
    train = fam.sample(int(cases), seed=int(seed), **opts)
    T = train.topology
    dt = jax.tree.leaves(train.data)[0].dtype
    solver = formulation(
        "local_explicit", T, anderson=int(anderson), max_iter=int(max_iter), **PAPER_ITERATION
    )
    u_star = jnp.asarray(reference_inputs(T, train.data), dt)
    s = float(T.horizon * T.n_u) if scale is None else float(scale)
    theta = theta_of(init_rho_scale, init_relaxation, T.n_objectives, dt)
    K = int(iterations)

    def record(step: int, th: Theta, value: Any, _: Any) -> dict[str, Any]:
        rho, alpha = unpack(th)
        return {
            "step": step,
            "loss": float(value),
            "rho_scale": [float(x) for x in np.asarray(rho)],
            "relaxation": float(alpha),
        }

    run = fit(
        lambda th: unrolled_loss(solver, th, train.data, u_star, K, s, loss, float(tol)),
        theta,
        spec,
        record=record,
    )
    history = run.history
    rho, alpha = unpack(run.theta)
    rho_scale = tuple(float(x) for x in np.asarray(rho))
    relaxation = float(alpha)
    settings = {
        "family": fam.name,
        "cases": int(cases),
        "steps": int(steps),
        "iterations": K,
        "lr": float(lr),
        "seed": int(seed),
        "heldout_seed": int(heldout_seed),
        "heldout_cases": int(heldout_cases),
        "horizon": T.horizon,
        "heldout_horizon": heldout_horizon,
        "anderson": int(anderson),
        "scale": s,
        "loss": loss,
        "tol": float(tol),
        "objectives": list(T.objective_names),
        "example": None if train.config is None else train.config.example,
        "train_seconds": time.perf_counter() - t0,
    }
    evaluation: dict[str, Any] = {}
    if evaluate:
        points = {"eq.opt_ro": (1.0, 1.0)}
        if settings["example"]:  # what simulate and solve run without --params
            d = example(settings["example"]).solver_defaults
            points[DEFAULTS_ROW] = (d.get("rho_scale", 1.0), float(d.get("relaxation", 1.0)))
        points["tuned"] = (rho_scale, relaxation)
        sets = [(f"seed {heldout_seed}, N_p {T.horizon}", horizon)]
        if heldout_horizon is not None and int(heldout_horizon) != T.horizon:
            sets.append((f"seed {heldout_seed}, N_p {int(heldout_horizon)}", heldout_horizon))
        for label, hz in sets:
            o = dict(opts)
            if hz is not None:
                o["horizon"] = int(hz)
            held = fam.sample(int(heldout_cases), seed=int(heldout_seed), **o)
            sv = (
                solver
                if held.topology == T
                else formulation(
                    "local_explicit",
                    held.topology,
                    anderson=int(anderson),
                    max_iter=int(max_iter),
                    **PAPER_ITERATION,
                )
            )
            us = reference_inputs(held.topology, held.data)
            ev = evaluate_points(sv, held.data, us, points, tol=tol)
            if anderson:
                plain = formulation(
                    "local_explicit", held.topology, max_iter=int(max_iter), **PAPER_ITERATION
                )
                extra = evaluate_points(
                    plain,
                    held.data,
                    us,
                    {"eq.opt_ro, plain ADMM": (1.0, 1.0)},
                    tol=tol,
                    grid=None,
                )
                ev["rows"].insert(0, extra["rows"][0])
            evaluation[label] = ev
    return SolverTuning(rho_scale, relaxation, history, evaluation, settings)


DEFAULTS_ROW = "example defaults"
"""The evaluation row of the example's ``solver_defaults`` (rho scale, alpha):
what ``ampc simulate`` and ``ampc solve`` run when no params.json is given."""


def evaluation_verdicts(evaluation: dict[str, Any]) -> list[str]:
    """One line per held-out set: the tuned point against the command's own
    defaults (:data:`DEFAULTS_ROW`; eq.opt_ro's choice for a problem of no
    example), saying when the tuned point is worse.

    Order: fewer cases converged is worse; then the median iterations, then
    the p95 (lower is better)."""
    lines = []
    for label, ev in evaluation.items():
        rows = {r["name"]: r for r in ev["rows"]}
        tuned = rows.get("tuned")
        ref = rows.get(DEFAULTS_ROW) or rows.get("eq.opt_ro")
        if tuned is None or ref is None:
            continue
        key_t = (-tuned["converged"], tuned["median"], tuned["p95"])
        key_r = (-ref["converged"], ref["median"], ref["p95"])
        word = "worse than" if key_t > key_r else "as good as" if key_t == key_r else "better than"
        line = (
            f"held-out {label}: tuned is {word} the {ref['name']} (median {tuned['median']:.1f} "
            f"vs {ref['median']:.1f} iterations, p95 {tuned['p95']:.1f} vs {ref['p95']:.1f}, "
            f"converged {tuned['converged']:.2f} vs {ref['converged']:.2f})"
        )
        if key_t > key_r:
            line += "; keep the defaults (run without this params.json)"
        lines.append(line)
    return lines


def evaluation_table(evaluation: dict[str, Any]) -> str:
    """The held-out evaluation as a text table (one block per held-out set)."""
    lines = []
    for label, ev in evaluation.items():
        lines.append(f"held-out {label}: {ev['cases']} cases, tol {ev['tol']:g}")
        lines.append(
            f"  {'point':<24} {'rho scale':<20} {'alpha':>6} {'median':>7} {'p95':>7} "
            f"{'max':>5} {'conv':>5} {'max|du0|':>9} {'rel':>8}"
        )
        for r in ev["rows"]:
            rs = ", ".join(f"{x:.3g}" for x in r["rho_scale"])
            lines.append(
                f"  {r['name']:<24} {rs:<20} {r['relaxation']:>6.3f} {r['median']:>7.1f} "
                f"{r['p95']:>7.1f} {r['max']:>5d} {r['converged']:>5.2f} "
                f"{r['u0_error']:>9.3g} {r['u0_rel_error']:>8.2g}"
            )
    return "\n".join(lines)
