"""``ampc replay``: a logged run re-run offline, bit for bit, and with other settings.

The determinism check: the run's configuration (``run.json``: scenario,
formulation, dtype, configuration hash) is rebuilt, its step compiled as the
run compiled it, and called in the run's order on the bus vectors of
``ticks.parquet`` (a tick that did not step leaves the warm state as it was,
as in the run); every command must come out identical bit for bit (the
float64 values compared with ``np.array_equal``).

The what-if: the same bus vectors through the controller with other rho
scales (one ``vmap`` over the scales of one ``lax.scan`` over the ticks, the
parameters a traced argument), other formulations and float32 (a scan each),
reported as the commands' difference from the logged ones. The states stay the
logged ones (open loop: how the commands would have differed on that drive,
not where the vehicle would have gone).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..closed_loop import config_for
from .runner import environment
from .signals import BUS_FIELDS, bus_measurement
from .step import RuntimeStep

__all__ = ["load_run", "replay_run"]

WHEELS = ("FL", "FR", "RL", "RR")


def load_run(log_dir: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``run.json`` and the columns of ``ticks.parquet`` of a run directory."""
    import pyarrow.parquet as pq

    meta_path, ticks_path = log_dir / "run.json", log_dir / "ticks.parquet"
    for p in (meta_path, ticks_path):
        if not p.is_file():
            raise ValueError(f"{log_dir}: no {p.name} (expected an `ampc run` output directory)")
    meta = json.loads(meta_path.read_text())
    table = pq.read_table(ticks_path).to_pydict()
    cols = {k: np.asarray(v) for k, v in table.items()}
    return meta, cols


def _config(meta: dict[str, Any], **overrides: Any) -> Any:
    kw = {"shadow": False, "formulation": meta["formulation"], **overrides}
    return config_for(meta["scenario"], **kw)


def _scan(cfg: Any, dtype: Any, buses: np.ndarray, params: Any = None) -> Any:
    """Torques and iterations of the controller over ``buses`` (K, 13): one scan."""
    ctrl = cfg.controller()
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
) -> dict[str, Any]:
    """Replay the run in ``log_dir``; write ``replay.json`` and ``replay.parquet`` to ``out``."""
    meta, cols = load_run(log_dir)
    cfg = _config(meta)
    step = RuntimeStep(cfg, meta["dtype"])
    if step.config_hash() != meta["config_hash"]:
        raise ValueError(
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
    stepped = cols["stepped"].astype(bool)
    buses = np.stack([cols[f"bus_{n}"] for n in BUS_FIELDS], axis=1)[stepped]
    logged = np.stack([cols[f"cmd_{w}"] for w in WHEELS], axis=1)[stepped]
    fn = step.compiled()
    leaves = step.init_leaves()
    got = np.empty_like(logged)
    iters = np.empty(len(buses), np.int64)
    for i, bus in enumerate(buses):
        torques, leaves, rep = fn(leaves, jnp.asarray(bus, step.jnp_dtype))
        got[i] = np.asarray(torques, np.float64)
        iters[i] = int(rep[0])
    same = np.array(
        [np.array_equal(a, b, equal_nan=True) for a, b in zip(got, logged, strict=True)]
    )
    diff = np.abs(got - logged)
    result: dict[str, Any] = {
        "run": str(log_dir),
        "scenario": meta["scenario"],
        "determinism": {
            "ticks": int(len(buses)),
            "identical": int(same.sum()),
            "differ": int((~same).sum()),
            "max_abs_diff_nm": float(np.nanmax(diff)) if diff.size else 0.0,
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
    if rho_scales:
        run, _, b = _scan(cfg, dtype, buses)
        stacked = jax.tree.map(
            lambda *x: jnp.stack(x),
            *[_config(meta, rho_scale=s).loop_params(dtype).controller for s in rho_scales],
        )
        T, it = jax.jit(jax.vmap(run, in_axes=(0, None)))(stacked, b)
        for s, Ts, its in zip(rho_scales, np.asarray(T), np.asarray(it), strict=True):
            add(f"rho_scale={s:g}", Ts.astype(np.float64), its)
    for form in formulations:
        c = _config(meta, formulation=form)
        run, p, b = _scan(c, dtype, buses)
        T, it = jax.jit(run)(p, b)
        add(f"formulation={form}", np.asarray(T, np.float64), np.asarray(it))
    if float32:
        run, p, b = _scan(cfg, jnp.float32, buses)
        T, it = jax.jit(run)(p, b)
        add("float32", np.asarray(T, np.float64), np.asarray(it))
    import pyarrow as pa
    import pyarrow.parquet as pq

    out.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(rows), out / "replay.parquet")
    (out / "replay.json").write_text(json.dumps(result, indent=1))
    return result
