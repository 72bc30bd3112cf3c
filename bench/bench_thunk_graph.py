"""Does XLA:CPU run a closed-loop control step inline, or split it onto its pool?

XLA:CPU's thunk executor (jaxlib 0.10) walks a program's thunk graph with a
FIFO ready queue and hands half of the ready thunks to its intra-op thread
pool whenever more than 8 are ready at once (``ExecuteSession::kSplitThreshold``),
then waits for them: 10 to 40 us per control step where it was seen
(docs/known-issues.md). Whether a step crosses that line depends on the shape of its
graph, so small code changes can flip it.

This script compiles the closed-loop controller step (``solve`` on logged
ProblemData, warm started) of Local Explicit and of the IntegratedADMM it is
timed against, for both vehicle examples with their default solver options,
each in a child process with ``TF_CPP_VMODULE=thunk_executor=6`` so that XLA
prints the top-level thunk graph; it then replays the executor's FIFO queue on
that graph and prints the most thunks waiting at once::

    taskset -c 1 python bench/bench_thunk_graph.py            # all four
    taskset -c 1 python bench/bench_thunk_graph.py --anderson 0
    python bench/bench_thunk_graph.py --smoke   # the cruise example only; no result file

A "max waiting" above 8 means the step splits onto the pool. The replay is a
model of ``ThunkExecutor::Execute`` (jaxlib 0.10, XLA's
``backends/cpu/runtime/thunk_executor.cc``) with every thunk completing
inline; it agreed with ``jax.profiler`` traces on the stability example.
Result file: ``bench/results/bench_thunk_graph.json`` (``--out``; ``bench/_meta.py``).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys

import _meta  # bench/_meta.py, beside this script

STEM = "bench_thunk_graph"
SCENARIOS = ("cruise_lane_change", "stability_dlc")

CHILD = r"""
import sys
import jax
jax.config.update("jax_enable_x64", True)
from ampc_jax.closed_loop import config_for, controller_for, simulate
from ampc_jax.formulations import IntegratedADMM, LocalExplicit

scenario, solver_kind, anderson = sys.argv[1], sys.argv[2], sys.argv[3]
kw = {} if anderson == "default" else {"anderson": int(anderson)}
cfg = config_for(scenario, shadow=False, **kw)
log = simulate(scenario, cfg, duration=1.0).log
T = controller_for(cfg).topology
data = jax.tree.map(lambda x: x[10], log.data)
if solver_kind == "le":
    solver = LocalExplicit(T, max_iter=cfg.max_iter, anderson=cfg.anderson)
    params = cfg.loop_params().controller.solver
    warm = jax.tree.map(lambda x: x[10], log.warm)
else:
    solver = IntegratedADMM(T, max_iter=cfg.max_iter, anderson=cfg.anderson)
    params = solver.params(rho=cfg.integrated_rho_scale, relaxation=cfg.relaxation,
                           tol_primal=cfg.tol_primal, tol_dual=cfg.tol_dual)
    warm = solver.cold_state(data.A.dtype)
print("MARKER-BEGIN", file=sys.stderr, flush=True)
f = jax.jit(solver.solve).lower(data, params, warm).compile()
jax.block_until_ready(f(data, params, warm))
"""


def top_level_graph(text: str) -> tuple[list[tuple[str, list[str]]], int]:
    """The largest thunk graph XLA printed: (name, dependency names) per thunk,
    and the number of thunks it has.

    absl truncates long log messages, so a large graph may be cut short; the
    thunks are printed in order and depend only on earlier ones, so the
    returned prefix is a closed graph of the program's first thunks.
    """
    lines = text.split("\n")
    heads = [i for i, line in enumerate(lines) if "ThunkExecutor: #thunks=" in line]
    if not heads:
        raise RuntimeError("XLA printed no thunk graph (is this jaxlib's thunk runtime?)")
    best = max(heads, key=lambda i: int(re.search(r"#thunks=(\d+)", lines[i]).group(1)))
    n = int(re.search(r"#thunks=(\d+)", lines[best]).group(1))
    nodes = []
    for line in lines[best + 1 : best + 1 + n]:
        m = re.search(r"op_name=(\S+), kind=\w+, dependencies=\[(.*?)\], source=", line)
        if m is None:  # the message was truncated here
            break
        deps = [d.strip() for d in m.group(2).split(",") if d.strip()]
        nodes.append((m.group(1), deps))
    return nodes, n


def max_waiting(nodes: list[tuple[str, list[str]]]) -> tuple[int, int]:
    """(sources, most thunks waiting in the FIFO queue right after a pop)."""
    where: dict[str, list[int]] = {}
    for i, (name, _) in enumerate(nodes):
        where.setdefault(name, []).append(i)
    ins = [[max(j for j in where[d] if j < i) for d in deps] for i, (_, deps) in enumerate(nodes)]
    outs: list[list[int]] = [[] for _ in nodes]
    for i, deps in enumerate(ins):
        for j in deps:
            outs[j].append(i)
    count = [len(d) for d in ins]
    queue = [i for i in range(len(nodes)) if count[i] == 0]
    sources, worst = len(queue), 0
    while queue:
        i = queue.pop(0)
        worst = max(worst, len(queue))
        for o in outs[i]:
            count[o] -= 1
            if count[o] == 0:
                queue.append(o)
    return sources, worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--anderson", default="default", help="memory, or 'default'")
    ap.add_argument(
        "--smoke", action="store_true", help=f"a quick check: {SCENARIOS[0]} (both solvers) only"
    )
    _meta.add_out_argument(ap, STEM)
    args = ap.parse_args()
    run = _meta.Run(_meta.output_path(args, STEM))
    rows = []
    env = dict(os.environ, TF_CPP_VMODULE="thunk_executor=6", TF_CPP_MIN_LOG_LEVEL="0")
    print(f"{'scenario':<24}{'solver':<8}{'thunks':>7}{'sources':>9}{'max waiting':>13}  verdict")
    for scenario in SCENARIOS[:1] if args.smoke else SCENARIOS:
        for kind in ("le", "ia"):
            out = subprocess.run(
                [sys.executable, "-c", CHILD, scenario, kind, args.anderson],
                env=env,
                capture_output=True,
                text=True,
                timeout=600,
            )
            if out.returncode != 0:
                print(out.stderr[-2000:], file=sys.stderr)
                raise SystemExit(f"{scenario} {kind}: child failed")
            # the step's program is compiled after MARKER-BEGIN
            text = out.stderr.split("MARKER-BEGIN", 1)[-1]
            nodes, n = top_level_graph(text)
            sources, worst = max_waiting(nodes)
            verdict = "inline" if worst <= 8 else "splits onto the pool"
            if len(nodes) < n:
                verdict += f" (XLA's log cut the graph after {len(nodes)} thunks)"
            name = "LE" if kind == "le" else "IA"
            print(f"{scenario:<24}{name:<8}{n:>7}{sources:>9}{worst:>13}  {verdict}", flush=True)
            rows.append(
                {
                    "scenario": scenario,
                    "solver": name,
                    "thunks": n,
                    "thunks_read": len(nodes),
                    "sources": sources,
                    "max_waiting": worst,
                    "splits": worst > 8,
                }
            )
    run.results = {"anderson": args.anderson, "split_threshold": 8, "rows": rows}
    run.finish()


if __name__ == "__main__":
    main()
