"""A finished closed-loop run (:class:`SimResult`): its headline numbers and warnings.

e_sub is eq.suboptimality (Nm per agent input, against the shadow integrated
MPC), r_time eq.t_ratio (from :func:`~ampc_jax.closed_loop.timing.replay_timing`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..results import Status
from .config import SimConfig
from .log import SimLog

__all__ = ["V_X_BACKWARDS", "SimResult"]

V_X_BACKWARDS = -0.1
"""m/s: a run whose v_x falls below this went backwards (:meth:`SimResult.warnings`);
the margin keeps a car braked to a stop, which may creep by a few mm/s, out."""


def _finite(x: np.ndarray, reduce: Any) -> float:
    """``reduce`` over the finite entries of ``x``; NaN when there are none."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(reduce(x)) if x.size else float("nan")


def _pct(x: np.ndarray, q: float) -> float:
    return _finite(x, lambda v: np.percentile(v, q))


def _max(x: np.ndarray) -> float:
    return _finite(x, np.max)


def _min(x: np.ndarray) -> float:
    return _finite(x, np.min)


def _plain(x: Any) -> Any:
    """A settings value as JSON has it (bool, int or float)."""
    return x if isinstance(x, (bool, int, np.bool_)) else float(x)


def settings_changed(config: Any) -> dict[str, dict[str, Any]]:
    """The example's settings ``config`` changes (``--set``, a tuned-parameters
    file): field -> ``{"value": ..., "default": ...}`` (empty: the defaults)."""
    st = config.settings
    default = config.vehicle_example.settings_type()
    out = {}
    for name in st.field_names():
        v, d = _plain(getattr(st, name)), _plain(getattr(default, name))
        if v != d:
            out[name] = {"value": v, "default": d}
    return out


def _rms(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")


@dataclass
class SimResult:
    """A finished run: the log (numpy), its configuration and timings, and :meth:`metrics`.

    Attributes
    ----------
    log : SimLog of numpy arrays.
    config : the SimConfig.
    scenario : scenario name.  focus : (t0, t1) window where both objectives act.
    duration : simulated time (s).  wall_time : run time of the compiled scan
    (s): the median of three executions after the first, whose one-time costs
    it leaves out (runs over 0.5 s: the first execution alone).
    compile_time : trace + compile time (s).  first_run_time : the first
    execution (s), one-time costs included.
    timing : per-step replay timings (:func:`replay_timing`), or None.
    """

    log: SimLog
    config: SimConfig
    scenario: str
    focus: tuple[float, float]
    duration: float
    wall_time: float
    compile_time: float
    timing: dict[str, np.ndarray] | None = None
    first_run_time: float | None = None

    @property
    def focus_mask(self) -> np.ndarray:
        t = np.asarray(self.log.t)
        return (t >= self.focus[0]) & (t <= self.focus[1])

    def metrics(self) -> dict[str, Any]:
        """Headline numbers: e_sub (eq.suboptimality), iterations, r_time (eq.t_ratio), tracking.

        ``e_sub`` statistics pool every enabled agent input of every step (Nm);
        ``focus`` restricts to the scenario's focus window (``focus_steps``
        control steps; the ``*_focus`` numbers are NaN when the run ends before
        the window starts). ``rho_scale_enabled`` is the part of ``rho_scale``
        that Local Explicit uses (the enabled objectives'). ``yaw_rms`` is the
        RMS of ``yaw_rate - yaw_ref``; rear slip statistics use wheels RL, RR
        and ``rear_slip_excess_rms`` is the RMS of ``max(|slip| - S_x,des, 0)``.
        """
        lg, c = self.log, self.config
        fm = self.focus_mask
        es = np.asarray(lg.e_sub, float)
        it = np.asarray(lg.iterations, float)
        yaw_err = np.asarray(lg.yaw_rate) - np.asarray(lg.yaw_ref)
        rear = np.abs(np.asarray(lg.slip)[:, 2:])
        target = c.vehicle_example.slip_target(c.settings)
        slip_des = 0.15 if target is None else target  # the paper's S_x,des otherwise
        excess = np.maximum(rear - slip_des, 0.0)
        active = c.mpc
        m: dict[str, Any] = {
            "scenario": self.scenario,
            "example": c.example,
            "formulation": c.formulation,
            "no_mpc": c.vehicle_example.no_mpc_label,
            "slip_target": target,
            "objectives": list(c.enabled),
            "warm_start": c.warm_start,
            "learned_start": None if c.learned_start is None else repr(c.learned_start),
            "horizon": c.horizon,
            "max_iter": c.max_iter,
            "fixed_iterations": c.fixed_iterations,
            "tol_primal": c.tol_primal,
            "tol_dual": c.tol_dual,
            **c.solver_options(),
            "rho_scale_enabled": (
                list(c.enabled_rho_scale)
                if isinstance(c.enabled_rho_scale, tuple)
                else c.enabled_rho_scale
            ),
            "dtype": np.asarray(lg.v_x).dtype.name,
            "settings_changed": self.settings_changed(),
            "steps": int(len(lg.t)),
            "duration_s": self.duration,
            "focus_s": list(self.focus),
            "focus_steps": int(np.sum(fm)),
            "yaw_rms": _rms(yaw_err),
            "yaw_rms_focus": _rms(yaw_err[fm]),
            # NaN (null) where the driver tracks no speed (stability examples)
            "speed_rms": _rms(np.asarray(lg.v_x) - np.asarray(lg.v_ref)),
            "v_x_min": _min(np.asarray(lg.v_x)),
            "lateral_error_max": _max(np.abs(np.asarray(lg.Y) - np.asarray(lg.path_y))),
            "rear_slip_abs_max": _max(rear),
            "rear_slip_abs_p95": _pct(rear, 95),
            "rear_slip_excess_rms": _rms(excess),
            "rear_slip_excess_rms_focus": _rms(excess[fm]),
            "fallbacks": int(np.sum(np.asarray(lg.fallback))),
            "wall_time_s": self.wall_time,
            "first_run_s": self.first_run_time,
            "compile_time_s": self.compile_time,
            "realtime_factor": self.duration / self.wall_time if self.wall_time > 0 else None,
        }
        if active:
            for name, mask in (("", slice(None)), ("_focus", fm)):
                e = es[mask]
                m[f"e_sub_p50{name}"] = _pct(e, 50)
                m[f"e_sub_p95{name}"] = _pct(e, 95)
                m[f"e_sub_max{name}"] = _max(e)
                i = it[mask]
                m[f"iterations_p50{name}"] = _pct(i, 50)
                m[f"iterations_p95{name}"] = _pct(i, 95)
                m[f"iterations_max{name}"] = _max(i)
            m["e_sub_max_per_input"] = {
                n: _max(es[:, k])
                for k, n in enumerate(c.input_names)
                if np.isfinite(es[:, k]).any()
            }
            st = np.asarray(lg.status)
            m["status_counts"] = {int(s): int(np.sum(st == s)) for s in np.unique(st)}
            sst = np.asarray(lg.shadow_status)
            m["shadow_not_solved"] = int(np.sum(sst != 0)) if c.shadow else None
            m["shadow_iterations_max"] = _max(np.asarray(lg.shadow_iterations, float))
        if self.timing is not None:
            r = self.timing["r_time"]
            m["r_time_median"] = _pct(r, 50)
            m["r_time_p95"] = _pct(r, 95)
            m["r_time_median_focus"] = _pct(r[fm], 50)
            m["t_distributed_median_us"] = _pct(self.timing["t_distributed"], 50) * 1e6
            m["t_integrated_median_us"] = _pct(self.timing["t_integrated"], 50) * 1e6
            m["integrated_iterations_p50"] = _pct(self.timing["integrated_iterations"], 50)
            load = self.timing.get("load")
            if load is not None:
                m["r_time_load"] = dict(load)
            m["timing_note"] = self.timing_note()
        m["warnings"] = self.warnings()
        return m

    def warnings(self) -> list[str]:
        """What makes parts of this run unreliable, one sentence each (empty: none).

        * the vehicle went backwards: the plant's slip and slip angles and the
          drivers are written for forward driving, so the rest of the run is not
          physical (e.g. ``cruise_lane_change --mu 0.3``, which spins the car);
        * control steps that stopped at ``max_iter`` without meeting eps_r/eps_s,
          or fell back (failed or non-finite solve, previous command held);
        * steps where the shadow integrated MPC did not converge: e_sub there
          compares with an unconverged reference;
        * r_time timed on a busy machine (:meth:`timing_busy`).
        """
        lg, c = self.log, self.config
        out = []
        vx = np.asarray(lg.v_x, float)
        back = vx < V_X_BACKWARDS
        if np.any(back):
            k = int(np.argmax(back))
            out.append(
                f"the vehicle went backwards (v_x {np.nanmin(vx):.3g} m/s; first at "
                f"t = {float(lg.t[k]):g} s): the plant and the drivers model forward "
                "driving only, so the run is not physical from there on"
            )
        if c.mpc:
            st = np.asarray(lg.status)
            n = len(st)
            capped = int(np.sum(st == 1))
            if capped:
                out.append(
                    f"{capped} of {n} control steps stopped at max_iter = {c.max_iter} "
                    "without meeting eps_r / eps_s"
                )
            fb = int(np.sum(np.asarray(lg.fallback)))
            if fb:
                out.append(
                    f"{fb} of {n} control steps fell back to the previous command "
                    "(a failed or non-finite solve)"
                )
            if c.shadow:
                bad = int(np.sum(np.asarray(lg.shadow_status) != Status.SOLVED))
                if bad:
                    out.append(
                        f"the shadow integrated MPC did not converge on {bad} of {n} steps: "
                        "e_sub there compares with an unconverged reference"
                    )
        busy = self.timing_busy()
        if busy:
            out.append(busy)
        return out

    def settings_changed(self) -> dict[str, dict[str, Any]]:
        """:func:`settings_changed` of this run's config."""
        return settings_changed(self.config)

    def timing_busy(self) -> str | None:
        """A sentence when the r_time replay ran on a busy machine (a 1-minute load
        average above this process's cores, at its start or end), else None: the
        times then include waits for other processes, in spikes."""
        load = (self.timing or {}).get("load")
        if not load:
            return None
        seen = [x for x in (load.get("start"), load.get("end")) if x is not None]
        cores = load.get("cores") or 1
        if not seen or max(seen) <= cores:
            return None
        return (
            f"r_time was timed at load {max(seen):.1f} on {cores} core(s): each step's time "
            "includes waits for other processes (spikes in the r_time panel); time it on an "
            "idle machine for the paper's comparison"
        )

    def timing_note(self) -> str:
        return (
            "per step, fastest of repeats of one compiled call (after an untimed one): "
            "full control step "
            "(make_data output -> local costs H_j/E_j, rho (eq.opt_ro), Cholesky, "
            "ADMM while_loop to tolerance, result) for Local Explicit and for IntegratedADMM "
            f"(same tolerances eps_r={self.config.tol_primal:g}, eps_s={self.config.tol_dual:g}, "
            f"same relaxation {self.config.relaxation:g}, rho* scaled by "
            f"{self.config.enabled_rho_scale} and {self.config.integrated_rho_scale:g} "
            "respectively, same warm/cold start policy)"
        )
