"""``ampc replay``: a logged run re-run offline, bit for bit, and with other settings.

First the logs are checked (:mod:`~.runcheck`: run.json's fields and digests,
the ticks against its counts and against the bridge's candump log); a log
that does not add up is refused, naming what. A run that did not finish (killed)
is replayed from its journal, as far as it reaches.

The determinism check: the run's configuration (``run.json``: scenario,
formulation, dtype, configuration hash) is rebuilt, its step compiled as the
run compiled it, and called in the run's order on the logged bus vectors (a
tick that did not step leaves the warm state as it was, as in the run); every
command must come out identical bit for bit (the float64 values compared with
``np.array_equal``).

The what-if: the same bus vectors through the controller with other rho
scales (one ``vmap`` over the scales of one ``lax.scan`` over the ticks, the
parameters a traced argument), other formulations and float32 (a scan each),
reported as the commands' difference from the logged ones. The states stay the
logged ones (open loop: how the commands would have differed on that drive,
not where the vehicle would have gone).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..closed_loop import config_for
from ..closed_loop.controller import controller_for
from .files import named
from .runcheck import check_run
from .runner import environment
from .signals import BUS_FIELDS, bus_measurement
from .step import RuntimeStep
from .ticklog import RunLogError

__all__ = ["load_run", "replay_run", "scaled_rho"]

WHEELS = ("FL", "FR", "RL", "RR")


def load_run(log_dir: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``run.json`` and the tick log's columns of a run directory, once they passed
    every check of :func:`~.runcheck.check_run` (RunLogError, a ValueError, if not).
    A run that did not finish gives the ticks of its journal."""
    run = check_run(Path(log_dir))
    return run.meta, run.cols


def _config(meta: dict[str, Any], **overrides: Any) -> Any:
    kw = {"shadow": False, "formulation": meta["formulation"], **overrides}
    return config_for(meta["scenario"], **kw)


def scaled_rho(base: Any, factor: float) -> Any:
    """The run's rho scales ``base`` (a float or one per objective) times ``factor``: a
    replay's ``--rho-scale 1`` is the run's own setting (the cruise example's (1, 0.5)),
    not 1 for every objective."""
    if isinstance(base, tuple):
        return tuple(float(b) * float(factor) for b in base)
    return float(base) * float(factor)


def _scan(cfg: Any, dtype: Any, buses: np.ndarray, params: Any = None) -> Any:
    """Torques and iterations of the controller over ``buses`` (K, 13): one scan."""
    ctrl = controller_for(cfg)
    p0 = cfg.loop_params(dtype).controller

    def run(params: Any, buses: Any) -> Any:
        def body(state: Any, bus: Any) -> Any:
            meas, drv = bus_measurement(bus, cfg.vehicle)
            torques, state, info = ctrl.step(state, params, meas, drv)
            return state, (torques, info.iterations)

        _, out = jax.lax.scan(body, ctrl.init(dtype), buses)
        return out

    return run, (p0 if params is None else params), jnp.asarray(buses, dtype)


def replay_run(
    log_dir: Path,
    out: Path,
    *,
    rho_scales: tuple[float, ...] | None = None,
    formulations: tuple[str, ...] = (),
    float32: bool = False,
    progress: Callable[[str], Any] | None = None,
) -> dict[str, Any]:
    """Replay the run in ``log_dir``; write ``replay.json`` and ``replay.parquet`` to ``out``.

    ``rho_scales``: factors on the run's own rho scales (:func:`scaled_rho`; 1 replays
    the run's setting), each one more variant of one vmapped batch.

    The logs are checked first (:func:`~.runcheck.check_run`: RunLogError, naming
    what does not add up). ``progress(text)`` gets a line when the step is
    compiled and about once a second while the ticks replay, with an ETA
    measured from the replay alone (compilation excluded).
    """
    run = check_run(Path(log_dir))
    meta, cols = run.meta, run.cols
    stepped = cols["stepped"].astype(bool)
    if not stepped.any():
        if not len(cols["tick"]) and not run.complete:
            how = "is still running and" if run.alive else "was killed before its first tick:"
            raise RunLogError(
                f"{log_dir}: the run {how} its {run.source} holds no tick; nothing to replay"
            )
        why = cols["reason"][0] if len(cols["reason"]) else "no ticks"
        raise RunLogError(
            f"{log_dir}: no tick of the run stepped the controller (the first said: {why!r:.80}); "
            "nothing to replay"
        )
    cfg = _config(meta)
    step = RuntimeStep(cfg, meta["dtype"])
    if step.config_hash() != meta["config_hash"]:
        raise RunLogError(
            f"{log_dir}: the run's controller configuration ({meta['config_hash'][:12]}...) is "
            f"not what this version builds for {meta['scenario']!r} ({step.config_hash()[:12]}...)"
        )
    env_run = meta.get("environment")
    env_now = environment()
    mismatch = (
        None
        if env_run is None or env_run == env_now
        else {k: (env_run.get(k), v) for k, v in env_now.items() if env_run.get(k) != v}
    )
    say = progress or (lambda _: None)
    buses = np.stack([cols[f"bus_{n}"] for n in BUS_FIELDS], axis=1)[stepped]
    logged = np.stack([cols[f"cmd_{w}"] for w in WHEELS], axis=1)[stepped]
    t0 = time.perf_counter()
    fn = step.compiled()
    leaves = step.init_leaves()
    say(f"compiled the step in {time.perf_counter() - t0:.1f} s; replaying {len(buses)} ticks")
    got = np.empty_like(logged)
    iters = np.empty(len(buses), np.int64)
    t_start = last = time.perf_counter()
    for i, bus in enumerate(buses):
        torques, leaves, rep = fn(leaves, jnp.asarray(bus, step.jnp_dtype))
        got[i] = np.asarray(torques, np.float64)
        iters[i] = int(rep[0])
        if time.perf_counter() - last >= 1.0:
            last = time.perf_counter()
            eta = (last - t_start) / (i + 1) * (len(buses) - i - 1)
            say(f"replayed {i + 1}/{len(buses)} ticks, ETA {eta:.0f} s")
    same = np.array(
        [np.array_equal(a, b, equal_nan=True) for a, b in zip(got, logged, strict=True)]
    )
    diff = np.abs(got - logged)
    result: dict[str, Any] = {
        "run": str(log_dir),
        "scenario": meta["scenario"],
        "log": {
            "source": run.source,
            "complete": run.complete,
            "state": meta["state"],
            "alive": run.alive,
            "pid": meta.get("pid"),
            "settings": run.settings,
            "ticks": int(len(cols["tick"])),
            "frames_checked": run.frames_checked,
            "frames_unchecked": run.frames_unchecked,
            "notes": list(run.notes),
        },
        "determinism": {
            "ticks": int(len(buses)),
            "identical": int(same.sum()),
            "differ": int((~same).sum()),
            "max_abs_diff_nm": float(np.nanmax(diff)) if np.isfinite(diff).any() else 0.0,
        },
        "variants": [],
        # bit for bit needs the run's jax, jaxlib and XLA flags: a difference is
        # reported (run's, replay's) and explains a determinism failure
        "environment_mismatch": mismatch,
    }
    rows: dict[str, list[Any]] = {"variant": [], "tick": [], "iterations": []}
    rows.update({f"T_{w}": [] for w in WHEELS})
    tick_idx = np.asarray(cols["tick"])[stepped]

    def add(name: str, torques: np.ndarray, it: np.ndarray) -> None:
        d = torques - logged
        result["variants"].append(
            {
                "variant": name,
                "max_abs_diff_nm": float(np.max(np.abs(d))) if d.size else 0.0,
                "rms_diff_nm": float(np.sqrt(np.mean(d**2))) if d.size else 0.0,
                "iterations_mean": float(np.mean(it)) if it.size else 0.0,
            }
        )
        rows["variant"] += [name] * len(torques)
        rows["tick"] += tick_idx.tolist()
        rows["iterations"] += np.asarray(it).tolist()
        for j, w in enumerate(WHEELS):
            rows[f"T_{w}"] += torques[:, j].tolist()

    add("logged", logged, np.asarray(cols["iterations"])[stepped])
    dtype = step.jnp_dtype

    def timed(name: str, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` compiled ahead of time, the two times said apart."""
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(*args).compile()
        t1 = time.perf_counter()
        res = jax.block_until_ready(compiled(*args))
        say(f"{name}: compiled in {t1 - t0:.1f} s, replayed in {time.perf_counter() - t1:.1f} s")
        return res

    if rho_scales:
        scan_fn, _, b = _scan(cfg, dtype, buses)
        stacked = jax.tree.map(
            lambda *x: jnp.stack(x),
            *[
                _config(meta, rho_scale=scaled_rho(cfg.rho_scale, s)).loop_params(dtype).controller
                for s in rho_scales
            ],
        )
        T, it = timed("rho scales", jax.vmap(scan_fn, in_axes=(0, None)), stacked, b)
        for s, Ts, its in zip(rho_scales, np.asarray(T), np.asarray(it), strict=True):
            add(f"rho_scale={s:g}", Ts.astype(np.float64), its)
    for form in formulations:
        scan_fn, p, b = _scan(_config(meta, formulation=form), dtype, buses)
        T, it = timed(f"formulation {form}", scan_fn, p, b)
        add(f"formulation={form}", np.asarray(T, np.float64), np.asarray(it))
    if float32:
        scan_fn, p, b = _scan(cfg, jnp.float32, buses)
        T, it = timed("float32", scan_fn, p, b)
        add("float32", np.asarray(T, np.float64), np.asarray(it))
    import pyarrow as pa
    import pyarrow.parquet as pq

    with named(out, "create the directory"):
        out.mkdir(parents=True, exist_ok=True)
    with named(out / "replay.parquet"):
        pq.write_table(pa.table(rows), out / "replay.parquet")
    with named(out / "replay.json"):
        (out / "replay.json").write_text(json.dumps(result, indent=1))
    return result
