"""Outputs of closed-loop runs: the per-step CSV, ``metrics.json``, figures and text summaries.

:func:`write_timeseries` writes ``timeseries.csv`` (one row per control step),
:func:`write_metrics` ``metrics.json`` (:meth:`SimResult.metrics`, NaN as
null), :func:`write_figures` the figures of :mod:`ampc_jax.io.figures`;
:func:`summary_lines` and :func:`comparison_line` are the text the command line prints.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from ..closed_loop.config import NO_MPC
from ..formulations.registry import formulation_info
from ..vehicle.params import WHEELS

__all__ = [
    "FIGURES",
    "comparison_line",
    "summary_lines",
    "write_figures",
    "write_metrics",
    "write_run",
    "write_timeseries",
]


def write_timeseries(res: Any, path: str | Path) -> Path:
    """One CSV row per control step: time, states, references, inputs, e_sub, solver stats."""
    lg, c = res.log, res.config
    cols: dict[str, Any] = {
        "t": lg.t,
        "X": lg.X,
        "Y": lg.Y,
        "path_y": lg.path_y,
        "psi": lg.psi,
        "v_x": lg.v_x,
        "v_ref": lg.v_ref,
        "v_y": lg.v_y,
        "yaw_rate": lg.yaw_rate,
        "yaw_ref": lg.yaw_ref,
        "steer": lg.steer,
        "driver_torque": lg.driver_torque,
        "omega_ref": lg.omega_ref,
    }
    for k, w in enumerate(WHEELS):
        cols[f"omega_{w}"] = lg.omega[:, k]
        cols[f"slip_{w}"] = lg.slip[:, k]
    for k, n in enumerate(c.input_names):
        cols[f"u_{n}"] = lg.u[:, k]
    for k, n in enumerate(c.input_names):
        cols[f"u_shadow_{n}"] = lg.u_shadow[:, k]
    for k, n in enumerate(c.input_names):
        cols[f"e_sub_{n}"] = lg.e_sub[:, k]
    for k, w in enumerate(WHEELS):
        cols[f"torque_{w}"] = lg.torques[:, k]
    cols.update(
        iterations=lg.iterations,
        status=lg.status,
        shadow_iterations=lg.shadow_iterations,
        shadow_status=lg.shadow_status,
        fallback=np.asarray(lg.fallback, int),
    )
    if res.timing is not None:
        cols["t_distributed_s"] = res.timing["t_distributed"]
        cols["t_integrated_s"] = res.timing["t_integrated"]
        cols["r_time"] = res.timing["r_time"]
        cols["integrated_iterations"] = res.timing["integrated_iterations"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(cols)
    arrays = [np.asarray(cols[n]) for n in names]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(names)
        for k in range(len(lg.t)):
            w.writerow([_fmt(a[k]) for a in arrays])
    return path


def _fmt(x: Any) -> str:
    x = x.item() if hasattr(x, "item") else x
    if isinstance(x, float):
        return "" if not np.isfinite(x) else f"{x:.9g}"
    return str(x)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def write_metrics(metrics: dict[str, Any], path: str | Path) -> Path:
    """``metrics.json`` (NaN written as null)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_jsonable(metrics), indent=2) + "\n")
    return path


FIGURES = ("vehicle_response", "wheel_torques", "convergence", "yaw_error")
"""The figures of a run, in the order written."""


def write_figures(
    results: list[Any], out: str | Path, stem: str = "", only: tuple[str, ...] = FIGURES
) -> list[Path]:
    """Write the figures of ``results`` (the first is the main run) into ``out``:
    those of :data:`FIGURES` named in ``only`` that the runs have (``convergence``
    needs an MPC, ``yaw_error`` a second run)."""
    from . import figures

    out = Path(out)
    main = results[0]
    draw = {
        "vehicle_response": lambda: figures.vehicle_response(results),
        "wheel_torques": lambda: figures.wheel_torques(main),
        # without the shadow (--no-shadow) its e_sub panels say so
        "convergence": (lambda: figures.convergence(main)) if main.config.mpc else None,
        "yaw_error": (lambda: figures.yaw_error_comparison(results)) if len(results) > 1 else None,
    }
    unknown = [n for n in only if n not in FIGURES]
    if unknown:
        raise ValueError(f"only: expected some of {list(FIGURES)}, got {unknown}")
    return [
        figures.save(draw[name](), out / f"{stem}{name}.png")
        for name in FIGURES
        if name in only and draw[name] is not None
    ]


def summary_lines(m: dict[str, Any]) -> list[str]:
    """The run's headline numbers as text lines (what ``ampc simulate`` prints)."""
    lines: list[str] = []

    def f(key: str, fmt: str = ".3g") -> str:
        v = m.get(key)
        return (
            "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)
        )

    if m["formulation"] == NO_MPC:
        lines.append(f"{m['scenario']} [none: {m.get('no_mpc', 'no MPC')}]")
    else:
        dtype = f"; {m['dtype']}" if m.get("dtype") else ""
        lines.append(
            f"{m['scenario']} [{m['formulation']}; {'+'.join(m['objectives'])}; "
            f"N_p={m['horizon']}; {'warm' if m['warm_start'] else 'cold'} start{dtype}]"
        )
        changed = m.get("settings_changed") or {}
        if changed:
            lines.append(
                "  settings        "
                + ", ".join(
                    f"{k} {v['value']:g} (default {v['default']:g})" for k, v in changed.items()
                )
            )
        if formulation_info(m["formulation"]).rho == "one":  # the integrated problem's rho
            scales = f"rho_scale {m['integrated_rho_scale']:g} (integrated)"
        else:
            rs = m.get("rho_scale_enabled", m["rho_scale"])
            rs = ", ".join(f"{x:g}" for x in rs) if isinstance(rs, list) else f"{rs:g}"
            scales = (
                f"rho_scale {rs} ({'+'.join(m['objectives'])}), "
                f"integrated_rho_scale {m['integrated_rho_scale']:g}"
            )
        lines.append(
            f"  solver          eps_r {m['tol_primal']:g}, eps_s {m['tol_dual']:g}, "
            f"relaxation {m['relaxation']:g}, {scales}, warm_shift {m.get('warm_shift', 1)}, "
            f"anderson {m.get('anderson', 0)}"
        )
    if "focus_steps" in m:
        f0, f1 = m["focus_s"]
        note = "; the run ends before it: focus numbers n/a" if m["focus_steps"] == 0 else ""
        lines.append(
            f"  focus window    {f0:g}..{f1:g} s, {m['focus_steps']} of {m['steps']} steps{note}"
        )
    if m["formulation"] != NO_MPC:
        lines.append(
            f"  e_sub (Nm)      p50 {f('e_sub_p50')}  p95 {f('e_sub_p95')}  max {f('e_sub_max')}"
            f"   focus p95 {f('e_sub_p95_focus')}"
        )
        lines.append(
            f"  iterations      p50 {f('iterations_p50')}  p95 {f('iterations_p95')}  "
            f"max {f('iterations_max')}"
        )
        if "r_time_median" in m:
            lines.append(
                f"  r_time          median {f('r_time_median')}  p95 {f('r_time_p95')}  "
                f"({m['formulation']} {f('t_distributed_median_us', '.0f')} us vs integrated "
                f"{f('t_integrated_median_us', '.0f')} us)"
            )
    lines.append(
        f"  yaw-rate rms    {f('yaw_rms')} rad/s (focus {f('yaw_rms_focus')}),"
        f"  rear |slip| max {f('rear_slip_abs_max')}, fallbacks {m['fallbacks']}"
    )
    lines.append(
        f"  run time        {f('wall_time_s')} s for {f('duration_s')} s simulated "
        f"({f('realtime_factor', '.1f')}x real time; first run {f('first_run_s')} s, "
        f"compile {f('compile_time_s', '.1f')} s)"
    )
    for w in m.get("warnings", ()):
        lines.append(f"  warning: {w}")
    return lines


def comparison_line(m: dict[str, Any], base: dict[str, Any]) -> str:
    """One line: what the run's objectives change against the baseline run ``base``."""

    def arrow(key: str, unit: str) -> str:
        a, b = base.get(key), m.get(key)
        if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)):
            return f"{key} n/a"
        ratio = f" ({a / b:.2f}x lower)" if b > 0 and a >= b else ""
        return f"{a:.4g} -> {b:.4g}{unit}{ratio}"

    who = "+".join(m["objectives"]) if m["formulation"] != NO_MPC else "no MPC"
    was = "+".join(base["objectives"]) if base["formulation"] != NO_MPC else "the driver alone"
    text = f"{who} against {was}: yaw-rate rms (focus) {arrow('yaw_rms_focus', ' rad/s')}"
    if m.get("slip_target") is not None:
        text += (
            f"; rear |slip| max {arrow('rear_slip_abs_max', '')}"
            f"; rear slip excess rms {arrow('rear_slip_excess_rms', '')}"
        )
    return text


def write_run(res: Any, out: str | Path) -> tuple[Path, Path]:
    """``timeseries.csv`` and ``metrics.json`` of one run into the folder ``out``."""
    out = Path(out)
    return write_timeseries(res, out / "timeseries.csv"), write_metrics(
        res.metrics(), out / "metrics.json"
    )
