"""ampc_jax.sweep.figures on small synthetic sweep tables (Agg backend): plain,
non-overlapping rho tick labels and the loop sweep's iteration axis."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow as pa  # noqa: E402
import pytest  # noqa: E402

from ampc_jax.sweep import rho_grid  # noqa: E402
from ampc_jax.sweep.figures import TICKED_POINTS, log_rho_axis, sweep_figures  # noqa: E402

pytestmark = pytest.mark.timeout(120)


def _table(grid: str, cases: int, loops: bool) -> pa.Table:
    r = np.asarray(rho_grid(grid), float)
    rng = np.random.default_rng(0)
    case, rho = np.repeat(np.arange(cases), r.size), np.tile(r, cases)
    it = 8 + 3 * np.abs(np.log(rho) - rng.normal(0, 0.5, case.size))
    cols = {
        "family": ["cruise_lane_change" if loops else "cruise_step"] * case.size,
        "case": case,
        "rho_scale": rho,
        "iterations": it if loops else np.round(4 * it),
        "converged": np.ones(case.size, bool),
    }
    if loops:  # a loop sweep's rows carry the run's reductions (sweep.loops.LoopRow)
        cols["iterations_max"] = it + 3
    return pa.table(cols)


def _labels(fig, which="major"):
    """The rho axis' visible tick labels after drawing."""
    fig.canvas.draw()
    ax = fig.axes[0]
    lo, hi = ax.get_xlim()
    ticks = ax.xaxis.get_major_ticks() if which == "major" else ax.xaxis.get_minor_ticks()
    return [t.label1.get_text() for t in ticks if lo <= t.get_loc() <= hi and t.label1.get_text()]


@pytest.mark.parametrize("grid", ["0.3:3:5", "0.03:30:30"])
def test_rho_axis_labels_are_plain_numbers_and_minor_ticks_unlabelled(grid):
    """A small grid (a loop sweep's few points) gets one label per point, a large one
    the decades; no minor tick carries a label (the default ``2 x 10^-1`` labels of
    a log axis spanning one or two decades overlapped their neighbours)."""
    r = np.asarray(rho_grid(grid), float)
    fig, ax = plt.subplots()
    try:
        ax.plot(r, np.ones_like(r))
        log_rho_axis(ax, r)
        major = _labels(fig)
        if r.size <= TICKED_POINTS:
            assert major == [f"{v:.3g}" for v in r]
        else:
            assert major == ["0.1", "1", "10"]
        assert _labels(fig, "minor") == []
        assert not any("10^" in t or "times" in t for t in major)
        # drawn labels do not overlap
        fig.canvas.draw()
        boxes = [t.label1.get_window_extent() for t in ax.xaxis.get_major_ticks()
                 if t.label1.get_text() and ax.get_xlim()[0] <= t.get_loc() <= ax.get_xlim()[1]]  # fmt: skip
        for a, b in zip(boxes, boxes[1:], strict=False):
            assert a.x1 < b.x0
    finally:
        plt.close(fig)


@pytest.mark.parametrize("loops", [True, False])
def test_sweep_figures_axis_names_what_the_iterations_are(tmp_path, monkeypatch, loops):
    """A loop sweep's ``iterations`` is the mean per control step, a step sweep's the
    iterations to tolerance of one solve: each figure's axis says which."""
    kept = []
    monkeypatch.setattr(plt, "close", kept.append)  # keep the figures to inspect them
    paths = sweep_figures(_table("0.3:3:5" if loops else "0.03:30:30", 12, loops), tmp_path)
    try:
        assert [p.name for p in paths] == ["iterations_vs_rho.png", "best_rho.png"]
        assert all(p.read_bytes()[:4] == b"\x89PNG" for p in paths)
        ylabel = kept[0].axes[0].get_ylabel()
        expect = "iterations per control step, mean" if loops else "iterations to tolerance"
        assert ylabel == expect
        for fig in kept:
            assert _labels(fig, "minor") == []
    finally:
        monkeypatch.undo()
        for fig in kept:
            plt.close(fig)
