"""``ampc sweep``: cases of a scenario family against a grid of rho scales, to Parquet."""

from __future__ import annotations

import argparse
import os
import sys
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
from .outdir import claim_dir
from .shards import add_merge_command, add_shard_flags, holds_sweep, quantile_lines, shard_report

__all__ = ["add_sweep_command", "cmd_sweep"]

RHO_DEFAULT = "0.1:10:13"

_FLAGS = {
    name: "--" + name.replace("_", "-")
    for name in (
        "family",
        "cases",
        "rho",
        "formulation",
        "seed",
        "tol",
        "relaxation",
        "anderson",
        "max_iter",
        "horizon",
        "chunk",
        "duration",
        "groups",
        "out",
        "shard",
    )
}
"""SweepSpec's fields (and ``out``) -> their flags, for the library's messages."""


def _force_cpu_devices(n: int) -> None:
    """``n`` CPU devices (XLA's host-platform count; read when JAX's backend starts)."""
    flag = f"--xla_force_host_platform_device_count={n}"
    old = os.environ.get("XLA_FLAGS", "")
    parts = [p for p in old.split() if not p.startswith("--xla_force_host_platform_device_count")]
    os.environ["XLA_FLAGS"] = " ".join([*parts, flag])


def _solver_defaults(args: argparse.Namespace) -> tuple[float, int, str]:
    """(relaxation, Anderson memory, where they come from): the flags where given,
    else the family's example's ``solver_defaults`` (what ``simulate`` and
    ``tune`` run), else the paper's plain iteration (1.0, 0) for a problem of no
    example."""
    from ..sweep.families import FAMILIES
    from ..vehicle.examples import example

    # the family's example by name: sampling a case would compile before the checks
    name = FAMILIES[args.family].example
    d = example(name).solver_defaults if name is not None else {}
    relaxation = float(d.get("relaxation", 1.0)) if args.relaxation is None else args.relaxation
    anderson = int(d.get("anderson", 0)) if args.anderson is None else args.anderson
    if args.relaxation is not None and args.anderson is not None:
        source = "as given"
    elif name is not None:
        source = f"the {name} example's defaults where not given"
    else:
        source = "the paper's plain iteration where not given"
    return relaxation, anderson, source


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run ``ampc sweep`` (exit 0; 2 on bad input)."""
    if args.cpu_devices > 1:
        _force_cpu_devices(args.cpu_devices)
    import jax

    if args.num_processes > 1:
        if args.coordinator is None or args.process_id is None:
            return fail("--coordinator: several processes need --coordinator and --process-id")
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=args.coordinator,
            num_processes=args.num_processes,
            process_id=args.process_id,
        )
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    from ..sweep import SweepSpec, rho_grid, run_sweep
    from ..sweep.families import FAMILIES

    if args.family not in FAMILIES:
        return fail(f"--family: expected one of {sorted(FAMILIES)}, got {args.family!r}")
    try:
        grid = rho_grid(args.rho)
    except ValueError as exc:
        return fail(f"--rho: {exc}")
    err = claim_dir(args.out, args.force, resumes=holds_sweep)
    if err:
        return fail(err)
    try:
        relaxation, anderson, source = _solver_defaults(args)
        if jax.process_index() == 0:
            print(
                f"ampc sweep: {args.family}, relaxation {relaxation:g}, Anderson {anderson} "
                f"({source})"
            )
        spec = SweepSpec(
            family=args.family,
            cases=args.cases,
            rho=grid,
            formulation=args.formulation,
            seed=args.seed,
            tol=args.tol,
            relaxation=relaxation,
            anderson=anderson,
            max_iter=args.max_iter,
            horizon=args.horizon,
            chunk=args.chunk,
            float32=args.float32,
            compaction=not args.no_compaction,
            duration=args.duration,
            groups=args.groups,
        )
        summary = run_sweep(
            spec,
            args.out,
            progress=False if args.quiet else None,
            figures=not args.no_figures,
            shard=args.shard,
        )
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    except OSError as exc:  # the output directory went away or filled up
        return fail(f"--out: {args.out}: {exc.strerror or exc}")
    if jax.process_index() != 0:
        return 0
    if args.shard is not None:
        return shard_report(summary, spec, args.shard)
    import pyarrow.parquet as pq

    tab = pq.read_table(summary.table)
    solves = summary.rows / summary.solve_s if summary.solve_s > 0 else float("nan")
    print(
        f"ampc sweep: {summary.rows} rows ({spec.cases} cases x {len(grid)} rho points) "
        f"on {summary.devices} device(s), {summary.processes} process(es); "
        f"{summary.chunks_run} chunk(s) run, {summary.chunks_skipped} skipped"
    )
    if summary.chunks_run and not summary.computed:  # closed loops
        print(
            f"  {summary.solve_s:.1f} s for {summary.rows} closed loops "
            f"({summary.rows / summary.solve_s:.2f} loops/s, compile included)"
        )
    elif summary.chunks_run:
        steady = summary.steady_pairs_per_s
        rate = (
            f"{steady:,.0f} case-point solves/s after the first chunk"
            if steady
            else f"{solves:,.0f} case-point solves/s, compile included"
        )
        print(
            f"  solve {summary.solve_s:.1f} s ({rate}), reference {summary.reference_s:.1f} s, "
            f"waste {summary.waste:.2f}x (pair-iterations computed / needed)"
        )
    for line in quantile_lines(tab):
        print("  " + line)
    print(f"  table: {summary.table}")
    for f in summary.figures:
        print(f"  figure: {f}")
    sys.stdout.flush()
    return 0


def add_sweep_command(sub: Any) -> None:
    """Register ``ampc sweep``."""
    from ..formulations import DEFAULT_FORMULATION, formulation_names

    p = sub.add_parser(
        "sweep",
        help="iterations, accuracy and status over many cases and rho scales (Parquet)",
        description=(
            "Solve cases of a scenario family for every point of a rho-scale grid in one "
            "compiled program (compaction; sharded over all devices), compare each first "
            "step with the integrated optimum (Clarabel), and write OUT/sweep.parquet, "
            "OUT/sweep.json and figures. A rerun into the same OUT resumes. --shard I/N "
            "runs one share as an array job; `ampc sweep-merge` joins the shards."
        ),
    )
    p.add_argument(
        "--family",
        required=True,
        help=(
            "scenario family: cruise_step, stability_step, generated (single steps) or "
            "cruise_lane_change (closed loops) (required)"
        ),
    )
    p.add_argument(
        "--cases",
        type=arg_type(at_least_one, int),
        default=1000,
        help="number of cases (default: 1000)",
    )
    p.add_argument(
        "--rho",
        default=RHO_DEFAULT,
        help=f"rho-scale grid, LO:HI:N geometric or a comma list (default: {RHO_DEFAULT})",
    )
    p.add_argument(
        "--formulation",
        default=DEFAULT_FORMULATION,
        choices=sorted(formulation_names()),
        help="formulation (default: local_explicit)",
    )
    p.add_argument("--seed", type=int, default=0, help="the family's seed (default: 0)")
    p.add_argument(
        "--tol",
        type=arg_type(positive_finite),
        default=None,
        help="eps_r = eps_s of eq.Convergence (default: 1 Nm^2 for the vehicle families, 1e-6 otherwise)",
    )
    add_solver_flags(
        p,
        relaxation="over-relaxation in (0, 2) (default: the family's example's, as simulate "
        "runs it: 1.5 for cruise and stability; 1.0, the paper's, for generated problems)",
        anderson="Anderson memory (default: the family's example's, as simulate runs it: 3 "
        "for cruise and stability; 0 for generated problems)",
        max_iter="iteration cap (default: 500)",
        max_iter_default=500,
    )
    p.add_argument(
        "--horizon",
        type=arg_type(at_least_one, int),
        default=None,
        help="N_p (default: the family's own: 2 cruise, 3 stability, 10 generated)",
    )
    p.add_argument(
        "--chunk",
        type=arg_type(at_least_one, int),
        default=256,
        help="cases per chunk: the memory bound and the resume grain (default: 256)",
    )
    p.add_argument(
        "--groups",
        choices=("paper", "full"),
        default=None,
        help=(
            "agent groups of a vehicle step family: paper (the example's, what the closed "
            "loop runs; its cruise groups drop a weak coupling) or full (every agent in "
            "every group: exact) (default: paper)"
        ),
    )
    p.add_argument(
        "--duration",
        type=arg_type(positive_finite),
        default=None,
        help="seconds of each closed-loop run of a loop family (default: the scenario's)",
    )
    p.add_argument(
        "--no-compaction",
        action="store_true",
        help="plain vmap of the while loop (default: compaction on)",
    )
    p.add_argument(
        "--cpu-devices",
        type=arg_type(at_least_one, int),
        default=1,
        help="CPU devices to force (XLA host-platform count) and shard over (default: 1)",
    )
    p.add_argument(
        "--num-processes",
        type=arg_type(at_least_one, int),
        default=1,
        help="processes of a jax.distributed run (default: 1)",
    )
    p.add_argument(
        "--process-id", type=int, default=None, help="this process's index (default: none)"
    )
    p.add_argument(
        "--coordinator",
        default=None,
        help="host:port of the jax.distributed coordinator (default: none)",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the figures (default: draw)")
    add_output_flags(
        p, float32="solve", quiet="no progress bar (default: on a terminal)", out="sweep"
    )
    add_shard_flags(p)
    p.set_defaults(func=cmd_sweep)
    add_merge_command(sub)
