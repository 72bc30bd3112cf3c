"""Figures of the closed-loop runs, after the paper's (section "Experimental Studies").

* :func:`vehicle_response` -- fig_CC_vehicle / fig_VSC_*_vehicle: speed, yaw rate
  and wheel slip/speeds against their references, and the path, for one or
  more runs (e.g. one objective against both);
* :func:`wheel_torques` -- fig_CC_torque / fig_VSC_*_torque: the agents' inputs
  and the resulting wheel torques;
* :func:`convergence` -- fig_CC_time / fig_VSC_*_time: (a) torque suboptimality
  e_sub (eq.suboptimality), (b) iterations, (c) time ratio r_time (eq.t_ratio),
  as box plots over the "whole" run and the "focus" window, plus time series;
* :func:`yaw_error_comparison` -- yaw-rate error of several runs over time.

All functions take :class:`~ampc_jax.closed_loop.SimResult` objects and return a
matplotlib Figure; :func:`save` writes PNGs with the Agg backend (headless).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["convergence", "save", "vehicle_response", "wheel_torques", "yaw_error_comparison"]


def _shade(ax: Any, res: Any) -> None:
    ax.axvspan(*res.focus, color="0.92", zorder=0, label="_focus")


def _formulation_label(config: Any) -> str:
    """The formulation's name as the paper writes it (legends show no class names)."""
    return config.formulation_info.label if config.mpc else config.formulation


def _label(res: Any) -> str:
    from ..formulations import DEFAULT_FORMULATION

    c = res.config
    if not c.mpc:
        return c.vehicle_example.no_mpc_label
    other = c.formulation != DEFAULT_FORMULATION
    return "+".join(c.enabled) + (f" ({_formulation_label(c)})" if other else "")


# the rear-slip panel's range for stability runs: the controlled runs stay
# within about +-0.15 (S_x,des; docs/results.md) and a wheel spinning up or
# locking still shows; a run beyond it (the driver alone reaches about 30 on
# the launch/brake) is drawn clipped and named in the panel
SLIP_SCALE = 1.0


def _off_scale(
    ax: Any,
    lo: float,
    hi: float,
    labels: Sequence[str],
    peaks: Sequence[float],
    unit: str,
    fmt: str,
) -> None:
    """Limit ``ax`` to [lo, hi] and name, inside the panel, each run whose peak
    magnitude lies outside it ("off scale: driver alone up to 29.8")."""
    ax.set_ylim(lo, hi)
    off = [
        f"{lab} up to {fmt.format(pk)}"
        for lab, pk in zip(labels, peaks, strict=True)
        if np.isfinite(pk) and pk > max(abs(lo), abs(hi))
    ]
    if off:
        ax.text(
            0.02,
            0.95,
            "off scale: " + ", ".join(off) + unit,
            transform=ax.transAxes,
            fontsize=7,
            va="top",
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.0},
        )


def vehicle_response(results: Sequence[Any], labels: Sequence[str] | None = None) -> Any:
    """Vehicle response against references for one or several runs of one scenario.

    Panels: (a) speed v_x and v_ref (cruise control; the stability examples'
    drivers apply an open-loop torque and track no speed), (b) yaw rate and the
    yaw-rate reference of eq.CC_objective, (c) rear-wheel slip (with the desired
    slip of eq.VSC_objective for stability runs), (d) rear wheel speeds against
    omega_ref (stability) or the steering angle (cruise), (e) lateral error,
    (f) path Y(X). Every run is drawn against its own references (dashed, in
    its colour): each is scored against them. The grey band is the focus window.
    """
    labels = list(labels) if labels else [_label(r) for r in results]
    fig, axs = plt.subplots(3, 2, figsize=(11, 9), constrained_layout=True)
    ax = axs.ravel()
    r0 = results[0]
    for a in ax[:5]:
        _shade(a, r0)
    # a wheel-speed panel where the example logs a wheel-speed reference
    # (stability control); the steering angle otherwise
    stab = bool(np.any(np.isfinite(r0.log.omega_ref)))
    target = r0.config.vehicle_example.slip_target(r0.config.settings)
    if target is not None:
        ax[2].axhline(target, color="k", ls="--", lw=0.8, label="+-S_x,des")
        ax[2].axhline(-target, color="k", ls="--", lw=0.8)
    for res, lab in zip(results, labels, strict=True):
        lg = res.log
        (line,) = ax[0].plot(lg.t, lg.v_x, lw=1.3, label=lab)
        col = line.get_color()
        # each run against its own references (they follow its own speed and
        # steering), dashed in its colour
        if np.any(np.isfinite(lg.v_ref)):  # the stability drivers track no speed
            ax[0].plot(lg.t, lg.v_ref, color=col, ls="--", lw=0.9, label=f"{lab} v_ref")
        ax[1].plot(lg.t, lg.yaw_rate, color=col, lw=1.3, label=lab)
        ax[1].plot(lg.t, lg.yaw_ref, color=col, ls="--", lw=0.9, label=f"{lab} reference")
        ax[2].plot(lg.t, lg.slip[:, 2], color=col, lw=1.2, label=f"{lab} RL")
        ax[2].plot(lg.t, lg.slip[:, 3], color=col, lw=1.0, ls=":", label=f"{lab} RR")
        if stab:
            ax[3].plot(lg.t, lg.omega_ref, color=col, ls="--", lw=0.9, label=f"{lab} omega_ref")
            ax[3].plot(lg.t, lg.omega[:, 2], color=col, lw=1.2, label=f"{lab} RL")
            ax[3].plot(lg.t, lg.omega[:, 3], color=col, lw=1.0, ls=":", label=f"{lab} RR")
        else:
            ax[3].plot(lg.t, np.degrees(lg.steer), color=col, lw=1.2, label=lab)
        ax[4].plot(lg.t, lg.Y - lg.path_y, color=col, lw=1.2, label=lab)
        ax[5].plot(lg.X, lg.Y, color=col, lw=1.3, label=lab)
    ax[5].plot(r0.log.X, r0.log.path_y, "k--", lw=1, label="path")
    ax[0].set_ylabel("v_x (m/s)")
    ax[1].set_ylabel("yaw rate (rad/s)")
    ax[2].set_ylabel("rear slip ratio (-)")
    ax[3].set_ylabel("rear wheel speed (rad/s)" if stab else "road-wheel angle (deg)")
    if stab:
        # a spinning or locked baseline (driver alone: rear slip up to about 30,
        # wheel speeds of hundreds of rad/s) would flatten the controlled run and
        # its references: keep their scale and say, in the panel, what is off it
        slips = [float(np.nanmax(np.abs(r.log.slip[:, 2:]))) for r in results]
        _off_scale(ax[2], -SLIP_SCALE, SLIP_SCALE, labels, slips, "", "{:.3g}")
        top = 1.3 * float(np.nanmax([np.nanmax(r0.log.omega[:, 2:]), np.nanmax(r0.log.omega_ref)]))
        peaks = [float(np.nanmax(r.log.omega[:, 2:])) for r in results]
        if np.isfinite(top) and top > 0 and max(peaks) > top:
            _off_scale(ax[3], 0.0, top, labels, peaks, " rad/s", "{:.0f}")
    ax[4].set_ylabel("lateral error Y - y_path (m)")
    ax[5].set_xlabel("X (m)")
    ax[5].set_ylabel("Y (m)")
    for a in ax[:5]:
        a.set_xlabel("t (s)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7, loc="best")
    fig.suptitle(f"{r0.scenario}: vehicle response (grey: focus window)")
    return fig


def wheel_torques(res: Any) -> Any:
    """Agents' first-step inputs (applied) and the four wheel torques of one run."""
    lg, c = res.log, res.config
    fig, axs = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True, constrained_layout=True)
    for a in axs:
        _shade(a, res)
    for k, name in enumerate(c.input_names):
        if np.any(lg.u[:, k] != 0):
            axs[0].plot(lg.t, lg.u[:, k], lw=1.2, label=name)
    if np.any(np.asarray(lg.driver_torque) != 0):
        axs[0].plot(lg.t, lg.driver_torque, "k--", lw=0.9, label="driver T_DTR")
    axs[0].set_ylabel("agent input (Nm)")
    for k, w in enumerate(("FL", "FR", "RL", "RR")):
        axs[1].plot(lg.t, lg.torques[:, k], lw=1.2, label=w)
    axs[1].set_ylabel("wheel torque (Nm)")
    axs[1].set_xlabel("t (s)")
    for a in axs:
        a.grid(alpha=0.3)
        a.legend(fontsize=8, ncol=5)
    name = _formulation_label(c)
    fig.suptitle(f"{res.scenario}: torque commands ({_label(res)}, {name})")
    return fig


def _box(ax: Any, whole: np.ndarray, focus: np.ndarray, ylabel: str, log: bool = False) -> None:
    w = np.asarray(whole, float)
    f = np.asarray(focus, float)
    w, f = w[np.isfinite(w)], f[np.isfinite(f)]
    if log:
        floor = 1e-6
        w, f = np.maximum(w, floor), np.maximum(f, floor)
    ax.boxplot([w, f], whis=(5, 95), showfliers=True, flierprops={"markersize": 2})
    ax.set_xticks([1, 2], ["Whole", "Focus"])
    if log:
        ax.set_yscale("log")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, axis="y")


def convergence(res: Any) -> Any:
    """(a) e_sub, (b) iterations, (c) r_time: "Whole" vs "Focus" boxes and time series.

    Boxes span the quartiles, whiskers the 5th..95th percentiles.
    """
    lg = res.log
    fm = res.focus_mask
    es = np.nanmax(np.where(np.isfinite(lg.e_sub), lg.e_sub, -np.inf), axis=1)
    es = np.where(np.isfinite(es), es, np.nan)
    ncol = 3 if res.timing is not None else 2
    fig, axs = plt.subplots(2, ncol, figsize=(4 * ncol, 6.5), constrained_layout=True)
    has_es = bool(np.any(np.isfinite(es)))  # none without the shadow MPC
    if has_es:
        _box(axs[0, 0], es, es[fm], "(a) e_sub, max over inputs (Nm)", log=True)
    _box(axs[0, 1], lg.iterations, lg.iterations[fm], "(b) iterations")
    for a in axs[1]:
        _shade(a, res)
        a.set_xlabel("t (s)")
        a.grid(alpha=0.3)
    if has_es:
        axs[1, 0].semilogy(lg.t, np.maximum(es, 1e-6), lw=1)
    else:
        for a in (axs[0, 0], axs[1, 0]):
            a.text(
                0.5,
                0.5,
                "no e_sub: run without\nthe shadow integrated MPC",
                ha="center",
                va="center",
                transform=a.transAxes,
            )
    axs[1, 0].set_ylabel("e_sub (Nm)")
    axs[1, 1].plot(lg.t, lg.iterations, lw=1, label=_formulation_label(res.config))
    axs[1, 1].set_ylabel("iterations")
    if res.timing is not None:
        r = res.timing["r_time"]
        _box(axs[0, 2], r, r[fm], "(c) r_time (eq.t_ratio)")
        axs[0, 2].axhline(1.0, color="r", lw=0.8)
        axs[1, 2].plot(lg.t, r, lw=1)
        axs[1, 2].axhline(1.0, color="r", lw=0.8)
        axs[1, 2].set_ylabel("r_time")
        load = res.timing.get("load") or {}
        seen = [x for x in (load.get("start"), load.get("end")) if x is not None]
        busy = res.timing_busy() if hasattr(res, "timing_busy") else None
        where = f"timed at load {max(seen):.1f} on {load.get('cores')} core(s)" if seen else "timed"
        axs[0, 2].set_title(
            where + (": load-sensitive, spikes are waits" if busy else ""),
            fontsize=8,
            color="tab:red" if busy else "0.3",
        )
        axs[1, 1].plot(
            lg.t,
            res.timing["integrated_iterations"],
            lw=1,
            alpha=0.7,
            label="integrated MPC (same ADMM)",
        )
        axs[1, 1].legend(fontsize=8)
    fig.suptitle(f"{res.scenario}: convergence and computational efficiency")
    return fig


def yaw_error_comparison(results: Sequence[Any], labels: Sequence[str] | None = None) -> Any:
    """Yaw-rate error (yaw rate - reference) of several runs, RMS (focus window) in the legend."""
    labels = list(labels) if labels else [_label(r) for r in results]
    fig, ax = plt.subplots(figsize=(9, 3.8), constrained_layout=True)
    _shade(ax, results[0])
    for res, lab in zip(results, labels, strict=True):
        e = res.log.yaw_rate - res.log.yaw_ref
        fm = res.focus_mask
        rms = f"{float(np.sqrt(np.mean(e[fm] ** 2))):.4f}" if fm.any() else "n/a"
        ax.plot(res.log.t, e, lw=1.2, label=f"{lab} (rms focus {rms} rad/s)")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("yaw-rate error (rad/s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{results[0].scenario}: yaw-rate error")
    return fig


def save(fig: Any, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` as PNG and close it; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
