"""``ampc tune``: gradient tuning of the solver's speed (or the closed loop's weights).

Writes ``DIR/params.json`` (the tuned-parameters file, ``ampc-params/1``, for
``--params`` of ``simulate``, ``solve``, ``run`` and ``export``), ``DIR/loss.png``
(the loss curve) and ``DIR/tune.json`` (the loss history and the held-out
evaluation), and prints the evaluation table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from .args import (
    add_output_flags,
    add_solver_flags,
    arg_type,
    at_least_one,
    fail,
    flag_error,
    positive_finite,
)
from .outdir import add_force, claim_dir

__all__ = ["add_tune_command", "cmd_tune"]

_FLAGS = {
    "family": "--family",
    "cases": "--cases",
    "steps": "--steps",
    "iterations": "--iterations",
    "lr": "--lr",
    "seed": "--seed",
    "heldout_seed": "--heldout-seed",
    "loss": "--loss",
    "anderson": "--anderson",
    "pretrain_steps": "--pretrain-steps",
    "schedule": "--schedule",
    "hidden": "--hidden",
    "batch": "--batch",
    "heldout_cases": "--heldout-cases",
    "horizon": "--horizon",
}

DEFAULTS = {
    "solver": {"cases": 32, "steps": 100, "iterations": 10, "lr": 0.1, "loss": "error"},
    "weights": {"cases": 32, "steps": 100, "iterations": 10, "lr": 0.1, "loss": "error"},
    "warm_start": {"cases": 512, "steps": 100, "iterations": 6, "lr": 3e-3, "loss": "error"},
}
"""Per objective, the value of each shared flag left out."""


def _loss_figure(history: list[dict[str, Any]], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    loss = [h["loss"] for h in history]
    ax.plot(range(len(loss)), loss)
    if min(loss) > 0:
        ax.set_yscale("log")
    ax.set_xlabel("Adam step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _solver(args: argparse.Namespace, out: Path) -> int:
    from ..io.params_file import write_params
    from ..tuning.solver import evaluation_table, evaluation_verdicts, tune_solver

    try:
        res = tune_solver(
            args.family,
            cases=args.cases,
            steps=args.steps,
            iterations=args.iterations,
            lr=args.lr,
            seed=args.seed,
            heldout_seed=args.heldout_seed,
            heldout_cases=args.heldout_cases,
            heldout_horizon=args.heldout_horizon,
            horizon=args.horizon,
            anderson=args.anderson,
            loss=args.loss,
            tol=args.tol,
            progress=None if not args.quiet else False,
        )
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    st = res.settings
    write_params(
        out / "params.json",
        example=st["example"],
        rho_scale=res.rho_scale,
        relaxation=res.relaxation,
        tuned_for={
            "formulation": "local_explicit",
            "anderson": int(args.anderson),
            "dtype": "float32" if args.float32 else "float64",
            "tol": float(args.tol),
        },
        provenance={"command": "ampc tune", "objective": "solver", **st},
    )
    (out / "tune.json").write_text(
        json.dumps(
            {
                "objective": "solver",
                "settings": st,
                "rho_scale": list(res.rho_scale),
                "relaxation": res.relaxation,
                "history": res.history,
                "evaluation": res.evaluation,
            },
            indent=2,
        )
        + "\n"
    )
    _loss_figure(res.history, out / "loss.png", f"{args.family}: K = {args.iterations}")
    rs = ", ".join(f"{x:.4g}" for x in res.rho_scale)
    print(
        f"tuned rho scale ({', '.join(st['objectives'])}) = {rs}; relaxation "
        f"{res.relaxation:.4g} (in {st['train_seconds']:.0f} s)"
    )
    print(evaluation_table(res.evaluation))
    for line in evaluation_verdicts(res.evaluation):
        print(line)
    for name in ("params.json", "tune.json", "loss.png"):
        print(f"wrote {out / name}")
    return 0


def _weights(args: argparse.Namespace, out: Path) -> int:
    from ..io.params_file import write_params
    from ..sweep.families import family

    try:
        from ..tuning.weights import tune_weights, weights_table, weights_verdicts
    except ImportError as exc:
        return fail(f"--objective weights: the weight tuner is not available ({exc})")
    try:
        fam = family(args.family)
        if fam.kind != "loop":
            raise ValueError(
                f"family: --objective weights needs a loop family (cruise_lane_change), "
                f"got {fam.name!r} ({fam.kind})"
            )
        cases = fam.sample(args.cases, seed=args.seed)
        heldout = fam.sample(args.cases, seed=args.heldout_seed)
        res = tune_weights(
            cases.config,
            cases,
            heldout=heldout,
            steps=args.steps,
            iterations=args.iterations,
            lr=args.lr,
            progress=not args.quiet,
        )
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    cfg = cases.config
    st = {
        "family": args.family,
        "cases": args.cases,
        "steps": args.steps,
        "iterations": args.iterations,
        "lr": args.lr,
        "seed": args.seed,
    }
    write_params(
        out / "params.json",
        example=cfg.example,
        formulation=cfg.formulation,
        settings=res.settings,
        provenance={"command": "ampc tune", "objective": "weights", **st},
    )
    doc = {
        "objective": "weights",
        "settings": st,
        "weights": res.settings,
        "history": res.history,
        "evaluation": res.evaluation,
    }
    (out / "tune.json").write_text(json.dumps(doc, indent=2, default=_plain) + "\n")
    _loss_figure(res.history, out / "loss.png", f"{args.family}: weights")
    run = res.evaluation["run"]
    print(
        f"tuned weights in {run['tune_seconds']:.0f} s: "
        + ", ".join(f"{k}={v:.4g}" for k, v in res.settings.items())
    )
    print(weights_table(res.evaluation))
    for line in weights_verdicts(res.evaluation):
        print(line)
    print("per case and the run's settings: tune.json")
    for name in ("params.json", "tune.json", "loss.png"):
        print(f"wrote {out / name}")
    return 0


def _warm_start(args: argparse.Namespace, out: Path) -> int:
    from ..io.params_file import write_params
    from ..tuning.warm_start import start_table, tune_warm_start

    try:
        hidden = tuple(int(h) for h in args.hidden.split(",") if h.strip())
    except ValueError:
        return fail(f"--hidden: expected comma-separated layer widths, got {args.hidden!r}")
    loss = args.loss if args.loss in ("error", "residual") else None
    if loss is None:
        return fail(
            f"--loss: {args.loss!r} is not a loss of --objective warm_start (error, residual)"
        )
    try:
        res = tune_warm_start(
            args.family,
            cases=args.cases,
            seed=args.seed,
            pretrain_steps=args.pretrain_steps,
            steps=args.steps,
            iterations=args.iterations,
            schedule=args.schedule,
            hidden=hidden,
            lr=args.lr,
            batch=args.batch,
            loss=loss,
            anderson=args.anderson,
            tol=args.tol,
            horizon=args.horizon,
            heldout_cases=max(args.heldout_cases, 1),
            heldout_seed=args.heldout_seed,
            shifted_seed=args.shifted_seed,
            evaluate=args.heldout_cases > 0,
            progress=None if not args.quiet else False,
        )
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    st = res.settings
    tuned_for = {k: v for k, v in st["tuned_for"].items()}
    write_params(
        out / "params.json",
        example=st["example"],
        rho_scale=tuned_for["rho_scale"],
        relaxation=tuned_for["relaxation"],
        warm_start=res.model,
        tuned_for=tuned_for,
        provenance={
            "command": "ampc tune",
            "objective": "warm_start",
            **{k: v for k, v in st.items() if k != "tuned_for"},
        },
    )
    doc = {
        "objective": "warm_start",
        "settings": st,
        "model": repr(res.model),
        "history": res.history,
        "evaluation": res.evaluation,
    }
    (out / "tune.json").write_text(json.dumps(doc, indent=2, default=_plain) + "\n")
    losses = [h for h in res.history if "loss" in h]
    if losses:
        _loss_figure(losses, out / "loss.png", f"{args.family}: learned start")
    print(
        f"trained {res.model!r}: {res.model.n_parameters} weights on {st['pairs']} "
        f"{'control steps' if st['kind'] == 'loop' else 'cases'} in {st['train_seconds']:.0f} s"
    )
    if res.evaluation:
        print(start_table(res.evaluation))
    for name in ("params.json", "tune.json", *(("loss.png",) if losses else ())):
        print(f"wrote {out / name}")
    return 0


def _plain(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


def _solver_header(args: argparse.Namespace) -> str | int:
    """The header line naming the solver settings tuning runs under (the family's
    example's defaults, as ``simulate`` runs them, where not given); sets
    ``args.anderson`` for the solver objective. An exit code on a bad family."""
    from ..sweep.families import FAMILIES
    from ..tuning.warm_start import command_settings

    fam = FAMILIES.get(args.family)
    if fam is None:
        return fail(f"--family: expected one of {sorted(FAMILIES)}, got {args.family!r}")
    cfg = fam.sample(1).config
    ex = None if cfg is None else cfg.example
    st = command_settings(ex, anderson=args.anderson)
    source = f"the {ex} example's defaults" if ex else "the paper's plain iteration"
    if args.objective == "solver":
        if args.anderson is None:  # the residual loss unrolls plain ADMM
            args.anderson = 0 if args.loss == "residual" else st["anderson"]
        return (
            f"ampc tune: solver on {args.family}, Anderson {args.anderson} ({source} "
            f"where not given; rho scale and relaxation are what is tuned)"
        )
    if args.objective == "weights":
        return (
            f"ampc tune: weights on {args.family}, the closed loop's solver ({source}); "
            f"{args.steps} Adam steps, each through {args.cases} closed loops, then the "
            "default and tuned weights run on the training, held-out and example scenarios: "
            "minutes (the bar shows the estimate)"
        )
    rs = ", ".join(f"{x:g}" for x in st["rho_scale"])
    return (
        f"ampc tune: warm_start on {args.family}, rho scale ({rs}), relaxation "
        f"{st['relaxation']:g}, Anderson {st['anderson']} ({source} where not given)"
    )


def cmd_tune(args: argparse.Namespace) -> int:
    """``ampc tune``: exit 0 with the files written, 2 on bad input."""
    if args.family is None:
        args.family = "cruise_lane_change" if args.objective == "weights" else "cruise_step"
    for key, value in DEFAULTS[args.objective].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if not args.float32:
        import jax

        jax.config.update("jax_enable_x64", True)
    header = _solver_header(args)
    if isinstance(header, int):
        return header
    print(header)
    if args.heldout_cases < (0 if args.objective == "warm_start" else 1):
        return fail(f"--heldout-cases: expected an integer >= 1, got {args.heldout_cases}")
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    out = Path(args.out)
    run = {"solver": _solver, "weights": _weights, "warm_start": _warm_start}[args.objective]
    return run(args, out)


def add_tune_command(sub: Any) -> None:
    """Register ``ampc tune`` on the ``ampc`` sub-parsers."""
    p = sub.add_parser(
        "tune",
        help="gradient tuning of the solver's rho scales and relaxation (or the weights)",
        description="Tune Local Explicit's rho scales (one per objective) and "
        "over-relaxation with Adam through K unrolled ADMM iterations from a cold start, "
        "so that they land closest to the integrated optimum (Clarabel) on a training "
        "batch of a step family; then compare iterations to tolerance on held-out cases "
        "with eq.opt_ro's defaults and the best point of a rho-scale grid. "
        "--objective weights tunes the closed loop's weights instead; --objective "
        "warm_start trains a learned start (a network predicting the ADMM iterate a "
        "solve starts from, and a schedule of the first iterations' rho and alpha) "
        "under the example's solver settings, saved in params.json's warm_start.",
    )
    p.add_argument(
        "--family",
        default=None,
        help="the scenario family: a step family (cruise_step, stability_step, generated) "
        "for --objective solver, a loop family (cruise_lane_change, stability_manoeuvres) "
        "for weights "
        "(default: cruise_step, or cruise_lane_change with --objective weights)",
    )
    p.add_argument(
        "--objective",
        choices=("solver", "weights", "warm_start"),
        default="solver",
        help="what to tune: the solver's speed, the closed loop's weights or a learned "
        "start; weights with the defaults takes about 15 min on 2 busy cores (8.7 s an "
        "Adam step at load 11, bench/bench_compile.py), less with fewer --cases or "
        "--steps (default: solver)",
    )
    p.add_argument(
        "--cases",
        type=arg_type(at_least_one, int),
        default=None,
        help="training cases (a loop family: closed loops, every control step a pair) "
        "(default: 32; 512 with --objective warm_start)",
    )
    p.add_argument(
        "--steps",
        type=arg_type(at_least_one, int),
        default=None,
        help="Adam steps (of the unrolled phase with --objective warm_start) (default: 100)",
    )
    p.add_argument(
        "--iterations",
        type=arg_type(at_least_one, int),
        default=None,
        help="K, the unrolled ADMM iterations of the loss (per control step with "
        "--objective weights) (default: 10; 6 with --objective warm_start)",
    )
    p.add_argument(
        "--lr",
        type=arg_type(positive_finite),
        default=None,
        help="Adam's learning rate (default: 0.1; 3e-3 with --objective warm_start, "
        "and a 30th of it in the unrolled phase)",
    )
    p.add_argument(
        "--pretrain-steps",
        type=int,
        default=1500,
        help="--objective warm_start: Adam steps of regression on the training cases' "
        "fixed points before the unrolled phase (default: 1500)",
    )
    p.add_argument(
        "--schedule",
        type=int,
        default=0,
        help="--objective warm_start: k, the first iterations given their own trained "
        "(rho, alpha); each costs one more factorisation per control step (default: 0)",
    )
    p.add_argument(
        "--hidden",
        default="64,64",
        help="--objective warm_start: the network's hidden layer widths (default: 64,64)",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=128,
        help="--objective warm_start: cases per Adam step (default: 128)",
    )
    p.add_argument(
        "--shifted-seed",
        type=int,
        default=2,
        help="--objective warm_start: the seed of the held-out cases in the family's "
        "other friction and speed range (default: 2)",
    )
    p.add_argument("--seed", type=int, default=0, help="the training cases' seed (default: 0)")
    p.add_argument(
        "--heldout-seed", type=int, default=1, help="the held-out cases' seed (default: 1)"
    )
    p.add_argument(
        "--heldout-cases",
        type=int,
        default=64,
        help="held-out cases of the evaluation (per held-out set; 0: no evaluation with "
        "--objective warm_start) (default: 64)",
    )
    p.add_argument(
        "--horizon",
        type=arg_type(at_least_one, int),
        default=None,
        help="the step family's horizon N_p (default: the example's)",
    )
    p.add_argument(
        "--heldout-horizon",
        type=arg_type(at_least_one, int),
        default=None,
        help="also evaluate on held-out cases at this horizon (default: none)",
    )
    p.add_argument(
        "--loss",
        choices=("error", "log", "residual"),
        default=None,
        help="error: mean normalised error ||U_K - U*||^2 / (||U*||^2 + N_p n_u); log: its "
        "geometric mean; residual: the smooth fraction of the K iterations above the "
        "tolerance (default: error)",
    )
    add_solver_flags(
        p,
        anderson="Anderson memory of the solver tuned and evaluated (default: the family's "
        "example's, as simulate runs it: 3 for cruise and stability; 0 for generated "
        "problems and for --loss residual, which unrolls plain ADMM)",
    )
    p.add_argument(
        "--tol",
        type=arg_type(positive_finite),
        default=1.0,
        help="eps_r = eps_s of the held-out evaluation, squared, in the rows' units "
        "(default: 1, the vehicle examples' closed-loop tolerance in Nm^2)",
    )
    add_output_flags(
        p,
        float32="tune and evaluate",
        quiet="no progress bar (default: shown)",
        out_required=True,
    )
    add_force(p)
    p.set_defaults(func=cmd_tune)
