"""Gradient tuning of the objectives' weights Q_j and R_(i) through the closed loop.

The weights of an example's settings (``WEIGHTS``: Q_j, ``INPUT_WEIGHTS``:
R_(i)) are tuned by their logs, so every value of the variables is a positive
weight::

    w_f = w_f^0 exp(theta_f)      (theta = 0: the example's default settings)

The closed loop (:meth:`~ampc_jax.closed_loop.loop.Simulator.run`) is made
reverse-mode differentiable by a controller with a fixed number K of ADMM
iterations per control step (``SimConfig(fixed_iterations=K)``, the
formulation's ``solve_fixed``: a ``lax.scan``, warm started as in deployment)
and no shadow. The plant, driver and wheel-torque map are smooth JAX functions
of the inputs, so ``jax.grad`` of a loss of the whole run exists. For the
training batch of n cases (a loop family's stacked scenarios, vmapped) the
loss is

    L(theta) = 1/n sum_i (e_i / e_s)^2
             + w_s 1/n sum_i (max(s_i - s_lim, 0) / s_lim)^2
             + w_T 1/n sum_i (max(T_i - T_lim, 0) / T_lim)^2

with

* e_i the RMS yaw-rate error r - r_ref (eq.CC_objective's friction-limited
  reference) over the focus window's control steps, e_s = ``yaw_scale``;
* s_i a soft maximum of the rear wheels' |slip ratio| over the run,
  tau log sum_(k, w) exp(|s_kw| / tau) (tau = ``slip_temperature``; it is at
  least the true maximum, and at most tau log(2 n_steps) above it), s_lim =
  ``slip_limit``, w_s = ``slip_weight``: a squared hinge that is zero while
  the soft maximum stays under the limit;
* T_i the same soft maximum of the four wheel torques' |T| (tau_T =
  ``torque_temperature`` Nm), T_lim = ``torque_limit`` (``None``: no torque
  term), w_T = ``torque_weight``.

Iterations are not in the loss (K is fixed while training); they are reported
by the evaluation. The loss is minimised with Adam (optax) on the logs by the
tuners' one loop (:func:`~ampc_jax.tuning.fit.fit`); the update is one jitted
program (vmap over cases inside). The best iterate seen
is then evaluated with the deployed controller (to tolerance, ``solve``) on
the training cases, optional held-out cases and the example's registered
scenarios, against the default weights and against the example's baseline
(:func:`~ampc_jax.closed_loop.config.baseline_config`: for cruise control, LST
alone), by :func:`evaluate_settings`.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..closed_loop.config import LoopParams, SimConfig, baseline_config
from ..closed_loop.loop import Simulator, run_closed_loop, simulator_for
from ..sweep.families import LoopCases
from ..validation import check_count, check_non_negative, check_positive
from ..vehicle.manoeuvres import SCENARIOS, scenario
from ..vehicle.params import CONTROL_DT
from .fit import FitSpec, fit

__all__ = [
    "LossOptions",
    "LossTerms",
    "WeightsResult",
    "evaluate_settings",
    "log_weights",
    "loop_loss",
    "soft_max",
    "tune_weights",
    "weight_fields",
    "weights_table",
    "weights_verdicts",
    "with_log_weights",
]


class LossOptions(NamedTuple):
    """Static options of :func:`loop_loss` (hashable). ``focus``: the control-step
    range [k0, k1) of the yaw term; the others as in the module's loss."""

    focus: tuple[int, int]
    yaw_scale: float = 0.02
    slip_limit: float = 0.15
    slip_weight: float = 10.0
    slip_temperature: float = 0.01
    torque_limit: float | None = None
    torque_weight: float = 1.0
    torque_temperature: float = 20.0


class LossTerms(NamedTuple):
    """The parts of :func:`loop_loss` (per case: shape (n,))."""

    tracking: Any  # () 1/n sum (e_i / e_s)^2
    slip: Any  # () w_s 1/n sum hinge^2
    torque: Any  # () w_T 1/n sum hinge^2 (0 without a torque limit)
    yaw_rms: Any  # (n,) e_i, rad/s
    slip_max: Any  # (n,) soft max of the rear |slip|
    torque_max: Any  # (n,) soft max of |T| (Nm)


class WeightsResult(NamedTuple):
    """What :func:`tune_weights` found.

    settings : the tuned weights by field name (the example's other settings unchanged).
    history : one dict per Adam step (``step``, ``loss``, the loss's parts, the weights).
    evaluation : :func:`evaluate_settings` of the default and the tuned weights
        per evaluation set, and how the run was made (``"run"``).
    """

    settings: dict[str, float]
    history: list[dict[str, Any]]
    evaluation: dict[str, Any]


def weight_fields(settings: Any) -> tuple[str, ...]:
    """The settings' weights: Q_j (``WEIGHTS``) then R_(i) (``INPUT_WEIGHTS``)."""
    return tuple(settings.WEIGHTS) + tuple(settings.INPUT_WEIGHTS)


def log_weights(settings: Any, fields: tuple[str, ...], dtype: Any = None) -> Any:
    """(F,) log w_f of ``fields`` of ``settings`` (every one must be > 0)."""
    dt = jnp.result_type(float) if dtype is None else dtype
    vals = np.array([float(getattr(settings, f)) for f in fields])
    if not np.all(vals > 0):
        bad = [f for f, v in zip(fields, vals, strict=True) if not v > 0]
        raise ValueError(f"{bad[0]}: a weight tuned by its log must be > 0, got 0")
    return jnp.asarray(np.log(vals), dt)


def with_log_weights(settings: Any, fields: tuple[str, ...], log_w: Any) -> Any:
    """``settings`` (array leaves) with w_f = exp(log_w[f]) for each of ``fields``."""
    return settings.replace(**{f: jnp.exp(log_w[k]) for k, f in enumerate(fields)})


def soft_max(x: Any, temperature: float, axis: Any = None) -> Any:
    """tau log sum exp(x / tau): a smooth upper bound of max(x), within tau log(size)."""
    return temperature * jax.nn.logsumexp(x / temperature, axis=axis)


def _smooth_abs(x: Any, eps: float = 1e-6) -> Any:
    return jnp.sqrt(x * x + eps * eps)


def loop_loss(
    log_w: Any,
    simulator: Simulator,
    params: LoopParams,
    scenarios: Any,
    n_steps: int,
    fields: tuple[str, ...],
    options: LossOptions,
) -> tuple[Any, LossTerms]:
    """L(theta) of the module docstring at w = exp(``log_w``), and its parts.

    ``scenarios`` carry a leading case axis (vmapped); ``params`` are the
    loop's numbers whose settings' ``fields`` are replaced. Differentiable in
    ``log_w`` when the simulator's controller runs fixed iterations and has no
    shadow. Jit with ``simulator``, ``n_steps``, ``fields``, ``options`` static.
    """
    ctrl = params.controller
    p = params._replace(
        controller=ctrl._replace(settings=with_log_weights(ctrl.settings, fields, log_w))
    )
    log = jax.vmap(lambda sc: run_closed_loop(simulator, sc, p, n_steps))(scenarios)
    k0, k1 = options.focus
    err = (log.yaw_rate - log.yaw_ref)[:, k0:k1]
    mean_sq = jnp.mean(err * err, axis=1)  # e_i^2: the loss uses it (sqrt has no slope at 0)
    yaw_rms = jnp.sqrt(mean_sq)
    n = yaw_rms.shape[0]
    rear = _smooth_abs(log.slip[:, :, 2:]).reshape(n, -1)
    slip_max = soft_max(rear, options.slip_temperature, axis=1)
    lim = options.slip_limit
    slip_pen = options.slip_weight * jnp.mean(jnp.square(jax.nn.relu(slip_max - lim) / lim))
    torque_max = soft_max(_smooth_abs(log.torques).reshape(n, -1), options.torque_temperature, 1)
    if options.torque_limit is None:
        torque_pen = jnp.zeros((), yaw_rms.dtype)
    else:
        tl = options.torque_limit
        torque_pen = options.torque_weight * jnp.mean(jnp.square(jax.nn.relu(torque_max - tl) / tl))
    tracking = jnp.mean(mean_sq) / options.yaw_scale**2
    terms = LossTerms(tracking, slip_pen, torque_pen, yaw_rms, slip_max, torque_max)
    return tracking + slip_pen + torque_pen, terms


# ------------------------------------------------------------------ evaluation
_batch_run = jax.jit(
    jax.vmap(run_closed_loop, in_axes=(None, 0, None, None)), static_argnums=(0, 3)
)


def _cast(tree: Any, dtype: Any) -> Any:
    return jax.tree.map(
        lambda x: jnp.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else x,
        tree,
    )


def _run_logs(config: SimConfig, scenarios: Any, n_steps: int, dtype: Any) -> Any:
    """The deployed closed loop (to tolerance, no shadow) of stacked scenarios, as numpy."""
    cfg = replace(config, fixed_iterations=None, shadow=False)
    log = _batch_run(simulator_for(cfg), _cast(scenarios, dtype), cfg.loop_params(dtype), n_steps)
    return jax.tree.map(np.asarray, log)


def _case_metrics(log: Any, focus: tuple[float, float]) -> dict[str, np.ndarray]:
    """Per case (n,): RMS yaw error in the focus window, rear |slip| max, peak |T|, iterations."""
    t = log.t[0]
    fm = (t >= focus[0]) & (t <= focus[1])
    err = (log.yaw_rate - log.yaw_ref)[:, fm]
    return {
        "yaw_rms_focus": np.sqrt(np.mean(err**2, axis=1)),
        "rear_slip_abs_max": np.max(np.abs(log.slip[:, :, 2:]), axis=(1, 2)),
        "speed_rms": np.sqrt(np.nanmean((log.v_x - log.v_ref) ** 2, axis=1)),
        "torque_abs_max": np.max(np.abs(log.torques), axis=(1, 2)),
        "iterations_max": np.max(log.iterations, axis=1).astype(float),
        "iterations_p95": np.percentile(log.iterations, 95, axis=1),
        "fallbacks": np.sum(log.fallback, axis=1).astype(float),
    }


def evaluate_settings(
    config: SimConfig,
    settings: Any,
    scenarios: Any,
    n_steps: int,
    focus: tuple[float, float],
    *,
    slip_limit: float = 0.15,
    dtype: Any = None,
) -> dict[str, Any]:
    """``config`` with ``settings`` against its baseline with the same settings, on
    stacked ``scenarios`` (deployed controller, to tolerance).

    Returns per-case lists and summaries: ``yaw_rms_focus`` (mean over cases),
    ``baseline_yaw_rms_focus``, ``yaw_ratio`` (geometric mean over cases of
    baseline / controller: 2 is "halves the yaw-rate error"), ``rear_slip_max``
    (worst case), ``cases_over_slip_limit``, ``torque_max`` (worst case, Nm),
    ``speed_rms`` (mean over cases of the RMS of v_x - v_ref: not in the loss),
    ``iterations_max`` / ``iterations_p95`` (worst case), ``fallbacks``.
    """
    dt = jnp.result_type(float) if dtype is None else dtype
    cfg = replace(config, settings=settings)
    per = _case_metrics(_run_logs(cfg, scenarios, n_steps, dt), focus)
    base = _case_metrics(_run_logs(baseline_config(cfg), scenarios, n_steps, dt), focus)
    ratio = base["yaw_rms_focus"] / per["yaw_rms_focus"]
    return {
        "n_cases": int(per["yaw_rms_focus"].size),
        "yaw_rms_focus": float(np.mean(per["yaw_rms_focus"])),
        "baseline_yaw_rms_focus": float(np.mean(base["yaw_rms_focus"])),
        "yaw_ratio": float(np.exp(np.mean(np.log(ratio)))),
        "yaw_ratio_min": float(np.min(ratio)),
        "rear_slip_max": float(np.max(per["rear_slip_abs_max"])),
        "rear_slip_max_median": float(np.median(per["rear_slip_abs_max"])),
        "cases_over_slip_limit": int(np.sum(per["rear_slip_abs_max"] > slip_limit)),
        "baseline_rear_slip_max": float(np.max(base["rear_slip_abs_max"])),
        "torque_max": float(np.max(per["torque_abs_max"])),
        "speed_rms": float(np.mean(per["speed_rms"])),
        "iterations_max": float(np.max(per["iterations_max"])),
        "iterations_p95": float(np.max(per["iterations_p95"])),
        "fallbacks": int(np.sum(per["fallbacks"])),
        "per_case": {k: [float(x) for x in v] for k, v in per.items()}
        | {"baseline_yaw_rms_focus": [float(x) for x in base["yaw_rms_focus"]]},
    }


# ------------------------------------------------------------------ tuning
def _take(scenarios: Any, n: int) -> Any:
    return jax.tree.map(lambda x: np.asarray(x)[:n], scenarios)


def _example_scenarios(config: SimConfig) -> tuple[str, ...]:
    return tuple(name for name, s in SCENARIOS.items() if s.example == config.example)


def tune_weights(
    config: SimConfig,
    cases: LoopCases,
    *,
    steps: int,
    iterations: int,
    lr: float = 0.05,
    progress: bool | None = True,
    slip_limit: float = 0.15,
    slip_weight: float = 10.0,
    slip_temperature: float = 0.01,
    yaw_scale: float = 0.02,
    torque_limit: float | None = None,
    torque_weight: float = 1.0,
    fields: tuple[str, ...] | None = None,
    train_cases: int | None = None,
    duration: float | None = None,
    focus: tuple[float, float] | None = None,
    heldout: LoopCases | None = None,
    scenarios: tuple[str, ...] | None = None,
    evaluate: bool = True,
    dtype: Any = None,
) -> WeightsResult:
    """Tune the weights ``fields`` (default every Q_j and R_(i) of the example)
    of ``config.settings`` by ``steps`` Adam steps (learning rate ``lr`` on the
    logs) on the loss L(theta) of the module docstring over a loop family's
    cases.

    Parameters
    ----------
    config : the run tuned (its example, formulation, solver options; its
        settings are the starting point theta = 0). The training loop runs it
        with ``fixed_iterations=iterations`` and no shadow.
    cases : training cases (:meth:`Family.sample` of a loop family); the first
        ``train_cases`` of them (default all).
    iterations : K, the ADMM iterations of each control step while training.
    duration : training run length in s (default the cases' ``n_steps``);
        evaluation runs the whole cases.
    focus : (t0, t1) s, the yaw term's window (default the focus of the
        example's first registered scenario; the whole run if it has none).
    slip_limit, slip_weight, slip_temperature, yaw_scale, torque_limit,
    torque_weight : the loss's s_lim, w_s, tau, e_s, T_lim (None: no torque
        term), w_T.
    heldout : further cases to evaluate on (e.g. the family under another seed).
    scenarios : registered scenarios to evaluate on (default the example's).
    evaluate : run :func:`evaluate_settings` on every set for the default and the
        tuned weights.
    progress : a tqdm bar with the loss (None: on a terminal only).

    Returns a :class:`WeightsResult` with the best weights seen (lowest training loss).
    """
    steps = check_count(steps, "steps")
    K = check_count(iterations, "iterations")
    spec = FitSpec(steps, lr, finite_grads=True, desc="tune weights", progress=progress)
    for name, v in (
        ("slip_limit", slip_limit),
        ("slip_temperature", slip_temperature),
        ("yaw_scale", yaw_scale),
    ):
        check_positive(v, name)
    for name, v in (("slip_weight", slip_weight), ("torque_weight", torque_weight)):
        check_non_negative(v, name)
    if torque_limit is not None:
        check_positive(torque_limit, "torque_limit")
    if not config.mpc:
        raise ValueError("formulation: 'none' runs no MPC: no weights to tune")
    all_fields = weight_fields(config.settings)
    fields = all_fields if fields is None else tuple(fields)
    unknown = [f for f in fields if f not in all_fields]
    if unknown or not fields:
        raise ValueError(f"fields: expected some of {list(all_fields)}, got {list(fields)!r}")
    n_all = int(np.shape(jax.tree.leaves(cases.scenarios)[0])[0])
    n_train = n_all if train_cases is None else check_count(train_cases, "train_cases")
    if n_train > n_all:
        raise ValueError(f"train_cases: expected at most the {n_all} cases given, got {n_train}")
    n_steps = int(cases.n_steps)
    if duration is not None:
        n_steps = min(
            n_steps, max(1, int(round(check_positive(duration, "duration") / CONTROL_DT)))
        )
    names = _example_scenarios(config) if scenarios is None else tuple(scenarios)
    specs = [scenario(s) for s in names]
    if focus is None:
        focus = specs[0].focus if specs else (0.0, n_steps * CONTROL_DT)
    focus = (float(focus[0]), float(focus[1]))
    k0 = max(0, int(np.ceil(focus[0] / CONTROL_DT - 1e-9)))
    k1 = min(n_steps, int(np.floor(focus[1] / CONTROL_DT + 1e-9)) + 1)
    if k1 <= k0:
        raise ValueError(
            f"duration: the training run ({n_steps * CONTROL_DT:g} s) ends before the focus "
            f"window {focus} starts"
        )
    options = LossOptions(
        (k0, k1),
        float(yaw_scale),
        float(slip_limit),
        float(slip_weight),
        float(slip_temperature),
        None if torque_limit is None else float(torque_limit),
        float(torque_weight),
    )
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    t0 = time.perf_counter()
    train_cfg = replace(config, fixed_iterations=K, shadow=False)
    sim = simulator_for(train_cfg)
    params = train_cfg.loop_params(dt)
    train_sc = _cast(_take(cases.scenarios, n_train), dt)
    theta0 = log_weights(config.settings, fields, dt)

    def loss_fn(th: Any) -> tuple[Any, LossTerms]:
        return loop_loss(th, sim, params, train_sc, n_steps, fields, options)

    def record(step: int, th: Any, value: Any, terms: LossTerms) -> dict[str, Any]:
        w = np.exp(np.asarray(th, float))
        return {
            "step": step,
            "loss": float(value),
            "tracking": float(terms.tracking),
            "slip": float(terms.slip),
            "torque": float(terms.torque),
            "yaw_rms_mean": float(np.mean(terms.yaw_rms)),
            "slip_max": float(np.max(terms.slip_max)),
            "torque_max": float(np.max(terms.torque_max)),
            **{f: float(w[k]) for k, f in enumerate(fields)},
        }

    def postfix(value: Any, terms: LossTerms) -> dict[str, str]:
        return {"loss": f"{float(value):.4g}", "slip": f"{float(np.max(terms.slip_max)):.3f}"}

    run = fit(loss_fn, theta0, spec, has_aux=True, record=record, postfix=postfix)
    history = run.history
    best = (run.value, run.theta)
    w_best = np.exp(np.asarray(best[1], float))
    tuned = {f: float(w_best[k]) for k, f in enumerate(fields)}
    run = {
        "example": config.example,
        "formulation": config.formulation,
        "fields": list(fields),
        "steps": steps,
        "iterations": K,
        "lr": lr,
        "train_cases": n_train,
        "train_steps": n_steps,
        "focus_s": list(focus),
        "loss": options._asdict(),
        "initial_loss": history[0]["loss"],
        "best_loss": float(best[0]),
        "tune_seconds": time.perf_counter() - t0,
        "columns": {
            k: [float(x) for x in np.asarray(v)[:n_train]] for k, v in cases.columns.items()
        },
    }
    evaluation: dict[str, Any] = {"run": run}
    if evaluate:
        default = config.settings
        tuned_settings = default.replace(**tuned)
        sets: list[tuple[str, Any, int, tuple[float, float]]] = [
            ("train", _take(cases.scenarios, n_train), int(cases.n_steps), focus)
        ]
        if heldout is not None:
            sets.append(("heldout", heldout.scenarios, int(heldout.n_steps), focus))
        for spec in specs:
            one = jax.tree.map(lambda x: np.asarray(x)[None], spec.scenario)
            sets.append((spec.name, one, spec.n_steps, spec.focus))
        for name, sc, n, fw in sets:
            evaluation[name] = {
                label: evaluate_settings(config, s, sc, n, fw, slip_limit=slip_limit, dtype=dt)
                for label, s in (("default", default), ("tuned", tuned_settings))
            }
    return WeightsResult(tuned, history, evaluation)


# ------------------------------------------------------------------ summary
_TABLE = (
    # (column, key of evaluate_settings, format)
    ("yaw RMS rad/s", "yaw_rms_focus", "{:>13.4f}"),
    ("x baseline", "yaw_ratio", "{:>10.2f}"),
    ("rear slip max", "rear_slip_max", "{:>13.3f}"),
    ("over limit", "cases_over_slip_limit", "{:>10d}"),
    ("|T| max Nm", "torque_max", "{:>10.0f}"),
    ("iter p95", "iterations_p95", "{:>8.0f}"),
    ("fallbacks", "fallbacks", "{:>9d}"),
)


def weights_table(evaluation: dict[str, Any]) -> str:
    """The evaluation of :func:`tune_weights` as a text table: per evaluation set
    the default and the tuned weights (means and worst cases of
    :func:`evaluate_settings`; ``x baseline``: the geometric mean of the
    baseline's yaw RMS over the controller's, 2 halves the error)."""
    head = f"  {'set':<24} {'weights':<8} " + " ".join(c for c, _, _ in _TABLE)
    lines = [head]
    for name, ev in evaluation.items():
        if name == "run":
            continue
        for label in ("default", "tuned"):
            row = ev[label]
            cells = " ".join(fmt.format(row[key]) for _, key, fmt in _TABLE)
            shown = f"{name} ({row['n_cases']})" if label == "default" else ""
            lines.append(f"  {shown:<24} {label:<8} {cells}")
    return "\n".join(lines)


def weights_verdicts(evaluation: dict[str, Any]) -> list[str]:
    """One line per evaluation set: the tuned weights against the example's own
    (what ``ampc simulate`` runs without --params), saying when they are worse.

    Worse: more cases over the slip limit, or (as many) a larger mean yaw RMS
    in the focus window, the loss's two terms that a user sees."""
    lines = []
    for name, ev in evaluation.items():
        if name == "run":
            continue
        d, t = ev["default"], ev["tuned"]
        key_d = (d["cases_over_slip_limit"], d["yaw_rms_focus"])
        key_t = (t["cases_over_slip_limit"], t["yaw_rms_focus"])
        word = "worse than" if key_t > key_d else "as good as" if key_t == key_d else "better than"
        line = (
            f"{name}: tuned weights are {word} the example's defaults (yaw RMS "
            f"{t['yaw_rms_focus']:.4f} vs {d['yaw_rms_focus']:.4f} rad/s, cases over the slip "
            f"limit {t['cases_over_slip_limit']} vs {d['cases_over_slip_limit']})"
        )
        if key_t > key_d:
            line += "; keep the defaults (run without this params.json)"
        lines.append(line)
    return lines
