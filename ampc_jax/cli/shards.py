"""``ampc sweep --shard I/N`` and ``ampc sweep-merge``: a sweep as array jobs, joined.

A cluster runs the shards of one sweep as independent jobs (a Slurm array,
``--shard $SLURM_ARRAY_TASK_ID/N``), each into a directory of its own, and
``ampc sweep-merge`` checks them (one spec, each shard once, each complete,
rows the spec's) and writes the table, ``sweep.json`` and figures an
unsharded run writes (:mod:`~ampc_jax.sweep.merge`, ``docs/sweeps.md``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from .args import fail, flag_error
from .outdir import add_force, claim_dir

__all__ = [
    "add_merge_command",
    "add_shard_flags",
    "cmd_sweep_merge",
    "holds_sweep",
    "quantile_lines",
    "shard_report",
]


def holds_sweep(path: Path) -> bool:
    """Whether ``path`` holds a sweep (``sweep.json`` or ``chunks/``): ``ampc sweep``
    resumes it or refuses it as another sweep's, whatever ``--force`` says."""
    return (path / "sweep.json").exists() or (path / "chunks").exists()


def _shard(text: str) -> Any:
    from ..sweep.store import Shard

    try:
        return Shard.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[-1]) from None


def add_shard_flags(p: Any) -> None:
    """``--shard`` and ``--force`` of ``ampc sweep``."""
    p.add_argument(
        "--shard",
        type=_shard,
        default=None,
        metavar="I/N",
        help="compute only shard I of N (counted from 0): the chunks I, I+N, I+2N, ... "
        "into this --out, one array job each; join the N directories with `ampc "
        "sweep-merge` (default: the whole sweep)",
    )
    add_force(
        p,
        "write into an --out that is not empty and holds no sweep (an --out holding this "
        "sweep is resumed, one of another sweep refused) (default: refuse it)",
    )


def quantile_lines(table: Any) -> list[str]:
    """Iterations (median, p95, max), the converged share and the worst e_sub per rho scale."""
    import numpy as np

    rho = table.column("rho_scale").to_numpy()
    it = table.column("iterations").to_numpy().astype(float)
    conv = table.column("converged").to_numpy()
    e = table.column("e_sub").to_numpy()
    lines = [
        f"{'rho scale':>10} {'median':>7} {'p95':>7} {'max':>6} {'conv %':>7} {'max e_sub':>10}"
    ]
    for s in np.unique(rho):
        m = rho == s
        ee = e[m & conv]
        worst = f"{np.nanmax(ee):10.2e}" if ee.size and np.isfinite(ee).any() else f"{'-':>10}"
        lines.append(
            f"{s:10.4g} {np.median(it[m]):7.0f} {np.percentile(it[m], 95):7.0f} "
            f"{it[m].max():6.0f} {100 * conv[m].mean():7.1f} {worst}"
        )
    return lines


def shard_report(summary: Any, spec: Any, shard: Any) -> int:
    """What ``ampc sweep --shard`` prints when its shard is done (exit 0)."""
    print(
        f"ampc sweep: shard {shard}: {summary.rows} rows of {spec.cases} cases x "
        f"{len(spec.rho)} rho points on {summary.devices} device(s); "
        f"{summary.chunks_run} chunk(s) run, {summary.chunks_skipped} skipped"
    )
    print(
        f"  shard: {summary.out} (join the {shard.count} shards' directories with "
        "`ampc sweep-merge DIR... --out OUT`)"
    )
    sys.stdout.flush()
    return 0


def cmd_sweep_merge(args: argparse.Namespace) -> int:
    """Run ``ampc sweep-merge`` (exit 0; 2 when a shard is missing, duplicated,
    unfinished or of another sweep, or on bad input)."""
    import jax

    from ..sweep.merge import merge_shards, read_shards

    try:
        shards = read_shards(args.shards)
    except ValueError as exc:
        return fail(exc)
    # the cases are drawn again to check the chunks: in the number format they were
    jax.config.update("jax_enable_x64", not shards[0][1]["spec"].get("float32", False))
    out = Path(args.out)
    if any(out.resolve() == d.resolve() for d, _, _ in shards):
        return fail(f"--out {args.out}: is one of the shards; merge into another directory")
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    progress = None if args.quiet else (lambda line: print(f"  checked {line}", flush=True))
    print(f"ampc sweep-merge: {len(shards)} shard(s) of sweep {shards[0][1].get('spec_hash')}")
    try:
        summary = merge_shards(args.shards, out, figures=not args.no_figures, progress=progress)
    except ValueError as exc:
        return fail(flag_error(exc, {"out": "--out"}))
    except OSError as exc:
        return fail(f"--out: {args.out}: {exc.strerror or exc}")
    import pyarrow.parquet as pq

    spec = shards[0][1]["spec"]
    print(
        f"ampc sweep-merge: {summary.rows} rows ({spec['cases']} cases x {len(spec['rho'])} "
        f"rho points) from {len(shards)} shard(s), {summary.chunks_run + summary.chunks_skipped} "
        f"chunk(s); solve {summary.solve_s:.1f} s, reference {summary.reference_s:.1f} s "
        "over the shards"
    )
    for line in quantile_lines(pq.read_table(summary.table)):
        print("  " + line)
    print(f"  table: {summary.table}")
    for f in summary.figures:
        print(f"  figure: {f}")
    sys.stdout.flush()
    return 0


def add_merge_command(sub: Any) -> None:
    """Register ``ampc sweep-merge``."""
    p = sub.add_parser(
        "sweep-merge",
        help="join the shards of an `ampc sweep --shard I/N` into one table",
        description=(
            "Check the directories of a sweep's N shards (one spec hash, each shard 0..N-1 "
            "exactly once, each finished, every chunk's rows the cases the spec draws) and "
            "write OUT/sweep.parquet, OUT/sweep.json and the figures, as the unsharded "
            "sweep writes them. A missing, duplicated, unfinished or foreign shard is "
            "refused by name and nothing is written."
        ),
    )
    p.add_argument(
        "shards",
        nargs="+",
        metavar="SHARD_DIR",
        help="the --out directories of the shards, in any order (required)",
    )
    p.add_argument("--out", required=True, help="output directory of the joined table (required)")
    add_force(p)
    p.add_argument("--no-figures", action="store_true", help="skip the figures (default: draw)")
    p.add_argument(
        "--quiet", action="store_true", help="no line per shard checked (default: one each)"
    )
    p.set_defaults(func=cmd_sweep_merge)
