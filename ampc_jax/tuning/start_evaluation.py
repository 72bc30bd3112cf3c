"""Evaluating a learned start (:mod:`.warm_start`): held-out step cases by the
iterations to the command's tolerance and the first-step error against
Clarabel (:func:`evaluate_starts`), held-out closed loops by the iterations per
control step and e_sub (:func:`evaluate_loops`), and the table of both
(:func:`start_table`)."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from ..admm.learned_start import LearnedStart, StartModel
from .solver import batch_params, pairs_program, point_row

__all__ = ["evaluate_loops", "evaluate_model", "evaluate_starts", "start_table"]


def evaluate_model(
    fam: Any,
    model: StartModel,
    settings: dict[str, Any],
    opts: dict[str, Any],
    heldout_cases: int,
    heldout_seed: int,
    shifted_seed: int,
    max_iter: int,
    dt: Any,
) -> dict[str, Any]:
    """The last phase: held-out step cases (and, where the family has them, cases
    in its shifted ranges) by :func:`evaluate_starts`; a loop family's held-out
    closed loops by :func:`evaluate_loops`."""
    evaluation: dict[str, Any] = {}
    if settings["kind"] == "step":
        sets = [(f"seed {heldout_seed}", heldout_seed, {})]
        if "ranges" in fam.options:
            sets.append(
                (f"seed {shifted_seed}, shifted ranges", shifted_seed, {"ranges": "shifted"})
            )
        for label, sd, extra in sets:
            held = fam.sample(int(heldout_cases), seed=int(sd), **opts, **extra)
            evaluation[label] = evaluate_starts(
                held, model, settings["tuned_for"], max_iter=int(max_iter)
            )
    else:
        held = fam.sample(int(heldout_cases), seed=int(heldout_seed), **opts)
        evaluation[f"seed {heldout_seed}"] = evaluate_loops(held, model, dtype=dt)
    return evaluation


def evaluate_starts(
    held: Any,
    model: StartModel | None,
    tuned_for: dict[str, Any],
    *,
    max_iter: int = 500,
    extra: dict[str, tuple[Any, float, int]] | None = None,
    finish: str = "none",
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
    ``finish``: every contender's exact finish (default ``"none"``, the paper's
    iteration the start is trained on; ``"active_set"``: the iterations to a
    verified finish, :mod:`~ampc_jax.admm.finish`).
    """
    from ..formulations import PAPER_ITERATION, formulation
    from .solver import reference_inputs

    T = held.topology
    iteration = {**PAPER_ITERATION, "finish": finish}
    J = T.n_objectives
    dt = jax.tree.leaves(held.data)[0].dtype
    n = int(jax.tree.leaves(held.data)[0].shape[0])
    tol = float(tuned_for["tol"])
    u0_star = reference_inputs(T, held.data)[:, 0, :]
    cmd = (tuned_for["rho_scale"], float(tuned_for["relaxation"]), int(tuned_for["anderson"]))
    contenders: list[tuple[str, Any, Any, float]] = [
        (
            "eq.opt_ro, cold",
            formulation("local_explicit", T, max_iter=max_iter, **iteration),
            1.0,
            1.0,
        ),
        (
            "command, cold",
            formulation("local_explicit", T, max_iter=max_iter, anderson=cmd[2], **iteration),
            cmd[0],
            cmd[1],
        ),
    ]
    for name, (rs, alpha, aa) in (extra or {}).items():
        contenders.append(
            (
                name,
                formulation("local_explicit", T, max_iter=max_iter, anderson=aa, **iteration),
                rs,
                alpha,
            )
        )
    if model is not None:
        inner = formulation("local_explicit", T, max_iter=max_iter, anderson=cmd[2], **iteration)
        contenders.append(("learned start", LearnedStart(inner, model), cmd[0], cmd[1]))
    rows = [
        point_row(
            name,
            pairs_program(solver)(held.data, batch_params(n, J, rs, alpha, tol, dt)),
            u0_star,
            np.broadcast_to(np.asarray(rs, float), (J,)),
            alpha,
        )
        for name, solver, rs, alpha in contenders
    ]
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
