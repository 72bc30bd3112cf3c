"""Training a learned start (:mod:`ampc_jax.admm.learned_start`) with optax.

After Sambharya et al. (JMLR 2024): the network h_w is first fitted to the
fixed points of the training cases (regression of its outputs on the
standardised targets: "pretraining"), then trained through K unrolled
iterations of the solver *as the consuming command runs it* (its rho scales,
relaxation, Anderson memory, KKT strategy and dtype), together with a
per-iteration schedule of k (rho_i, alpha_i) (Sambharya and Stellato)::

    L(w, s) = 1/n sum_i ||U_K,i(w, s) - U*_i||^2 / (||U*_i||^2 + c)      ("error")

the fixed-point residual after K iterations, log(sum_j ||r_j||^2 + ||s_j||^2) /
eps) (``"fixed_point"``, Sambharya et al.'s), or the smooth count of the K
iterations whose residuals are still above the tolerance (``"residual"``,
:func:`~ampc_jax.tuning.solver.residual_loss`'s form),
U*_i the fixed point (the solver run far below the command's tolerance), c =
N_p n_u. The schedule is parametrised as rho_i = exp(theta_i) times the steady
rho and alpha_i = 2 sigmoid(phi_i).

Two training sets (:data:`~ampc_jax.admm.learned_start.KINDS`): a step family
(``cruise_step``, ``stability_step``) trains a ``"step"`` network on its cases;
a loop family (``cruise_lane_change``, ``stability_manoeuvres``) runs its
closed loops with today's warm start and trains a ``"loop"`` network on
every control step's data and previous iterate.

Evaluation (:func:`evaluate_starts`): on held-out cases, iterations to the
command's tolerance (the while loop, :func:`~ampc_jax.sweep.engine.solve_pairs`)
and the worst first-step error against Clarabel, for eq.opt_ro's cold start
(plain ADMM, rho scale 1, alpha 1), the command's cold start and the learned
start; closed loops (:func:`evaluate_loops`) by the iterations per control
step and e_sub against today's warm start.
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..admm.learned_start import (
    SCHEDULE_MAX,
    LearnedStart,
    StartArrays,
    StartModel,
    box_coordinates,
    mlp,
    problem_features,
)
from ..admm.params import SolverParams
from ..admm.runners import loop_parts
from ..validation import check_choice, check_count, check_positive
from .fit import FitSpec, Validation, fit
from .solver import batch_params
from .start_evaluation import (
    evaluate_loops,
    evaluate_model,
    evaluate_starts,
    start_table,
)

__all__ = [
    "START_LOSSES",
    "StartTuning",
    "command_settings",
    "evaluate_loops",
    "evaluate_starts",
    "fixed_points",
    "start_table",
    "tune_warm_start",
]

START_LOSSES = ("error", "fixed_point", "residual")
"""Forms of the unrolled loss (module docstring)."""

BOUND_MARGIN = 0.02
"""Where an input of the training optimum is at a bound, the pretraining loss
asks for a prediction this fraction of the range beyond it (a hinge)."""

VALIDATE_EVERY = 25
"""Unrolled Adam steps between two validations (iterations to tolerance on the
validation split: mean, then median, then p95 decide)."""

TARGET_TOL = 1e-12
"""eps_r = eps_s of the fixed points the network is fitted to (squared, the rows'
units; float64): far below the commands' 1 Nm^2, so a target is the fixed point."""


class StartTuning(NamedTuple):
    """What :func:`tune_warm_start` made.

    model : the trained :class:`~ampc_jax.admm.learned_start.StartModel`.
    history : one dict per Adam step (``phase``: pretrain or unrolled, ``step``, ``loss``).
    evaluation : the held-out evaluation, per held-out set.
    settings : how it was made, including ``tuned_for`` (the solver settings).
    """

    model: StartModel
    history: list[dict[str, Any]]
    evaluation: dict[str, Any]
    settings: dict[str, Any]


def command_settings(
    example_name: str | None,
    *,
    rho_scale: Any = None,
    relaxation: float | None = None,
    anderson: int | None = None,
) -> dict[str, Any]:
    """The solver settings the consuming commands run for ``example_name`` (its
    ``solver_defaults``: rho scale per objective, relaxation, Anderson), each
    replaced where given; eq.opt_ro's plain iteration for a problem of no example."""
    from ..vehicle.examples import example

    d = example(example_name).solver_defaults if example_name else {}
    rs = d.get("rho_scale", 1.0) if rho_scale is None else rho_scale
    return {
        "rho_scale": [float(x) for x in np.atleast_1d(np.asarray(rs, float))],
        "relaxation": float(d.get("relaxation", 1.0) if relaxation is None else relaxation),
        "anderson": int(d.get("anderson", 0) if anderson is None else anderson),
    }


def fixed_points(solver: Any, data: Any, params: SolverParams) -> tuple[np.ndarray, Any, Any]:
    """(U* (n, N_p, n_u), the final states, converged (n,)): every case of ``data``
    solved by ``solver`` (vmapped while loop) at ``params``' tolerances."""
    res = jax.jit(jax.vmap(solver.solve))(data, params)
    return np.asarray(res.u), res.state, np.asarray(res.converged)


def _scales(x: np.ndarray, floor_rel: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Per-column mean and a scale: the standard deviation, floored at ``floor_rel``
    of the largest (a column that never moves keeps a finite scale)."""
    m = x.mean(0)
    s = x.std(0)
    top = float(s.max()) if s.size else 1.0
    return m, np.maximum(s, floor_rel * top if top > 0 else 1.0)


def _init_layers(key: Any, sizes: list[int], dt: Any) -> tuple:
    layers = []
    for k, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        key, sub = jax.random.split(key)
        last = k == len(sizes) - 2
        W = jnp.zeros((a, b), dt) if last else jax.random.normal(sub, (a, b), dt) / np.sqrt(a)
        layers.append((W, jnp.zeros((b,), dt)))
    return tuple(layers)


class _Train(NamedTuple):
    """The trainable variables: the network and the schedule's logs and logits."""

    layers: tuple
    log_rho: Any  # (k, J)
    relaxation_logit: Any  # (k,)


def _arrays(v: _Train, fixed: StartArrays) -> StartArrays:
    return fixed._replace(
        layers=v.layers,
        schedule_rho=jnp.exp(v.log_rho),
        schedule_relaxation=2.0 * jax.nn.sigmoid(v.relaxation_logit),
    )


def _cases(fam: Any, n: int, seed: int, opts: dict[str, Any]) -> Any:
    return fam.sample(int(n), seed=int(seed), **opts)


def _loop_pairs_of(cases: Any, dtype: Any) -> tuple[Any, Any, Any]:
    """(config, per-step data, per-step previous iterate) of every control step of a
    loop family's closed loops, run with today's warm start (no shadow)."""
    from dataclasses import replace

    from ..closed_loop.loop import simulate_batch

    cfg = replace(cases.config, shadow=False)
    log = simulate_batch(cfg, cases.scenarios, cases.n_steps, dtype=dtype)
    flat = lambda x: jnp.reshape(x, (-1, *x.shape[2:]))  # noqa: E731
    return cfg, jax.tree.map(flat, log.data), jax.tree.map(flat, log.warm)


class _TrainingSet(NamedTuple):
    """The training pairs of a family: what a network reads and what it is fitted to.

    kind : ``"step"`` or ``"loop"``; inner : Local Explicit at the command's settings.
    data : the steps' ProblemData (leading pair axis); prev : the previous
        iterates (``"loop"``) or None; fx : the fixed points' states; u_star :
        (n, N_p, n_u) their inputs; settings : :func:`command_settings`; rho : (J,);
    tol : the command's tolerance; example : the family's example (or None).
    """

    kind: str
    inner: Any
    data: Any
    prev: Any
    fx: Any
    u_star: Any
    settings: dict[str, Any]
    rho: np.ndarray
    tol: float
    example: str | None


class _Scaled(NamedTuple):
    """The standardised regression problem of the pretraining phase and the
    network's fixed numbers (its input and output maps, the schedule's start)."""

    fixed: StartArrays
    var: _Train
    X: Any
    Y: Any
    M: Any
    at_lo: Any
    at_hi: Any
    lo_y: Any
    hi_y: Any
    sizes: dict[str, Any]


def _check_settings(**kw: Any) -> None:
    """The counts, the schedule, the loss and the widths of :func:`tune_warm_start`."""
    for name, low in (
        ("cases", 1),
        ("pretrain_steps", 0),
        ("steps", 0),
        ("iterations", 1),
        ("schedule", 0),
        ("batch", 1),
        ("heldout_cases", 1),
    ):
        check_count(kw[name], name, low)
    if kw["schedule"] > SCHEDULE_MAX:
        raise ValueError(
            f"schedule: expected at most {SCHEDULE_MAX} iterations, got {kw['schedule']}"
        )
    check_choice(kw["loss"], "loss", START_LOSSES)
    check_positive(kw["lr"], "lr")
    hidden = kw["hidden"]
    if not hidden or any(int(h) < 1 for h in hidden):
        raise ValueError(f"hidden: expected layer widths >= 1, got {hidden!r}")


def _training_set(
    fam: Any,
    train: Any,
    dt: Any,
    *,
    rho_scale: Any,
    relaxation: float | None,
    anderson: int | None,
    tol: float | None,
    max_iter: int,
) -> _TrainingSet:
    """Phase 1: the pairs (a step family's cases; a loop family's control steps under
    today's warm start) and their fixed points, far below the command's tolerance
    (:data:`TARGET_TOL`), from the same start a solve has; pairs that did not
    reach theirs are dropped (ValueError when more than half)."""
    from ..closed_loop.controller import controller_for
    from ..formulations import PAPER_ITERATION, formulation

    kind = "loop" if fam.kind == "loop" else "step"
    if kind == "loop":
        cfg, data, prev = _loop_pairs_of(train, dt)
        T = controller_for(cfg).topology
        example_name = cfg.example
    else:
        cfg, data, prev = train.config, train.data, None
        T = train.topology
        example_name = None if cfg is None else cfg.example
    st = command_settings(
        example_name, rho_scale=rho_scale, relaxation=relaxation, anderson=anderson
    )
    if tol is None:
        tol = float(cfg.tol_primal) if cfg is not None else 1e-6
    J = T.n_objectives
    rho = np.broadcast_to(np.asarray(st["rho_scale"], float), (J,))
    inner = formulation(
        "local_explicit", T, anderson=st["anderson"], max_iter=int(max_iter), **PAPER_ITERATION
    )
    n = int(jax.tree.leaves(data)[0].shape[0])
    tight = batch_params(n, J, rho, st["relaxation"], TARGET_TOL, dt)
    deep = formulation(
        "local_explicit", T, anderson=st["anderson"], max_iter=20 * int(max_iter), **PAPER_ITERATION
    )
    if kind == "loop":
        res = jax.jit(jax.vmap(deep.solve))(data, tight, prev)
        u_star, fx, conv = np.asarray(res.u), res.state, np.asarray(res.converged)
    else:
        u_star, fx, conv = fixed_points(deep, data, tight)
    keep = np.flatnonzero(conv)
    if keep.size < max(1, n // 2):
        raise ValueError(
            f"cases: only {keep.size} of {n} training cases reached the fixed point "
            f"({TARGET_TOL:g}); the family's problems are too hard for this solver"
        )
    take = lambda tree: jax.tree.map(lambda x: jnp.asarray(x)[keep], tree)  # noqa: E731
    return _TrainingSet(
        kind=kind,
        inner=inner,
        data=take(data),
        prev=None if prev is None else take(prev),
        fx=take(fx),
        u_star=jnp.asarray(u_star[keep], dt),
        settings=st,
        rho=rho,
        tol=float(tol),
        example=example_name,
    )


def _scaled(
    ts: _TrainingSet, hidden: tuple[int, ...], schedule: int, seed: int, dt: Any
) -> _Scaled:
    """Phase 2: the network's inputs (the step's data, and a ``"loop"`` network's
    previous iterate) and outputs (a ``"step"`` network's inputs as positions in
    their ranges; a ``"loop"`` network's correction of the previous iterate),
    standardised; the initial weights (a zero last layer) and schedule."""
    inner, data, n = ts.inner, ts.data, int(ts.u_star.shape[0])
    T = inner.topology
    J = T.n_objectives
    feats = np.asarray(jax.vmap(problem_features)(data), np.float64)
    x_point = np.asarray(jax.vmap(inner.point)(ts.fx), np.float64)
    if ts.kind == "loop":
        p_point = np.asarray(jax.vmap(inner.point)(ts.prev), np.float64)
        feats = np.concatenate([feats, p_point], axis=1)
        target = x_point - p_point
        o_mean = np.zeros(target.shape[1])
        _, o_scale = _scales(target)
        mask = (np.abs(target).max(0) > 0).astype(float)
    else:
        target = np.asarray(jax.vmap(box_coordinates)(ts.u_star, data), np.float64).reshape(n, -1)
        box = np.asarray(jnp.isfinite(data.lb) & jnp.isfinite(data.ub)).reshape(n, -1)
        o_mean, o_scale = _scales(target)
        mask = np.ones(target.shape[1])
    f_mean = feats.mean(0)
    f_std = feats.std(0)
    f_scale = np.where(f_std > 1e-9 * (1.0 + np.abs(f_mean)), f_std, 1.0)
    sizes = [feats.shape[1], *(int(h) for h in hidden), target.shape[1]]
    relaxation = ts.settings["relaxation"]
    fixed = StartArrays(
        layers=(),
        input_mean=jnp.asarray(f_mean, dt),
        input_scale=jnp.asarray(f_scale, dt),
        out_mean=jnp.asarray(o_mean, dt),
        out_scale=jnp.asarray(o_scale, dt),
        out_mask=jnp.asarray(mask, dt),
        schedule_rho=jnp.ones((schedule, J), dt),
        schedule_relaxation=jnp.full((schedule,), relaxation, dt),
    )
    a0 = relaxation / 2.0
    var = _Train(
        _init_layers(jax.random.PRNGKey(int(seed)), sizes, dt),
        jnp.zeros((schedule, J), dt),
        jnp.full((schedule,), np.log(a0 / (1.0 - a0)), dt),
    )
    Y = jnp.asarray((target - o_mean) / o_scale, dt)
    if ts.kind == "step":
        # an input at its bound is met by any prediction beyond it (the start clips):
        # a hinge there, BOUND_MARGIN of the range beyond the bound, so that the
        # start's row is active (kkt_multipliers) rather than just inside
        at_lo = jnp.asarray(box & (target <= 1e-9), bool)
        at_hi = jnp.asarray(box & (target >= 1.0 - 1e-9), bool)
        lo_y = jnp.asarray((-BOUND_MARGIN - o_mean) / o_scale, dt)
        hi_y = jnp.asarray((1.0 + BOUND_MARGIN - o_mean) / o_scale, dt)
    else:
        at_lo = at_hi = jnp.zeros(Y.shape, bool)
        lo_y = hi_y = jnp.zeros(Y.shape[1:], dt)
    return _Scaled(
        fixed=fixed,
        var=var,
        X=jnp.asarray((feats - f_mean) / f_scale, dt).clip(-10.0, 10.0),
        Y=Y,
        M=jnp.asarray(mask, dt),
        at_lo=at_lo,
        at_hi=at_hi,
        lo_y=lo_y,
        hi_y=hi_y,
        sizes={"n_point": x_point.shape[1], "objectives": T.objective_names, "horizon": T.horizon},
    )


def _pretrain_loss(sc: _Scaled) -> Any:
    """The regression of the outputs on the fixed points (a hinge at the bounds)."""

    def loss(v: _Train, idx: Any) -> Any:
        y = jax.vmap(lambda x: mlp(v.layers, x))(sc.X[idx])
        e = jnp.where(
            sc.at_lo[idx],
            jnp.maximum(y - sc.lo_y, 0.0),
            jnp.where(sc.at_hi[idx], jnp.maximum(sc.hi_y - y, 0.0), y - sc.Y[idx]),
        )
        return jnp.sum(sc.M * e**2) / (jnp.sum(sc.M) * idx.shape[0])

    return loss


def _unrolled_loss(
    ts: _TrainingSet, sc: _Scaled, wrapper: Any, p_one: Any, loss: str, iterations: int
) -> Any:
    """The loss of K unrolled iterations of the wrapped solver (module docstring)."""
    T = ts.inner.topology
    scale_c = float(T.horizon * T.n_u)
    tol = ts.tol

    def one_case(arrays: StartArrays, d: Any, pv: Any, us: Any) -> Any:
        setup = wrapper.setup_with(d, p_one, arrays)
        s0 = wrapper.init(setup, pv)
        if loss == "error":
            s = wrapper.run_fixed(setup, s0, int(iterations))
            u = wrapper.result(setup, s).u
            return jnp.sum((u - us) ** 2) / (jnp.sum(us**2) + scale_c)
        if loss == "fixed_point":
            s = wrapper.run_fixed(setup, s0, int(iterations))
            return jnp.log(jnp.sum(s.primal + s.dual) / tol + 1e-12)
        carry, body, it_of = loop_parts(
            lambda x: wrapper.step(setup, x), s0, wrapper.anderson, wrapper.point, wrapper.at
        )

        def f(c: Any, _: Any) -> tuple[Any, Any]:
            c = body(c)
            x = it_of(c)
            m = jnp.maximum(jnp.max(x.primal), jnp.max(x.dual)) / tol
            return c, jax.nn.sigmoid(jnp.log(m + 1e-30) / 2.0)

        return jnp.mean(jax.lax.scan(f, carry, None, length=int(iterations))[1])

    def un_loss(v: _Train, idx: Any) -> Any:
        arrays = _arrays(v, sc.fixed)
        d = jax.tree.map(lambda x: x[idx], ts.data)
        us = ts.u_star[idx]
        if ts.prev is None:
            e = jax.vmap(lambda dd, uu: one_case(arrays, dd, None, uu))(d, us)
        else:
            pv = jax.tree.map(lambda x: x[idx], ts.prev)
            e = jax.vmap(lambda dd, pp, uu: one_case(arrays, dd, pp, uu))(d, pv, us)
        return jnp.mean(e)

    return un_loss


def _validation_score(
    ts: _TrainingSet, sc: _Scaled, wrapper: Any, p_one: Any, val: np.ndarray
) -> Any:
    """(mean, median, p95) of the iterations to tolerance on the validation split."""

    @jax.jit
    def val_iterations(arrays: StartArrays) -> Any:
        d = jax.tree.map(lambda x: x[val], ts.data)

        def one(dd: Any, pv: Any) -> Any:
            setup = wrapper.setup_with(dd, p_one, arrays)
            return wrapper.run(setup, wrapper.init(setup, pv)).iteration

        if ts.prev is None:
            return jax.vmap(lambda dd: one(dd, None))(d)
        return jax.vmap(one)(d, jax.tree.map(lambda x: x[val], ts.prev))

    def score(v: _Train) -> tuple[float, float, float]:
        it = np.asarray(val_iterations(_arrays(v, sc.fixed)), float)
        return float(np.mean(it)), float(np.median(it)), float(np.percentile(it, 95))

    return score


def tune_warm_start(
    family_name: str = "cruise_step",
    *,
    cases: int = 512,
    seed: int = 0,
    pretrain_steps: int = 1500,
    steps: int = 300,
    iterations: int = 6,
    schedule: int = 0,
    hidden: tuple[int, ...] = (64, 64),
    lr: float = 3e-3,
    unrolled_lr: float | None = None,
    batch: int = 256,
    loss: str = "error",
    rho_scale: Any = None,
    relaxation: float | None = None,
    anderson: int | None = None,
    tol: float | None = None,
    max_iter: int = 500,
    horizon: int | None = None,
    heldout_cases: int = 256,
    heldout_seed: int = 1,
    shifted_seed: int = 2,
    dtype: Any = None,
    evaluate: bool = True,
    progress: bool | None = None,
) -> StartTuning:
    """Train a learned start (and a schedule of ``schedule`` iterations) on a family.

    ``cases`` training cases of ``family_name`` under ``seed`` (a loop family:
    that many closed loops, every control step a training pair); the solver is
    Local Explicit with the consuming commands' settings (:func:`command_settings`
    of the family's example, each replaced where given; ``tol``: the example's
    closed-loop tolerance, 1 Nm^2, by default). ``pretrain_steps`` Adam steps of
    regression on the fixed points, then ``steps`` Adam steps on the unrolled
    loss (``loss``, K = ``iterations``), minibatches of ``batch`` cases, learning
    rate ``lr`` (cosine decay; ``unrolled_lr``, default ``lr / 30``, for the
    unrolled phase). With ``evaluate``: ``heldout_cases`` cases
    under ``heldout_seed``, and (step families) as many under ``shifted_seed``
    in the family's other friction and speed range (``ranges="shifted"``),
    by :func:`evaluate_starts`; loop families by :func:`evaluate_loops`.

    The phases: the training pairs and their fixed points
    (:func:`_training_set`), the standardised regression problem
    (:func:`_scaled`), pretraining and the unrolled phase (both by
    :func:`~ampc_jax.tuning.fit.fit`; the unrolled phase keeps the point of
    fewest validation iterations), then the evaluation.
    """
    from ..sweep.families import family

    fam = family(family_name)
    _check_settings(
        cases=cases,
        pretrain_steps=pretrain_steps,
        steps=steps,
        iterations=iterations,
        schedule=schedule,
        batch=batch,
        heldout_cases=heldout_cases,
        loss=loss,
        lr=lr,
        hidden=hidden,
    )
    t0 = time.perf_counter()
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    opts: dict[str, Any] = {}
    if "dtype" in fam.options:
        opts["dtype"] = dt
    if horizon is not None:
        if "horizon" not in fam.options:
            raise ValueError(f"horizon: family {fam.name!r} has no horizon option")
        opts["horizon"] = int(horizon)
    ts = _training_set(
        fam,
        _cases(fam, cases, seed, opts),
        dt,
        rho_scale=rho_scale,
        relaxation=relaxation,
        anderson=anderson,
        tol=tol,
        max_iter=max_iter,
    )
    sc = _scaled(ts, hidden, schedule, seed, dt)
    st, T, kind = ts.settings, ts.inner.topology, ts.kind
    n = int(ts.u_star.shape[0])
    wrapper = LearnedStart(
        ts.inner, StartModel.from_arrays(_arrays(sc.var, sc.fixed), kind, **sc.sizes)
    )
    p_one = SolverParams(
        jnp.asarray(ts.rho, dt),
        jnp.asarray(st["relaxation"], dt),
        *(jnp.asarray(v, dt) for v in (ts.tol, ts.tol, 0.0)),
    )
    history: list[dict[str, Any]] = []
    rng = np.random.default_rng(int(seed))
    # a validation split of the training cases picks the unrolled phase's point by
    # what it is for, iterations to the tolerance (its loss is only a proxy)
    n_val = max(1, min(n // 8, 512)) if n > 1 else 0
    n_fit = n - n_val
    bsize = min(int(batch), n_fit)
    score = _validation_score(ts, sc, wrapper, p_one, np.arange(n_fit, n))

    def batches(_: int) -> Any:
        return jnp.asarray(rng.choice(n_fit, bsize, replace=False))

    def phase(name: str) -> Any:
        return lambda k, v, value, aux: {"phase": name, "step": k, "loss": float(value)}

    rate = float(lr) / 30.0 if unrolled_lr is None else float(unrolled_lr)
    untrained = sc.var  # a "loop" network with its zero last layer is today's warm start
    pre = fit(
        _pretrain_loss(sc),
        sc.var,
        FitSpec(
            int(pretrain_steps),
            float(lr),
            0.05,
            finite_updates=True,
            desc="pretrain",
            progress=progress,
        ),
        batches=batches,
        select="last",
        record=phase("pretrain"),
        history=history,
    )
    validation = (
        Validation(
            score,
            VALIDATE_EVERY,
            lambda k, s: {"phase": "validation", "step": k, "iterations": s},
        )
        if n_val
        else None
    )
    un = fit(
        _unrolled_loss(ts, sc, wrapper, p_one, loss, iterations),
        pre.theta,
        FitSpec(int(steps), rate, 0.05, finite_updates=True, desc="unrolled", progress=progress),
        batches=batches,
        select="last",
        validation=validation,
        record=phase("unrolled"),
        history=history,
    )
    var, kept_untrained = un.theta, False
    if kind == "loop" and n_val and int(steps) > 0:
        # the validation split decides: a trained correction that costs iterations
        # against the previous step's iterate is not kept
        sc0 = score(untrained)
        history.append({"phase": "validation", "step": "untrained", "iterations": sc0})
        if sc0 < score(var):
            var, kept_untrained = untrained, True
    model = StartModel.from_arrays(_arrays(var, sc.fixed), kind, **sc.sizes)
    settings = {
        "family": fam.name,
        "kind": kind,
        "cases": int(cases),
        "pairs": n,
        "validation_pairs": n_val,
        "seed": int(seed),
        "pretrain_steps": int(pretrain_steps),
        "steps": int(steps),
        "iterations": int(iterations),
        "schedule": int(schedule),
        "hidden": [int(h) for h in hidden],
        "lr": float(lr),
        "unrolled_lr": rate,
        "batch": bsize,
        "loss": loss,
        "tol": ts.tol,
        "max_iter": int(max_iter),
        "example": ts.example,
        "objectives": list(T.objective_names),
        "horizon": T.horizon,
        "parameters": model.n_parameters,
        "kept_untrained": kept_untrained,
        "tuned_for": {
            "formulation": ts.inner.info.name,
            "rho_scale": [float(x) for x in ts.rho],
            "relaxation": st["relaxation"],
            "anderson": st["anderson"],
            "kkt": ts.inner.kkt,
            "dtype": jnp.dtype(dt).name,
            "tol": ts.tol,
        },
        "train_seconds": time.perf_counter() - t0,
    }
    evaluation: dict[str, Any] = {}
    if evaluate:
        evaluation = evaluate_model(
            fam, model, settings, opts, heldout_cases, heldout_seed, shifted_seed, max_iter, dt
        )
    return StartTuning(model, history, evaluation, settings)
