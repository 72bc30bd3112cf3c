"""ampc-jax: multi-objective agent-based MPC (consensus ADMM, Local Explicit) in pure JAX.

What importing the package changes, and why (the one global effect of the
import; it is chosen over an explicit call because the flags below are what the
package's measured speed is, for a script and a notebook as for ``ampc``):

Importing appends flags to the environment variable ``XLA_FLAGS``, nothing
else in the environment, no ``jax.config`` option and no other process state.
XLA reads ``XLA_FLAGS`` once, when JAX's CPU backend starts (the first
computation, not ``import jax``), so the flags apply to every JAX computation
of the process, this package's and any other's, and only if ``ampc_jax`` is
imported before the first one. A flag already named in ``XLA_FLAGS`` is left as
the user set it; ``AMPC_KEEP_XLA_FLAGS=1`` leaves ``XLA_FLAGS`` untouched.
The flags (:data:`XLA_WORKAROUND_FLAGS`, :data:`XLA_PERFORMANCE_FLAGS`):

* ``--xla_cpu_multi_thread_eigen=false`` and
  ``--xla_cpu_enable_concurrency_optimized_scheduler=false``, always. Rule:
  set both; reason: batched XLA:CPU programs can deadlock on small (2-core)
  machines. The deadlock's cause is XLA:CPU's batched LAPACK kernels, which
  the solvers do not call under ``vmap``; ``rho_method="eigh"`` and
  rank-deficient constraint rows still do (docs/known-issues.md).
* with jaxlib 0.10.x only (the flag is experimental; an unknown flag aborts
  XLA), ``--xla_cpu_experimental_ynn_fusion_type=``: no YNNPACK fusions.
  Reason: on this package's small matrices YNNPACK's per-call overhead
  dominates a batched Local Explicit iteration (the batched throughput of
  ``bench/bench_local_explicit.py --only throughput``; docs/known-issues.md).
* with jaxlib 0.10.x only,
  ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000``:
  XLA:CPU compiles a ``while_loop`` whose accessed bytes are under this limit
  (1 kB by default) into one kernel instead of running its body kernel by
  kernel. Rule: a limit that covers the solvers' iteration loops up to
  N_p = 20 (and batches of 32 at N_p = 10 and 20); reason: a step at these
  sizes is mostly per-kernel cost, so one kernel per loop is what makes a
  control step and a closed loop fast (``bench/bench_call_overhead.py``,
  docs/benchmarks.md "The cost of a call"). Skipped when ``XLA_FLAGS``
  already sets ``--xla_backend_extra_options``.

``tests/test_package.py`` pins this list: the import changes ``XLA_FLAGS``
alone, by exactly the flags named here.
"""

import os as _os

__version__ = "0.1.0"

XLA_WORKAROUND_FLAGS = (
    "--xla_cpu_multi_thread_eigen=false",
    "--xla_cpu_enable_concurrency_optimized_scheduler=false",
)


# Performance flags, only for the jaxlib versions they were measured with.
XLA_PERFORMANCE_FLAGS = {
    "0.10.": (
        "--xla_cpu_experimental_ynn_fusion_type=",
        "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000",
    )
}


def _jaxlib_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("jaxlib")
    except PackageNotFoundError:
        return ""


def _apply_xla_workaround() -> None:
    if _os.environ.get("AMPC_KEEP_XLA_FLAGS") == "1":
        return
    flags = _os.environ.get("XLA_FLAGS", "")
    wanted = list(XLA_WORKAROUND_FLAGS)
    jaxlib = _jaxlib_version()
    for prefix, extra in XLA_PERFORMANCE_FLAGS.items():
        if jaxlib.startswith(prefix):
            wanted.extend(extra)
    missing = [f for f in wanted if f.split("=")[0] not in flags]
    if missing:
        _os.environ["XLA_FLAGS"] = " ".join([flags, *missing]).strip()


_apply_xla_workaround()

# The public API, imported after the flags are set (importing JAX does not start
# its CPU backend; the first computation does).
from .admm import ADMMState, SolverParams, cold_state, shift_state, solver_params  # noqa: E402
from .formulations import (  # noqa: E402
    FORMULATIONS,
    FormulationInfo,
    IntegratedADMM,
    LocalExplicit,
    formulation,
    formulation_info,
    formulation_names,
    register_formulation,
)
from .problem import (  # noqa: E402
    Agent,
    Constraint,
    Objective,
    Problem,
    ProblemData,
    ProblemError,
    Topology,
    make_data,
)
from .reference import solve_reference  # noqa: E402
from .results import STATUS, SolveResult, SolveStats, Status, status_name, usable  # noqa: E402

__all__ = [
    "FORMULATIONS",
    "STATUS",
    "ADMMState",
    "Agent",
    "Constraint",
    "FormulationInfo",
    "IntegratedADMM",
    "LocalExplicit",
    "Objective",
    "Problem",
    "ProblemData",
    "ProblemError",
    "SolveResult",
    "SolveStats",
    "Status",
    "SolverParams",
    "Topology",
    "__version__",
    "cold_state",
    "formulation",
    "formulation_info",
    "formulation_names",
    "make_data",
    "register_formulation",
    "shift_state",
    "solve_reference",
    "solver_params",
    "status_name",
    "usable",
]
