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
    problem_features,
)
from ..admm.params import SolverParams
from ..admm.runners import check_iterations, loop_parts

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


def _params(n: int, J: int, rho: Any, alpha: float, tol: float, dt: Any) -> SolverParams:
    r = jnp.broadcast_to(jnp.asarray(np.broadcast_to(np.asarray(rho, float), (J,)), dt), (n, J))
    full = lambda v: jnp.full((n,), v, dt)  # noqa: E731
    return SolverParams(r, full(alpha), full(tol), full(tol), full(0.0))


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
    rate ``lr`` (cosine decay). With ``evaluate``: ``heldout_cases`` cases
    under ``heldout_seed``, and (step families) as many under ``shifted_seed``
    in the family's other friction and speed range (``ranges="shifted"``),
    by :func:`evaluate_starts`; loop families by :func:`evaluate_loops`.
    """
    import optax
    from tqdm import tqdm

    from ..formulations import formulation
    from ..sweep.families import family

    fam = family(family_name)
    for name, v, low in (
        ("cases", cases, 1),
        ("pretrain_steps", pretrain_steps, 0),
        ("steps", steps, 0),
        ("iterations", iterations, 1),
        ("schedule", schedule, 0),
        ("batch", batch, 1),
        ("heldout_cases", heldout_cases, 1),
    ):
        check_iterations(v, name, low)
    if schedule > SCHEDULE_MAX:
        raise ValueError(f"schedule: expected at most {SCHEDULE_MAX} iterations, got {schedule}")
    if loss not in START_LOSSES:
        raise ValueError(f"loss: expected one of {START_LOSSES}, got {loss!r}")
    if not (np.isfinite(lr) and lr > 0):
        raise ValueError(f"lr: expected a positive finite number, got {lr!r}")
    if not hidden or any(int(h) < 1 for h in hidden):
        raise ValueError(f"hidden: expected layer widths >= 1, got {hidden!r}")
    t0 = time.perf_counter()
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    opts: dict[str, Any] = {}
    if "dtype" in fam.options:
        opts["dtype"] = dt
    if horizon is not None:
        if "horizon" not in fam.options:
            raise ValueError(f"horizon: family {fam.name!r} has no horizon option")
        opts["horizon"] = int(horizon)
    train = _cases(fam, cases, seed, opts)
    kind = "loop" if fam.kind == "loop" else "step"
    if kind == "loop":
        cfg, data, prev = _loop_pairs_of(train, dt)
        from ..closed_loop.controller import controller_for

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
    inner = formulation("local_explicit", T, anderson=st["anderson"], max_iter=int(max_iter))
    n = int(jax.tree.leaves(data)[0].shape[0])
    # the fixed points: far below the command's tolerance, from the same start a solve has
    tight = _params(n, J, rho, st["relaxation"], TARGET_TOL, dt)
    deep = formulation("local_explicit", T, anderson=st["anderson"], max_iter=20 * int(max_iter))
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
    data, fx, u_star = take(data), take(fx), jnp.asarray(u_star[keep], dt)
    prev = None if prev is None else take(prev)
    n = int(keep.size)
    feats = np.asarray(jax.vmap(problem_features)(data), np.float64)
    x_point = np.asarray(jax.vmap(inner.point)(fx), np.float64)
    if kind == "loop":
        p_point = np.asarray(jax.vmap(inner.point)(prev), np.float64)
        feats = np.concatenate([feats, p_point], axis=1)
        target = x_point - p_point
        o_mean = np.zeros(target.shape[1])
        _, o_scale = _scales(target)
        mask = (np.abs(target).max(0) > 0).astype(float)
    else:
        target = np.asarray(jax.vmap(box_coordinates)(u_star, data), np.float64).reshape(n, -1)
        box = np.asarray(jnp.isfinite(data.lb) & jnp.isfinite(data.ub)).reshape(n, -1)
        o_mean, o_scale = _scales(target)
        mask = np.ones(target.shape[1])
    f_mean = feats.mean(0)
    f_std = feats.std(0)
    f_scale = np.where(f_std > 1e-9 * (1.0 + np.abs(f_mean)), f_std, 1.0)
    sizes = [feats.shape[1], *(int(h) for h in hidden), target.shape[1]]
    fixed = StartArrays(
        layers=(),
        input_mean=jnp.asarray(f_mean, dt),
        input_scale=jnp.asarray(f_scale, dt),
        out_mean=jnp.asarray(o_mean, dt),
        out_scale=jnp.asarray(o_scale, dt),
        out_mask=jnp.asarray(mask, dt),
        schedule_rho=jnp.ones((schedule, J), dt),
        schedule_relaxation=jnp.full((schedule,), st["relaxation"], dt),
    )
    a0 = st["relaxation"] / 2.0
    var = _Train(
        _init_layers(jax.random.PRNGKey(int(seed)), sizes, dt),
        jnp.zeros((schedule, J), dt),
        jnp.full((schedule,), np.log(a0 / (1.0 - a0)), dt),
    )
    model_sizes = {
        "n_point": x_point.shape[1],
        "objectives": T.objective_names,
        "horizon": T.horizon,
    }
    wrapper = LearnedStart(inner, StartModel.from_arrays(_arrays(var, fixed), kind, **model_sizes))
    X = jnp.asarray((feats - f_mean) / f_scale, dt).clip(-10.0, 10.0)
    Y = jnp.asarray((target - o_mean) / o_scale, dt)
    M = jnp.asarray(mask, dt)
    if kind == "step":
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
    scale_c = float(T.horizon * T.n_u)
    p_one = SolverParams(
        jnp.asarray(rho, dt),
        jnp.asarray(st["relaxation"], dt),
        *(jnp.asarray(v, dt) for v in (tol, tol, 0.0)),
    )

    def pre_loss(v: _Train, idx: Any) -> Any:  # regression on the fixed points
        from ..admm.learned_start import mlp

        y = jax.vmap(lambda x: mlp(v.layers, x))(X[idx])
        e = jnp.where(
            at_lo[idx],
            jnp.maximum(y - lo_y, 0.0),
            jnp.where(at_hi[idx], jnp.maximum(hi_y - y, 0.0), y - Y[idx]),
        )
        return jnp.sum(M * e**2) / (jnp.sum(M) * idx.shape[0])

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
        arrays = _arrays(v, fixed)
        d = jax.tree.map(lambda x: x[idx], data)
        us = u_star[idx]
        if prev is None:
            e = jax.vmap(lambda dd, uu: one_case(arrays, dd, None, uu))(d, us)
        else:
            pv = jax.tree.map(lambda x: x[idx], prev)
            e = jax.vmap(lambda dd, pp, uu: one_case(arrays, dd, pp, uu))(d, pv, us)
        return jnp.mean(e)

    history: list[dict[str, Any]] = []
    rng = np.random.default_rng(int(seed))
    # a validation split of the training cases picks the unrolled phase's point by
    # what it is for, iterations to the tolerance (its loss is only a proxy)
    n_val = max(1, min(n // 8, 512)) if n > 1 else 0
    n_fit = n - n_val
    bsize = min(int(batch), n_fit)
    bar_off = None if progress is None else not progress
    val = np.arange(n_fit, n)

    @jax.jit
    def val_iterations(arrays: StartArrays) -> Any:
        d = jax.tree.map(lambda x: x[val], data)

        def one(dd: Any, pv: Any) -> Any:
            setup = wrapper.setup_with(dd, p_one, arrays)
            return wrapper.run(setup, wrapper.init(setup, pv)).iteration

        if prev is None:
            return jax.vmap(lambda dd: one(dd, None))(d)
        return jax.vmap(one)(d, jax.tree.map(lambda x: x[val], prev))

    def score(v: _Train) -> tuple[float, float, float]:
        it = np.asarray(val_iterations(_arrays(v, fixed)), float)
        return float(np.mean(it)), float(np.median(it)), float(np.percentile(it, 95))

    def train_phase(name: str, fn: Any, n_steps: int, rate: float) -> _Train:
        nonlocal var
        if n_steps == 0:
            return var
        opt = optax.adam(optax.cosine_decay_schedule(rate, n_steps, alpha=0.05))
        state = opt.init(var)

        @jax.jit
        def update(v: _Train, s: Any, idx: Any) -> tuple[_Train, Any, Any]:
            value, g = jax.value_and_grad(fn)(v, idx)
            upd, s = opt.update(g, s, v)
            return optax.apply_updates(v, upd), s, value

        bar = tqdm(range(n_steps), desc=name, disable=bar_off)
        unrolled = name == "unrolled"
        best = (score(var), var) if unrolled and n_val else None
        if best is not None:
            history.append({"phase": "validation", "step": 0, "iterations": best[0]})
        for k in bar:
            idx = jnp.asarray(rng.choice(n_fit, bsize, replace=False))
            new, state, value = update(var, state, idx)
            history.append({"phase": name, "step": k, "loss": float(value)})
            bar.set_postfix(loss=f"{float(value):.3e}")
            var = new if np.all([np.all(np.isfinite(x)) for x in jax.tree.leaves(new)]) else var
            if best is not None and ((k + 1) % VALIDATE_EVERY == 0 or k + 1 == n_steps):
                sc = score(var)
                history.append({"phase": "validation", "step": k + 1, "iterations": sc})
                if sc < best[0]:
                    best = (sc, var)
        return best[1] if best is not None else var

    untrained = var  # a "loop" network with its zero last layer is today's warm start
    var = train_phase("pretrain", pre_loss, int(pretrain_steps), float(lr))
    var = train_phase(
        "unrolled", un_loss, int(steps), float(lr) / 30.0 if unrolled_lr is None else unrolled_lr
    )
    kept_untrained = False
    if kind == "loop" and n_val and int(steps) > 0:
        # the validation split decides: a trained correction that costs iterations
        # against the previous step's iterate is not kept
        sc0 = score(untrained)
        history.append({"phase": "validation", "step": "untrained", "iterations": sc0})
        if sc0 < score(var):
            var, kept_untrained = untrained, True
    model = StartModel.from_arrays(_arrays(var, fixed), kind, **model_sizes)
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
        "unrolled_lr": float(lr) / 30.0 if unrolled_lr is None else float(unrolled_lr),
        "batch": bsize,
        "loss": loss,
        "tol": float(tol),
        "max_iter": int(max_iter),
        "example": example_name,
        "objectives": list(T.objective_names),
        "horizon": T.horizon,
        "parameters": model.n_parameters,
        "kept_untrained": kept_untrained,
        "tuned_for": {
            "formulation": "local_explicit",
            "rho_scale": [float(x) for x in rho],
            "relaxation": st["relaxation"],
            "anderson": st["anderson"],
            "kkt": inner.kkt,
            "dtype": jnp.dtype(dt).name,
            "tol": float(tol),
        },
        "train_seconds": time.perf_counter() - t0,
    }
    evaluation: dict[str, Any] = {}
    if evaluate:
        if kind == "step":
            sets = [(f"seed {heldout_seed}", heldout_seed, {})]
            if "ranges" in fam.options:
                sets.append(
                    (f"seed {shifted_seed}, shifted ranges", shifted_seed, {"ranges": "shifted"})
                )
            for label, sd, extra in sets:
                held = _cases(fam, heldout_cases, sd, {**opts, **extra})
                evaluation[label] = evaluate_starts(
                    held, model, settings["tuned_for"], max_iter=int(max_iter)
                )
        else:
            held = _cases(fam, heldout_cases, heldout_seed, opts)
            evaluation[f"seed {heldout_seed}"] = evaluate_loops(held, model, dtype=dt)
    return StartTuning(model, history, evaluation, settings)


def _pairs_program(solver: Any) -> Any:
    from ..sweep.engine import solve_pairs

    return jax.jit(lambda d, p: solve_pairs(solver, d, p)[0])


def evaluate_starts(
    held: Any,
    model: StartModel | None,
    tuned_for: dict[str, Any],
    *,
    max_iter: int = 500,
    extra: dict[str, tuple[Any, float, int]] | None = None,
) -> dict[str, Any]:
    """Iterations to tolerance on the step cases ``held`` from three starts.

    Contenders (each solved to ``tuned_for["tol"]`` by the while loop, cap
    ``max_iter``): ``eq.opt_ro, cold`` (plain ADMM, rho scale 1, alpha 1: the
    paper's iteration), ``command, cold`` (the command's rho scales, relaxation
    and Anderson memory from a cold start), ``learned start`` (the same with
    ``model``'s start and schedule), and ``extra`` name -> (rho scale,
    relaxation, anderson) from a cold start (a rho-tuned point). Returns
    ``{"cases", "tol", "rows": [{name, median, p95, max, converged, u0_error,
    u0_rel_error}]}``; ``u0_error`` is the worst ||u0 - u0*|| against Clarabel.
    """
    from ..formulations import formulation
    from .solver import reference_inputs

    T = held.topology
    J = T.n_objectives
    dt = jax.tree.leaves(held.data)[0].dtype
    n = int(jax.tree.leaves(held.data)[0].shape[0])
    tol = float(tuned_for["tol"])
    u0_star = reference_inputs(T, held.data)[:, 0, :]
    cmd = (tuned_for["rho_scale"], float(tuned_for["relaxation"]), int(tuned_for["anderson"]))
    contenders: list[tuple[str, Any, Any, float]] = [
        ("eq.opt_ro, cold", formulation("local_explicit", T, max_iter=max_iter), 1.0, 1.0),
        (
            "command, cold",
            formulation("local_explicit", T, max_iter=max_iter, anderson=cmd[2]),
            cmd[0],
            cmd[1],
        ),
    ]
    for name, (rs, alpha, aa) in (extra or {}).items():
        contenders.append(
            (name, formulation("local_explicit", T, max_iter=max_iter, anderson=aa), rs, alpha)
        )
    if model is not None:
        inner = formulation("local_explicit", T, max_iter=max_iter, anderson=cmd[2])
        contenders.append(("learned start", LearnedStart(inner, model), cmd[0], cmd[1]))
    rows = []
    for name, solver, rs, alpha in contenders:
        out = _pairs_program(solver)(held.data, _params(n, J, rs, alpha, tol, dt))
        it = np.asarray(out.iterations)
        err = np.linalg.norm(np.asarray(out.u0, float) - u0_star, axis=1)
        rows.append(
            {
                "name": name,
                "rho_scale": [float(x) for x in np.broadcast_to(np.asarray(rs, float), (J,))],
                "relaxation": float(alpha),
                "median": float(np.median(it)),
                "p95": float(np.percentile(it, 95)),
                "max": int(np.max(it)),
                "converged": float(np.mean(np.asarray(out.converged))),
                "u0_error": float(np.max(err)),
                "u0_rel_error": float(np.max(err / (np.linalg.norm(u0_star, axis=1) + 1.0))),
            }
        )
    return {"cases": n, "tol": tol, "rows": rows}


def evaluate_loops(held: Any, model: StartModel | None, *, dtype: Any = None) -> dict[str, Any]:
    """Closed loops of a loop family's cases ``held`` with today's warm start and with
    ``model``'s: iterations per control step (median, p95, max, mean over every
    step of every loop) and e_sub (the integrated MPC in shadow; p95 and max, Nm)."""
    from dataclasses import replace

    from ..closed_loop.loop import simulate_batch

    rows = []
    runs = [("previous step (today)", held.config)]
    if model is not None:
        runs.append(("learned start", replace(held.config, learned_start=model)))
    for name, cfg in runs:
        log = simulate_batch(cfg, held.scenarios, held.n_steps, dtype=dtype)
        it = np.asarray(log.iterations, float).ravel()
        e = np.asarray(log.e_sub, float)
        e = e[np.isfinite(e)]
        rows.append(
            {
                "name": name,
                "median": float(np.median(it)),
                "p95": float(np.percentile(it, 95)),
                "max": int(np.max(it)),
                "mean": float(np.mean(it)),
                "e_sub_p95": float(np.percentile(e, 95)) if e.size else float("nan"),
                "e_sub_max": float(np.max(e)) if e.size else float("nan"),
                "fallbacks": int(np.sum(np.asarray(log.fallback))),
            }
        )
    return {"loops": int(np.shape(held.scenarios.mu)[0]), "steps": held.n_steps, "rows": rows}


def start_table(evaluation: dict[str, Any]) -> str:
    """The held-out evaluation as a compact text table (one block per held-out set)."""
    lines = []
    for label, ev in evaluation.items():
        if "loops" in ev:
            lines.append(f"held-out {label}: {ev['loops']} closed loops of {ev['steps']} steps")
            lines.append(
                f"  {'start':<24} {'median':>7} {'p95':>6} {'max':>5} {'mean':>6} "
                f"{'e_sub p95':>10} {'max':>7}"
            )
            for r in ev["rows"]:
                lines.append(
                    f"  {r['name']:<24} {r['median']:>7.1f} {r['p95']:>6.1f} {r['max']:>5d} "
                    f"{r['mean']:>6.2f} {r['e_sub_p95']:>10.3g} {r['e_sub_max']:>7.3g}"
                )
            continue
        lines.append(f"held-out {label}: {ev['cases']} cases, tol {ev['tol']:g}")
        lines.append(
            f"  {'start':<24} {'median':>7} {'p95':>6} {'max':>5} {'conv':>5} "
            f"{'max|du0|':>9} {'rel':>8}"
        )
        base = ev["rows"][0]
        for r in ev["rows"]:
            lines.append(
                f"  {r['name']:<24} {r['median']:>7.1f} {r['p95']:>6.1f} {r['max']:>5d} "
                f"{r['converged']:>5.2f} {r['u0_error']:>9.3g} {r['u0_rel_error']:>8.2g}"
            )
        best = ev["rows"][-1]
        lines.append(
            f"  {best['name']} against {base['name']}: median {base['median'] / max(best['median'], 1):.2f}x "
            f"fewer, p95 {base['p95'] / max(best['p95'], 1):.2f}x fewer"
        )
    return "\n".join(lines)
