"""ampc_jax.io.figures on short closed-loop runs (Agg backend, nothing shown)."""

import dataclasses
import warnings

import numpy as np
import pytest

from ampc_jax.closed_loop import config_for, simulate
from ampc_jax.io import figures
from ampc_jax.io.reports import write_figures

pytestmark = pytest.mark.timeout(180)

SCENARIO = "cruise_lane_change"
DURATION = 3.0  # into the single lane change (X 25..55 m): the runs' yaw references differ


@pytest.fixture(scope="module")
def runs():
    """LST+YRT and LST alone, both without the shadow MPC (so no e_sub)."""
    both = simulate(SCENARIO, config_for(SCENARIO, shadow=False), duration=DURATION)
    lst = simulate(
        SCENARIO, config_for(SCENARIO, shadow=False, disabled=("YRT",)), duration=DURATION
    )
    return both, lst


def _dashed(ax):
    return [ln for ln in ax.get_lines() if ln.get_linestyle() == "--"]


@pytest.mark.parametrize("n_runs", [1, 2])
def test_vehicle_response_draws_each_runs_own_reference(runs, n_runs):
    results = list(runs[:n_runs])
    # the runs steer and drive differently, so their eq.CC_objective references differ
    assert np.max(np.abs(runs[0].log.yaw_ref - runs[1].log.yaw_ref)) > 1e-3
    fig = figures.vehicle_response(results)
    try:
        yaw_ax = fig.axes[1]
        assert yaw_ax.get_ylabel() == "yaw rate (rad/s)"
        refs = _dashed(yaw_ax)
        assert len(refs) == len(results)
        for line, res in zip(refs, results, strict=True):
            np.testing.assert_array_equal(line.get_xdata(), res.log.t)
            np.testing.assert_array_equal(line.get_ydata(), res.log.yaw_ref)
        # and in its run's colour
        solid = [ln for ln in yaw_ax.get_lines() if ln.get_linestyle() == "-"]
        assert [ln.get_color() for ln in solid] == [ln.get_color() for ln in refs]
        # the speed panel likewise: one v_ref per run (cruise drivers track a speed)
        speed_refs = _dashed(fig.axes[0])
        assert len(speed_refs) == len(results)
        for line, res in zip(speed_refs, results, strict=True):
            np.testing.assert_array_equal(line.get_ydata(), res.log.v_ref)
    finally:
        figures.plt.close(fig)


def test_convergence_without_e_sub_still_renders(runs, tmp_path):
    """No shadow MPC: no e_sub; the e_sub panels say why they are empty (log
    scaling an empty panel crashed) and the figure is written."""
    res = runs[0]
    assert np.all(np.isnan(res.log.e_sub))
    fig = figures.convergence(res)
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert sum("no e_sub" in t for t in texts) == 2
    path = figures.save(fig, tmp_path / "convergence.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_save_writes_a_png_and_closes_the_figure(runs, tmp_path):
    fig = figures.wheel_torques(runs[0])
    number = fig.number
    path = figures.save(fig, tmp_path / "deeper" / "wheel_torques.png")
    assert path == tmp_path / "deeper" / "wheel_torques.png"
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert number not in figures.plt.get_fignums()


@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:invalid value encountered")
def test_write_figures_of_a_comparison(runs, tmp_path):
    paths = write_figures(list(runs), tmp_path)
    assert [p.name for p in paths] == [
        "vehicle_response.png",
        "wheel_torques.png",
        "convergence.png",
        "yaw_error.png",
    ]
    assert all(p.read_bytes()[:4] == b"\x89PNG" for p in paths)
    one = write_figures([runs[0]], tmp_path / "one", stem="x_")
    assert [p.name for p in one] == ["x_vehicle_response.png", "x_wheel_torques.png",
                                     "x_convergence.png"]  # fmt: skip


def test_yaw_error_comparison_of_runs_before_the_focus_window_is_quiet(runs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fig = figures.yaw_error_comparison(list(runs))
    figures.plt.close(fig)


def _legend_texts(ax):
    legend = ax.get_legend()
    return [t.get_text() for t in legend.get_texts()] if legend is not None else []


def test_convergence_legend_names_the_formulations_in_words(runs):
    """The iterations panel's legend names the controller and its integrated peer
    as the paper does, not by class name (it read "IntegratedADMM")."""
    res = runs[0]
    n = len(res.log.t)
    timed = dataclasses.replace(
        res,
        timing={"r_time": np.linspace(0.8, 1.2, n), "integrated_iterations": np.full(n, 7)},
    )
    fig = figures.convergence(timed)
    try:
        texts = [t for ax in fig.axes for t in _legend_texts(ax)]
        assert texts == ["Local Explicit", "integrated MPC (same ADMM)"]
    finally:
        figures.plt.close(fig)


def _as_stability(res, slip_peak):
    """A run drawn as a stability run (a finite omega_ref) whose rear slip peaks at
    ``slip_peak``; the rest of its log is the cruise run's."""
    lg = res.log
    slip = np.array(lg.slip, float)
    slip[len(slip) // 2, 2] = slip_peak
    return dataclasses.replace(
        res, log=lg._replace(omega_ref=np.asarray(lg.v_x) / 0.351, slip=slip)
    )


def test_rear_slip_beyond_the_panel_is_named_in_it(runs):
    """Stability runs' slip panel keeps the controlled run's scale (+-1); a run
    beyond it (the driver alone reaches about 30) is named with its peak, and a
    panel with nothing clipped carries no note."""
    ctrl, spin = _as_stability(runs[0], 0.12), _as_stability(runs[1], -29.8)
    fig = figures.vehicle_response([ctrl, spin], labels=["VSC+WSC", "driver alone"])
    try:
        ax = fig.axes[2]
        assert ax.get_ylabel() == "rear slip ratio (-)"
        assert ax.get_ylim() == (-figures.SLIP_SCALE, figures.SLIP_SCALE)
        assert [t.get_text() for t in ax.texts] == ["off scale: driver alone up to 29.8"]
    finally:
        figures.plt.close(fig)
    fig = figures.vehicle_response([ctrl], labels=["VSC+WSC"])
    try:
        assert len(fig.axes[2].texts) == 0
    finally:
        figures.plt.close(fig)
