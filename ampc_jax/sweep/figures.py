"""Figures of a rho sweep (matplotlib, Agg backend), drawn from its Parquet table.

* ``iterations_vs_rho.png``: iterations to tolerance against the rho scale
  (log axis), the median with 25-75 % and 5-95 % bands over the cases,
  eq.opt_ro's rho* (scale 1) marked; non-converged pairs count at the cap.
* ``best_rho.png``: the distribution of each case's best rho scale (fewest
  iterations among its converged points; ties to the one nearest rho*)
  against rho*, with the share of cases whose best point is the grid point
  nearest rho*.

Both rho axes are logarithmic with plain-number labels: at the grid's own
points when the grid has at most ``TICKED_POINTS`` of them (a closed-loop
sweep's few points), else at the decades; minor ticks carry no label (their
default ``2 x 10^-1`` labels overlap on axes spanning one or two decades).
A loop sweep's ``iterations`` column is the mean per control step, and its
axis says so.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["TICKED_POINTS", "best_rho", "iteration_quantiles", "log_rho_axis", "sweep_figures"]

TICKED_POINTS = 9  # grids up to this size get a labelled tick at every point


def log_rho_axis(ax: Any, r: np.ndarray) -> None:
    """Log rho axis, labelled with plain numbers: every grid point of a small
    grid, the decades of a large one; no labels on minor ticks."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    plain = FuncFormatter(lambda v, _: f"{v:.3g}")
    if 0 < r.size <= TICKED_POINTS:
        ax.xaxis.set_major_locator(FixedLocator(r))
    else:
        ax.xaxis.set_major_locator(LogLocator(base=10.0))
    ax.xaxis.set_major_formatter(plain)
    ax.xaxis.set_minor_formatter(NullFormatter())


def iteration_quantiles(table: Any, q: tuple[float, ...] = (5, 25, 50, 75, 95)) -> dict:
    """rho scales (P,) and iteration quantiles {q: (P,)} over the cases of a sweep table."""
    rho = np.asarray(table.column("rho_scale").to_numpy())
    it = np.asarray(table.column("iterations").to_numpy(), float)
    scales = np.unique(rho)
    out = {"rho_scale": scales}
    for qq in q:
        out[qq] = np.array([np.percentile(it[rho == s], qq) for s in scales])
    return out


def best_rho(table: Any) -> tuple[np.ndarray, np.ndarray]:
    """(case, best rho scale) per case: fewest iterations among converged points
    (ties to the scale nearest 1, eq.opt_ro's rho*); NaN for a case with none converged."""
    case = table.column("case").to_numpy()
    rho = table.column("rho_scale").to_numpy()
    it = table.column("iterations").to_numpy().astype(float)
    conv = table.column("converged").to_numpy()
    it = np.where(conv, it, np.inf)
    order = np.lexsort((np.abs(np.log(rho)), it, case))  # by case, then iterations, then |log rho|
    c_sorted = case[order]
    first = np.r_[True, c_sorted[1:] != c_sorted[:-1]]
    pick = order[first]
    best = np.where(np.isfinite(it[pick]), rho[pick], np.nan)
    return case[pick], best


def sweep_figures(table: Any, out: str | Path) -> list[Path]:
    """Draw both figures into ``out``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    meta_fam = table.column("family")[0].as_py() if table.num_rows else ""
    qs = iteration_quantiles(table)
    r = qs["rho_scale"]
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.fill_between(r, qs[5], qs[95], alpha=0.2, color="C0", label="5-95 %")
    ax.fill_between(r, qs[25], qs[75], alpha=0.35, color="C0", label="25-75 %")
    ax.plot(r, qs[50], "o-", color="C0", label="median")
    ax.axvline(1.0, color="C3", ls="--", lw=1.2, label="eq.opt_ro rho* (scale 1)")
    log_rho_axis(ax, r)
    ax.set_xlabel("rho scale (factor on eq.opt_ro's rho_j*)")
    loops = "iterations_max" in table.column_names  # a loop sweep's rows: LoopRow
    ax.set_ylabel("iterations per control step, mean" if loops else "iterations to tolerance")
    n_cases = len(np.unique(table.column("case").to_numpy()))
    ax.set_title(f"{meta_fam}: {n_cases} cases")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    p1 = out / "iterations_vs_rho.png"
    fig.tight_layout()
    fig.savefig(p1, dpi=120)
    plt.close(fig)

    _, best = best_rho(table)
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ok = best[np.isfinite(best)]
    if ok.size:
        edges = np.sqrt(r[1:] * r[:-1]) if r.size > 1 else np.array([])
        bins = np.r_[r[0] / 1.5, edges, r[-1] * 1.5] if r.size > 1 else 3
        ax.hist(ok, bins=bins, color="C2", edgecolor="k")
    ax.axvline(1.0, color="C3", ls="--", lw=1.2, label="eq.opt_ro rho*")
    log_rho_axis(ax, r)
    star = float(r[np.argmin(np.abs(np.log(r)))])  # the grid point nearest rho*
    at_star = float(np.mean(np.isclose(ok, star))) if ok.size else float("nan")
    ax.set_xlabel("each case's best rho scale")
    ax.set_ylabel("cases")
    ax.set_title(
        f"best rho per case: {100 * at_star:.0f} % at the point nearest rho* "
        f"({star:.3g}); {best.size - ok.size} with none converged",
        fontsize=10,
    )
    ax.legend(fontsize=8)
    p2 = out / "best_rho.png"
    fig.tight_layout()
    fig.savefig(p2, dpi=120)
    plt.close(fig)
    return [p1, p2]
