"""Sweeps: many cases of a scenario family against a grid of solver parameters.

* :mod:`~.families` -- named, seeded scenario families (:func:`family`,
  :func:`register_family`): single control steps of each vehicle example over
  its envelope, generated problems, whole closed-loop manoeuvres;
* :mod:`~.engine` -- one compiled program over (case, point) pairs:
  per-pair freezing, compaction of the pairs still running, the pair axis
  sharded over every device of every process (:func:`sweep_solve`);
* :mod:`~.run` -- :func:`run_sweep` (``ampc sweep``): chunks streamed to
  Parquet, resumable, with figures (:mod:`~.figures`); one :class:`Shard` of
  it (``--shard I/N``);
* :mod:`~.merge` -- :func:`merge_shards` (``ampc sweep-merge``): the shards
  checked and joined into the unsharded run's table.

See ``docs/sweeps.md``.
"""

from .engine import PairResult, Work, bucket_sizes, pair_data, pair_params, solve_pairs, sweep_solve
from .families import FAMILIES, Family, LoopCases, StepCases, family, register_family
from .merge import merge_shards
from .run import SweepSpec, SweepSummary, rho_grid, run_sweep
from .store import Shard

__all__ = [
    "FAMILIES",
    "Family",
    "LoopCases",
    "PairResult",
    "Shard",
    "StepCases",
    "SweepSpec",
    "SweepSummary",
    "Work",
    "bucket_sizes",
    "family",
    "merge_shards",
    "pair_data",
    "pair_params",
    "register_family",
    "rho_grid",
    "run_sweep",
    "solve_pairs",
    "sweep_solve",
]
