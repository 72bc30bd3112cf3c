"""Training curve of a learned warm start: loss per Adam step and iterations to tolerance.

Trains a start network on a step family (``ampc_jax.tuning.warm_start.tune_warm_start``:
regression on the fixed points, then unrolled iterations of the solver as
``ampc simulate`` runs it) and records, per Adam step, the loss of each phase
and, every 25 unrolled steps, the validation split's iterations to tolerance
(mean, median, p95); then the held-out evaluation against eq.opt_ro's cold start
and the command's cold start (median, p95 and the worst first-step error
against Clarabel). Writes ``bench/results/bench_warm_start.json`` (``--out``;
``bench/_meta.py``) and the figure beside it (``.png``: the two phases' losses
and the validation iterations against the held-out cold starts' medians).

    python bench/bench_warm_start.py --family cruise_step --cases 512 --heldout-cases 1000
    python bench/bench_warm_start.py --heldout-cases 200 --finish   # also with the exact finish
    python bench/bench_warm_start.py --smoke      # a tiny training, no evaluation, nothing written
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _meta  # bench/_meta.py, beside this script

STEM = "bench_warm_start"


def _figure(history: list[dict[str, Any]], evaluation: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    for phase, colour in (("pretrain", "C0"), ("unrolled", "C1")):
        rows = [h for h in history if h.get("phase") == phase]
        if not rows:
            continue
        offset = 0 if phase == "pretrain" else sum(h.get("phase") == "pretrain" for h in history)
        a.plot([offset + h["step"] for h in rows], [h["loss"] for h in rows], colour, label=phase)
    a.set_yscale("log")
    a.set_xlabel("Adam step")
    a.set_ylabel("loss")
    a.set_title("training loss (regression, then unrolled)")
    a.grid(True, alpha=0.3)
    a.legend()
    val = [h for h in history if h.get("phase") == "validation" and isinstance(h["step"], int)]
    if val:
        b.plot([h["step"] for h in val], [h["iterations"][1] for h in val], "o-", label="median")
        b.plot([h["step"] for h in val], [h["iterations"][2] for h in val], "s--", label="p95")
    for ev in list(evaluation.values())[:1]:
        for r, style in zip(ev.get("rows", [])[:2], (":", "-."), strict=False):
            b.axhline(r["median"], color="grey", ls=style, label=f"held-out {r['name']} median")
    b.set_xlabel("unrolled Adam step")
    b.set_ylabel("iterations to tolerance")
    b.set_title("validation split (learned start)")
    b.grid(True, alpha=0.3)
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _with_finish(args: argparse.Namespace, model: Any, st: dict[str, Any]) -> dict[str, Any]:
    """The held-out evaluation again, every start ended by the exact finish: does the
    learned start still save iterations once the finish solves the active set's QP?"""
    from ampc_jax.sweep import family
    from ampc_jax.tuning.start_evaluation import evaluate_starts

    fam = family(args.family)
    sets = [("seed 1", 1, {})]
    if "ranges" in fam.options:
        sets.append(("seed 2, shifted ranges", 2, {"ranges": "shifted"}))
    out = {}
    for label, seed, extra in sets:
        held = fam.sample(args.heldout_cases, seed=seed, **extra)
        out[label] = evaluate_starts(held, model, st["tuned_for"], finish="active_set")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", default="cruise_step", help="a step family (default cruise_step)")
    ap.add_argument("--cases", type=int, default=512, help="training cases (default 512)")
    ap.add_argument("--pretrain-steps", type=int, default=1500, help="(default 1500)")
    ap.add_argument("--steps", type=int, default=100, help="unrolled Adam steps (default 100)")
    ap.add_argument("--iterations", type=int, default=6, help="K unrolled (default 6)")
    ap.add_argument("--schedule", type=int, default=0, help="scheduled iterations (default 0)")
    ap.add_argument("--hidden", default="64,64", help="hidden widths (default 64,64)")
    ap.add_argument("--heldout-cases", type=int, default=1000, help="(default 1000)")
    ap.add_argument(
        "--finish",
        action="store_true",
        help="also evaluate every start with Local Explicit's exact finish (iterations to a "
        "verified finish; default: the paper's iteration only)",
    )
    ap.add_argument("--smoke", action="store_true", help="tiny sizes; nothing written")
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args(argv)
    if args.smoke:
        args.cases, args.pretrain_steps, args.steps = 16, 30, 2
        args.iterations, args.hidden, args.heldout_cases = 2, "4", 8

    import jax

    jax.config.update("jax_enable_x64", True)
    from ampc_jax.tuning.warm_start import start_table, tune_warm_start

    run = _meta.Run(_meta.output_path(args, STEM))
    res = tune_warm_start(
        args.family,
        cases=args.cases,
        pretrain_steps=args.pretrain_steps,
        steps=args.steps,
        iterations=args.iterations,
        schedule=args.schedule,
        hidden=tuple(int(h) for h in args.hidden.split(",")),
        batch=min(128, args.cases),
        heldout_cases=args.heldout_cases,
        evaluate=not args.smoke,  # a smoke run trains only (the held-out solves compile 6 programs)
        progress=False,
    )
    st = res.settings
    print(
        f"{args.family}: {res.model!r}, {st['pairs']} training cases, "
        f"{st['pretrain_steps']} + {st['steps']} Adam steps in {st['train_seconds']:.0f} s"
    )
    val = [h for h in res.history if h["phase"] == "validation"]
    for h in val:
        mean, med, p95 = h["iterations"]
        print(
            f"validation after {h['step']} unrolled steps: mean {mean:.2f} median {med:g} p95 {p95:g}"
        )
    if res.evaluation:
        print(start_table(res.evaluation))
    run.results = {"settings": st, "history": res.history, "evaluation": res.evaluation}
    if args.finish and res.evaluation:
        run.results["evaluation_finish"] = fin = _with_finish(args, res.model, st)
        print("\nthe same starts with the exact finish (iterations to a verified finish):")
        print(start_table(fin))
    path = run.finish()
    if path is not None:
        png = path.with_suffix(".png")
        _figure(res.history, res.evaluation, png)
        print(f"figure {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
