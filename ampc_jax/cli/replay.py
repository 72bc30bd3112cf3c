"""``ampc replay``: a run that ``ampc run`` logged re-run offline, bit for bit and
with other settings, or (``--candump``) a drive's candump log through the
controller (docs/runtime.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from . import extras
from .args import arg_type, enable_x64, fail, positive_finite
from .outdir import add_force, claim_dir

__all__ = ["add_replay_command", "cmd_replay"]


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def cmd_replay(args: argparse.Namespace) -> int:
    """``ampc replay``: a logged run re-run offline, and with other settings; or
    (``--candump``) a drive's candump log through the controller."""
    missing = extras.missing_message("replay", extras.BUS)
    if missing:
        return fail(missing)
    enable_x64()
    from ..runtime.replay import replay_run

    if args.candump is not None:
        return _replay_candump(args)
    if args.log is None:
        return fail("replay: expected a run's output directory, or --candump FILE")
    if args.scenario is not None or args.lead_ms is not None:
        flag = "--scenario" if args.scenario is not None else "--lead-ms"
        return fail(f"{flag}: only with --candump (a run directory's run.json names it)")
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    rho = None
    if args.rho_scale:
        items = args.rho_scale.split(",")
        bad = [x for x in items if not _is_float(x)]
        if bad:
            return fail(f"--rho-scale: expected comma-separated numbers, got {bad[0]!r}")
        rho = tuple(float(x) for x in items)
        if not all(np.isfinite(r) and r > 0 for r in rho):
            return fail(f"--rho-scale: expected positive finite numbers, got {args.rho_scale!r}")
    progress = lambda line: print(line, flush=True)  # noqa: E731
    try:
        res = replay_run(
            Path(args.log),
            Path(args.out),
            rho_scales=rho,
            formulations=tuple(args.formulation or ()),
            float32=args.float32,
            progress=progress,
        )
    except (OSError, ValueError) as exc:
        return fail(f"replay: {exc}")
    d, lg = res["determinism"], res["log"]
    if not lg["complete"]:
        how = {
            False: f"it was killed (its process {lg['pid']} is gone)",
            True: f"it is still running (process {lg['pid']})",
            None: "killed, or still running on another machine",
        }[lg["alive"]]
        print(
            f"ampc: warning: {args.log} did not finish: {how}; no final logs were written, "
            f"replayed the {lg['ticks']} ticks its {lg['source']} holds",
            file=sys.stderr,
        )
    for note in lg["notes"]:
        print(f"ampc: warning: {note}", file=sys.stderr)
    if res.get("environment_mismatch"):
        print(
            f"ampc: warning: the run's environment differs from this one (run, now): "
            f"{res['environment_mismatch']}",
            file=sys.stderr,
        )
    print(
        f"checked {lg['ticks']} ticks of {lg['source']} against run.json and "
        f"{lg['frames_checked']} framed commands against bridge.log"
    )
    print(
        f"replayed {d['ticks']} ticks: {d['identical']} commands identical bit for bit, "
        f"{d['differ']} differ (max |dT| {d['max_abs_diff_nm']:g} Nm)"
    )
    for v in res["variants"]:
        print(
            f"  {v['variant']:<28} max |dT| {v['max_abs_diff_nm']:8.2f} Nm, rms "
            f"{v['rms_diff_nm']:7.2f} Nm, iterations mean {v['iterations_mean']:.1f}"
        )
    print(f"wrote {Path(args.out) / 'replay.json'}, {Path(args.out) / 'replay.parquet'}")
    return 0 if d["differ"] == 0 else 1


def _replay_candump(args: argparse.Namespace) -> int:
    """``ampc replay --candump FILE --scenario NAME``."""
    from ..runtime.candump import CandumpError, replay_candump
    from ..vehicle import SCENARIOS

    if args.log is not None:
        return fail(f"--candump: replays a candump log, not also the run directory {args.log!r}")
    if args.scenario is None:
        return fail("--scenario: required with --candump (the controller to replay)")
    if args.scenario not in SCENARIOS:
        return fail(
            f"--scenario: unknown scenario {args.scenario!r}; expected one of {sorted(SCENARIOS)}"
        )
    if args.rho_scale or args.float32 or len(args.formulation or ()) > 1:
        return fail(
            "--candump: replays one controller (one --formulation at most; no --rho-scale "
            "or --float32)"
        )
    lead = 25.0 if args.lead_ms is None else float(args.lead_ms)
    if not 0.0 < lead < 45.0:
        return fail(f"--lead-ms: expected a lead time in (0, 45) ms, got {args.lead_ms!r}")
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    out = Path(args.out)
    try:
        res = replay_candump(
            Path(args.candump),
            args.scenario,
            out,
            formulation=(args.formulation or [None])[0],
            lead_ms=lead,
            progress=lambda line: print(line, flush=True),
        )
    except CandumpError as exc:
        return fail(f"replay: {exc}")
    except OSError as exc:
        return fail(f"replay: {exc}", 1)
    by = ", ".join(f"{k} {v}" for k, v in sorted(res["frames_by_message"].items()))
    refused = sum(res["frames_refused"].values())
    print(
        f"read {args.candump}: {res['frames']} frames ({by}; {refused} refused, "
        f"{res['frames_other']} of other messages)"
    )
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(res["skipped"].items())) or "none"
    print(
        f"replayed {res['ticks']} ticks on {res['ticks_on']} (lead {lead:g} ms): "
        f"stepped {res['stepped']}, skipped {skipped}"
    )
    if res["compared"]:
        print(
            f"compared {res['compared']} active frames: {res['identical']} identical bit for "
            f"bit, {res['differ']} differ (max |dT| {res['max_abs_diff_nm']:g} Nm)"
        )
    else:
        print("the log holds no active torque frame to compare with")
    print(f"wrote {out / 'candump_replay.json'}, {out / 'candump_replay.parquet'}, "
          f"{out / 'candump_replay.png'}")  # fmt: skip
    return 0


def add_replay_command(sub: Any, formulations: list[str]) -> None:
    """Register ``replay`` (``formulations``: the controllers it may replay with)."""
    forms = formulations
    p = sub.add_parser(
        "replay",
        help="re-run a logged run offline, bit for bit and with other settings",
        description="Re-run the controller step on the states `ampc run` logged: the "
        "determinism check (every command reproduced bit for bit), then the same states "
        "with other rho scales (one vmapped batch), formulations or float32.",
    )
    p.add_argument(
        "log",
        nargs="?",
        default=None,
        help="the run's output directory (with ticks.parquet and run.json) (default: none, "
        "with --candump)",
    )
    p.add_argument(
        "--candump",
        metavar="FILE",
        default=None,
        help="replay a drive's candump log (candump -l) instead: its state frames through "
        "the controller at their timestamps, its torque frames compared with what the "
        "controller would have framed (needs --scenario) (default: none)",
    )
    p.add_argument(
        "--scenario",
        default=None,
        help="with --candump: the scenario the controller is set up for (default: none)",
    )
    p.add_argument(
        "--lead-ms",
        type=arg_type(positive_finite),
        default=None,
        help="with --candump: the state is read this long before each torque frame, as "
        "`ampc run --lead-ms` did (default: 25)",
    )
    p.add_argument(
        "--rho-scale",
        default=None,
        help="comma-separated factors on the run's own rho scales (the example's default, "
        "e.g. the cruise example's (1, 0.5): 1 replays the run's setting), replayed in one "
        "vmapped batch (default: none)",
    )
    p.add_argument(
        "--formulation",
        action="append",
        choices=forms,
        help="also replay with this formulation, repeatable; with --candump, the "
        "controller's formulation (default: none; with --candump the scenario's)",
    )
    p.add_argument("--float32", action="store_true", help="also replay in float32 (default: off)")
    p.add_argument("--out", default="replay", help="output directory (default: replay)")
    add_force(p)
    p.set_defaults(func=cmd_replay)
