"""One compiled program over many (case, parameter point) pairs, with compaction.

A sweep solves the same formulation for B pairs (a case's
:class:`~ampc_jax.problem.ProblemData` and a
:class:`~ampc_jax.admm.SolverParams` point) in one program: the setups
(H_j, E_j, rho_j, the factorisation of K_j) are vmapped over the pairs, and the
ADMM iterations run in *segments* of ``segment`` iterations.

* **Freezing.** Inside a segment a pair that has met eq.Convergence (or its
  cap, or a non-finite residual) keeps its state (a ``where`` on the whole
  carry), so every pair reports the iteration count it gets alone
  (``tests/sweep/test_engine.py``).
* **Compaction.** ``jax.vmap`` of a ``while_loop`` computes every pair until
  the slowest is done: the waste is B * max_q(iterations) against
  sum_q(iterations). Between segments the pairs still running are moved to
  the front (a stable ``argsort`` of the running flags) and the next segment
  runs on the first ``size`` of them only, ``size`` the smallest of a static
  ladder of bucket sizes (B, B/2, B/4, ..., ``min_bucket``) that holds them:
  one ``lax.switch`` branch per bucket, so the program is compiled once and a
  sweep's wall time tracks the typical pair, not the worst. :class:`Work`
  counts the pair-iterations computed and needed, for both runners.

Under :func:`sweep_solve` with several devices, the pair axis is split over
them with ``jax.shard_map`` (each device compacts its own share); with
several processes after ``jax.distributed.initialize()`` the same program runs
on global arrays (:func:`global_pairs`) and each process reads back the
shards it holds. Nothing crosses devices, so there are no collectives.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from ..admm.core import ADMMSolver
from ..admm.params import SolverParams
from ..admm.runners import loop_parts, run_segment, still_running
from ..problem.data import ProblemData
from ..validation import check_count

__all__ = [
    "PairResult",
    "Work",
    "bucket_sizes",
    "global_pairs",
    "pair_params",
    "solve_pairs",
    "sweep_solve",
]


class PairResult(NamedTuple):
    """What a sweep keeps of one (case, point) solve (leading axis: pairs).

    u0 : (n_u,) first-step inputs (consensus, projected on the bounds).
    iterations, converged, status : as :class:`~ampc_jax.results.SolveResult`.
    primal, dual : () the largest objective's squared residuals.
    rho : (n_rho,) the rho_j used.
    violation : () the largest violation of a constraint row over the horizon,
        max(0, max_k,c (A_in U^(k) - b_in^(k))_c) in the rows' units.
    """

    u0: Any
    iterations: Any
    converged: Any
    status: Any
    primal: Any
    dual: Any
    rho: Any
    violation: Any


class Work(NamedTuple):
    """Pair-iterations a run computed, and the ones its pairs needed (sum of iterations)."""

    computed: Any
    needed: Any

    @property
    def waste(self) -> float:
        """computed / needed (1 is no waste; NaN when nothing was needed)."""
        needed = float(self.needed)
        return float(self.computed) / needed if needed > 0 else float("nan")


CHUNK: int | None = 128
"""Pairs per chunk of the iterations in :func:`solve_pairs` (None: all of them at
once). Rule: 128; reason: the iterations read every pair's factors at every
step, and a chunk's fit in cache where a device's whole share does not: on
1,000 ``cruise_step`` cases x 4 rho points (2 devices, Anderson 3, the sweep
benchmark's setting) chunks of 32, 64 and 128 ran 1.6x to 1.8x faster than one
compaction over all 2,000 pairs of a device, 256 1.3x, 512 1.1x; the same
iteration counts, compaction's waste 1.35 against 1.24. The setups have no
loop and run over all pairs at once."""


def _check_solver(solver: Any) -> ADMMSolver:
    """``solver`` when it implements the core protocol, else a TypeError naming ``formulation``."""
    if not isinstance(solver, ADMMSolver):
        raise TypeError(
            f"formulation: expected an ADMM formulation (ampc_jax.admm.core.ADMMSolver), "
            f"got {type(solver).__name__}"
        )
    return solver


def bucket_sizes(batch: int, min_bucket: int = 8) -> tuple[int, ...]:
    """The compaction ladder, largest first: ``batch``, then halvings down to ``min_bucket``."""
    sizes = [int(batch)]
    while sizes[-1] // 2 >= max(int(min_bucket), 1):
        sizes.append(sizes[-1] // 2)
    return tuple(sizes)


def _take(tree: Any, idx: Any) -> Any:
    return jax.tree.map(lambda x: x[idx], tree)


def _where(go: Any, new: Any, old: Any) -> Any:
    return jax.tree.map(lambda a, b: jnp.where(go, a, b), new, old)


def violation(data: ProblemData, u: Any) -> Any:
    """max(0, max_k,c (A_in U^(k) - b_in^(k))_c): the worst constraint row of ``u`` (N_p, n_u)."""
    if data.Ain.shape[0] == 0:
        return jnp.zeros((), u.dtype)
    return jnp.maximum(jnp.max(u @ data.Ain.T - data.bin), 0.0)


def solve_pairs(
    solver: ADMMSolver,
    data: ProblemData,
    params: SolverParams,
    *,
    compaction: bool = True,
    segment: int = 16,
    min_bucket: int = 16,
    chunk: int | None = CHUNK,
    refill: bool = False,
) -> tuple[PairResult, Work]:
    """Solve B pairs (leading axis of ``data`` and ``params``) on one device, to tolerance.

    ``compaction`` False runs ``jax.vmap`` of the formulation's ``while_loop``
    (every pair iterates until the slowest is done; frozen by JAX's batching
    rule); True runs segments of ``segment`` iterations on the pairs still
    running (see the module docstring). Results are the same pair by pair.
    The setups (no loop) run over all B pairs at once; the iterations run on
    consecutive chunks of ``chunk`` pairs (:data:`CHUNK`; None: all B at once),
    one after the other under ``lax.map``, each compacted on its own.
    ``refill`` True runs ``chunk`` slots (continuous batching): after each segment
    a pair that has stopped hands its slot to the next waiting pair, so a slot
    never idles while pairs wait (:func:`_iterate_refill`).
    Returns the per-pair :class:`PairResult` and the :class:`Work` done. Jittable.
    """
    solver = _check_solver(solver)
    setups = jax.vmap(solver.setup)(data, params)
    states = jax.vmap(solver.init)(setups)
    if chunk is not None and (isinstance(chunk, bool) or int(chunk) < 1):
        raise ValueError(f"chunk: expected an integer >= 1 or None, got {chunk!r}")
    if refill:
        slots = CHUNK if chunk is None else int(chunk)
        finals, work = _iterate_refill(solver, setups, states, segment, slots)
    else:
        finals, work = _iterate(solver, setups, states, compaction, segment, min_bucket, chunk)
    res = jax.vmap(solver.result)(setups, finals)
    viol = jax.vmap(violation)(data, res.u)
    out = PairResult(
        u0=res.u[:, 0, :],
        iterations=res.iterations,
        converged=res.converged,
        status=res.status,
        primal=jnp.max(res.primal_residual, axis=-1),
        dual=jnp.max(res.dual_residual, axis=-1),
        rho=res.rho,
        violation=viol,
    )
    return out, work


def _iterate(
    solver: ADMMSolver,
    setups: Any,
    states: Any,
    compaction: bool,
    segment: int,
    min_bucket: int,
    chunk: int | None,
) -> tuple[Any, Work]:
    """The final iterates of B pairs from their setups and start states, in chunks
    of ``chunk`` pairs (the last padded with copies of the first pair, whose
    results are dropped and whose work is not counted)."""
    B = int(np.shape(jax.tree.leaves(states)[0])[0])
    if chunk is None or int(chunk) >= B:
        return _iterate_all(solver, setups, states, compaction, segment, min_bucket)
    C = int(chunk)
    n = -(-B // C)
    pad = n * C - B
    padded = (setups, states)
    if pad:
        padded = _take(padded, jnp.concatenate([jnp.arange(B), jnp.zeros(pad, int)]))
    blocks = jax.tree.map(lambda x: x.reshape((n, C) + x.shape[1:]), padded)
    real = (jnp.arange(n * C) < B).reshape(n, C)

    def one(args: tuple) -> tuple:
        (s, st), keep = args
        fin, work = _iterate_all(solver, s, st, compaction, segment, min_bucket)
        # the padded copies' own iterations are not needed work
        return fin, Work(work.computed, jnp.sum(jnp.where(keep, fin.iteration, 0)))

    fin, work = jax.lax.map(one, (blocks, real))
    finals = jax.tree.map(lambda x: x.reshape((n * C,) + x.shape[2:])[:B], fin)
    return finals, Work(jnp.sum(work.computed), jnp.sum(work.needed))


def _parts_of(solver: ADMMSolver) -> tuple[Any, Any, Any]:
    """(initial carry, segment of ``segment`` iterations, running) of ``solver`` on one pair."""

    def iterate_of(carry: Any) -> Any:
        return carry[0] if solver.anderson else carry

    def carry_of(setup: Any, st: Any) -> Any:
        return loop_parts(
            lambda s: solver.step(setup, s), st, solver.anderson, solver.point, solver.at
        )[0]

    def running(setup: Any, carry: Any) -> Any:
        return still_running(
            iterate_of(carry), lambda s: solver.converged(setup, s), solver.max_iter
        )

    def segment_of(setup: Any, carry: Any, length: int) -> Any:
        _, body, _ = loop_parts(
            lambda s: solver.step(setup, s),
            iterate_of(carry),
            solver.anderson,
            solver.point,
            solver.at,
        )
        return run_segment(
            body,
            iterate_of,
            lambda c: running(setup, c),
            carry,
            length,
            finish=solver.finisher(setup),
            anderson=solver.anderson,
        )

    return carry_of, segment_of, running


def _iterate_refill(
    solver: ADMMSolver, setups: Any, states: Any, segment: int, slots: int
) -> tuple[Any, Work]:
    """The final iterates of B pairs by continuous batching: ``slots`` pairs iterate
    together in segments of ``segment`` iterations; after each segment the pairs
    that stopped are written out and their slots take the next waiting pairs in
    order. Each pair's iterations are its own (a stopped pair is frozen inside a
    segment), so results match the unbatched solve; the work computed is slots x
    segment per segment, idle only once no pair waits."""
    B = int(np.shape(jax.tree.leaves(states)[0])[0])
    C = max(1, min(int(slots), B))
    seg = check_segment(segment)
    carry_of, segment_of, running = _parts_of(solver)
    iterate_of = (lambda c: c[0]) if solver.anderson else (lambda c: c)
    carries = jax.vmap(carry_of)(setups, states)  # every pair's start, read when loaded
    finals = jax.vmap(iterate_of)(carries)
    idx0 = jnp.arange(C)
    live0 = jnp.ones((C,), bool)

    def cond(loop: tuple) -> Any:
        return jnp.any(loop[2])

    def body(loop: tuple) -> tuple:
        carry, idx, live, nxt, finals, computed = loop
        carry = jax.vmap(lambda s, c: segment_of(s, c, seg))(_take(setups, idx), carry)
        done = live & ~jax.vmap(running)(_take(setups, idx), carry)
        out = jnp.where(done, idx, B)  # B: out of range, dropped
        finals = jax.tree.map(
            lambda f, x: f.at[out].set(x, mode="drop"), finals, jax.vmap(iterate_of)(carry)
        )
        new = nxt + jnp.cumsum(done) - 1  # the next waiting pairs, in order
        load = done & (new < B)
        idx = jnp.where(load, new, idx)
        live = jnp.where(done, load, live)
        carry = _where_rows(load, _take(carries, jnp.minimum(idx, B - 1)), carry)
        nxt = jnp.minimum(nxt + jnp.sum(done), B)
        return carry, idx, live, nxt, finals, computed + jnp.asarray(C * seg, jnp.int32)

    loop0 = (_take(carries, idx0), idx0, live0, jnp.asarray(C), finals, jnp.zeros((), jnp.int32))
    _, _, _, _, finals, computed = jax.lax.while_loop(cond, body, loop0)
    return finals, Work(computed, jnp.sum(finals.iteration))


def _where_rows(go: Any, new: Any, old: Any) -> Any:
    """Per leading-axis row: ``new`` where ``go``, else ``old``."""
    return jax.tree.map(
        lambda a, b: jnp.where(go.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), new, old
    )


def check_segment(segment: Any) -> int:
    if isinstance(segment, bool) or int(segment) < 1:
        raise ValueError(f"segment: expected an integer >= 1, got {segment!r}")
    return int(segment)


def _iterate_all(
    solver: ADMMSolver,
    setups: Any,
    states: Any,
    compaction: bool,
    segment: int,
    min_bucket: int,
) -> tuple[Any, Work]:
    """The final iterates of all B pairs at once (the module docstring's compaction)."""
    B = int(np.shape(jax.tree.leaves(states)[0])[0])

    def parts(setup: Any, st: Any) -> tuple[Any, Any, Any]:
        return loop_parts(
            lambda s: solver.step(setup, s), st, solver.anderson, solver.point, solver.at
        )

    def iterate_of(carry: Any) -> Any:
        return carry[0] if solver.anderson else carry

    def running(setup: Any, carry: Any) -> Any:
        return still_running(
            iterate_of(carry), lambda s: solver.converged(setup, s), solver.max_iter
        )

    if not compaction:
        finals = jax.vmap(solver.run)(setups, states)
        it = finals.iteration
        work = Work(B * jnp.max(it), jnp.sum(it))
    else:
        seg = check_count(segment, "segment")

        def segment_of(setup: Any, carry: Any) -> Any:
            _, body, _ = parts(setup, iterate_of(carry))
            return run_segment(
                body,
                iterate_of,
                lambda c: running(setup, c),
                carry,
                seg,
                finish=solver.finisher(setup),
                anderson=solver.anderson,
            )

        carry0 = jax.vmap(lambda s, st: parts(s, st)[0])(setups, states)
        sizes = bucket_sizes(B, min_bucket)
        ladder = jnp.asarray(sizes)

        def branch(size: int) -> Any:
            def run(args: tuple) -> tuple:
                carry, idx = args
                sel = idx[:size]
                new = jax.vmap(segment_of)(_take(setups, sel), _take(carry, sel))
                carry = jax.tree.map(lambda x, y: x.at[sel].set(y), carry, new)
                return carry, jnp.asarray(size * seg, jnp.int32)

            return run

        branches = [branch(s) for s in sizes]

        def loop_cond(loop: tuple) -> Any:
            return jnp.any(jax.vmap(running)(setups, loop[0]))

        def loop_body(loop: tuple) -> tuple:
            carry, computed = loop
            go = jax.vmap(running)(setups, carry)
            n = jnp.sum(go)
            idx = jnp.argsort(~go, stable=True)  # the running pairs first
            k = jnp.sum(ladder >= n) - 1  # the smallest bucket that holds them
            carry, c = jax.lax.switch(k, branches, (carry, idx))
            return carry, computed + c

        carry, computed = jax.lax.while_loop(
            loop_cond, loop_body, (carry0, jnp.zeros((), jnp.int32))
        )
        finals = jax.vmap(iterate_of)(carry)
        work = Work(computed, jnp.sum(finals.iteration))
    return finals, work


def pair_params(grid: SolverParams, n_cases: int) -> SolverParams:
    """``grid`` (leading axis P) tiled for ``n_cases`` cases: pair q = case q // P, point q % P."""
    return jax.tree.map(
        lambda x: jnp.tile(jnp.asarray(x), (int(n_cases),) + (1,) * (jnp.ndim(x) - 1)), grid
    )


def pair_data(data: ProblemData, n_points: int) -> ProblemData:
    """Each case's data repeated for the ``n_points`` points of a grid (pairs case-major)."""
    return jax.tree.map(lambda x: jnp.repeat(jnp.asarray(x), n_points, axis=0), data)


def _mesh(devices: Sequence[Any]) -> jax.sharding.Mesh:
    return jax.sharding.Mesh(np.asarray(list(devices)), ("pairs",))


def global_pairs(tree: Any, mesh: jax.sharding.Mesh) -> Any:
    """A pytree of host arrays (every process holds all of it) as global
    ``jax.Array``s split along their leading axis over ``mesh``; each process
    places only the shards of its own devices (``jax.make_array_from_callback``)."""
    sharding = NamedSharding(mesh, PartitionSpec("pairs"))

    def put(x: Any) -> Any:
        a = np.asarray(x)
        return jax.make_array_from_callback(a.shape, sharding, lambda idx: a[idx])

    return jax.tree.map(put, tree)


def sweep_solve(
    solver: ADMMSolver,
    data: ProblemData,
    params: SolverParams,
    *,
    devices: Sequence[Any] | None = None,
    compaction: bool = True,
    segment: int = 16,
    min_bucket: int = 16,
    chunk: int | None = CHUNK,
    refill: bool = False,
) -> tuple[PairResult, Work]:
    """:func:`solve_pairs` with the pair axis split over ``devices`` (default: all of
    ``jax.devices()``, every process's), by ``jax.shard_map``.

    ``data`` and ``params`` hold B pairs on their leading axis, B a multiple
    of the device count (pad with copies; the sweep runner does). Returns
    global arrays: each process reads the shards of its own devices
    (``addressable_shards``); with one process, ``np.asarray`` reads them all.
    :class:`Work` is summed over devices.
    """
    devs = list(jax.devices() if devices is None else devices)
    B = int(np.shape(jax.tree.leaves(data)[0])[0])
    if B % len(devs):
        raise ValueError(f"pairs: {B} pairs do not split over {len(devs)} devices; pad them")
    chunk = None if chunk is None else int(chunk)
    fn, mesh = _program(
        solver, tuple(devs), bool(compaction), int(segment), int(min_bucket), chunk, bool(refill)
    )
    if jax.process_count() > 1:
        data, params = global_pairs(data, mesh), global_pairs(params, mesh)
    return fn(data, params)


@functools.lru_cache(maxsize=32)
def _program(
    solver: Any,
    devices: tuple,
    compaction: bool,
    segment: int,
    min_bucket: int,
    chunk: int | None = CHUNK,
    refill: bool = False,
) -> tuple[Any, jax.sharding.Mesh]:
    """The jitted, sharded sweep program for one static configuration (compiled
    once per pair count and dtype, then reused by every chunk)."""
    mesh = _mesh(devices)
    spec = PartitionSpec("pairs")
    kw = {
        "compaction": compaction,
        "segment": segment,
        "min_bucket": min_bucket,
        "chunk": chunk,
        "refill": refill,
    }

    def local(d: Any, p: Any) -> tuple:
        out, work = solve_pairs(solver, d, p, **kw)
        return out, jax.tree.map(lambda x: jnp.reshape(x, (1,)), work)

    sharded = jax.shard_map(
        local, mesh=mesh, in_specs=(spec, spec), out_specs=spec, check_vma=False
    )
    return jax.jit(sharded), mesh
