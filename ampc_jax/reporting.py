"""``ampc simulate`` and ``ampc demo``: run closed loops, write CSV/JSON/PNG outputs.

``ampc simulate SCENARIO --out DIR`` writes ``timeseries.csv`` (one row per
control step), ``metrics.json`` (:meth:`SimResult.metrics`) and the figures of
:mod:`ampc_jax.figures`; with ``--compare`` it also runs the paper's baseline
(:func:`~ampc_jax.simulation.baseline_config`: LST alone for cruise control,
the driver alone for stability control) into ``DIR/baseline/`` and overlays
both runs in the figures. ``ampc demo`` runs the cruise-control lane change with
both objectives and with LST alone and prints the key numbers.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .cli import _arg_type, _at_least_one, _positive_finite

__all__ = ["add_cli_commands", "cmd_demo", "cmd_simulate", "write_metrics", "write_timeseries"]


def _fail(msg: str) -> int:
    print(f"ampc: error: {msg}", file=sys.stderr)
    return 2


def _duration(value: float) -> None:
    from .simulation import check_duration

    check_duration(value)


def _mu(value: float) -> None:
    from .simulation import check_mu

    check_mu(value)


def _output_dir(text: str) -> str | None:
    """Create the output directory ``text``; an error message if that fails (else None)."""
    out = Path(text)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"--out {text}: cannot create the output directory ({exc.strerror or exc})"
    if not os.access(out, os.W_OK | os.X_OK):
        return f"--out {text}: the output directory is not writable"
    return None


def _enable_x64(float32: bool = False) -> None:
    import jax

    if not float32:
        jax.config.update("jax_enable_x64", True)


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
    for k, w in enumerate(("FL", "FR", "RL", "RR")):
        cols[f"omega_{w}"] = lg.omega[:, k]
        cols[f"slip_{w}"] = lg.slip[:, k]
    for k, n in enumerate(c.input_names):
        cols[f"u_{n}"] = lg.u[:, k]
    for k, n in enumerate(c.input_names):
        cols[f"u_shadow_{n}"] = lg.u_shadow[:, k]
    for k, n in enumerate(c.input_names):
        cols[f"e_sub_{n}"] = lg.e_sub[:, k]
    for k, w in enumerate(("FL", "FR", "RL", "RR")):
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


def _figures(results: list[Any], out: Path, stem: str = "") -> list[Path]:
    """Write the figures of ``results`` (the first is the main run)."""
    from . import figures

    main = results[0]
    paths = [
        figures.save(figures.vehicle_response(results), out / f"{stem}vehicle_response.png"),
        figures.save(figures.wheel_torques(main), out / f"{stem}wheel_torques.png"),
    ]
    if main.config.formulation != "none":
        # without the shadow (--no-shadow) its e_sub panels say so
        paths.append(figures.save(figures.convergence(main), out / f"{stem}convergence.png"))
    if len(results) > 1:
        paths.append(
            figures.save(figures.yaw_error_comparison(results), out / f"{stem}yaw_error.png")
        )
    return paths


def _progress_disabled(quiet: bool) -> bool | None:
    """tqdm's ``disable``: off with ``--quiet``; otherwise None, which shows the
    bars on a terminal only (redirected output gets no carriage-return debris)."""
    return True if quiet else None


def _bar(total: int, quiet: bool) -> Any:
    from tqdm import tqdm

    return tqdm(
        total=total,
        disable=_progress_disabled(quiet),
        bar_format="{desc:<28}{bar:20}| {n_fmt}/{total_fmt}",
    )


def _replay(cfg: Any, log: Any, repeats: int, quiet: bool) -> dict:
    """:func:`replay_timing` with a bar over the replayed control steps."""
    from tqdm import tqdm

    from .simulation import replay_timing

    n = int(np.shape(log.t)[0])
    with tqdm(
        total=n,
        disable=_progress_disabled(quiet),
        leave=False,
        unit="step",
        bar_format="  {desc}{bar:20}| {n_fmt}/{total_fmt} steps [{elapsed}<{remaining}]",
        desc="replayed ",
    ) as steps:
        return replay_timing(cfg, log, repeats=repeats, progress=steps.update)


def cmd_simulate(args: argparse.Namespace) -> int:
    """``ampc simulate``: one scenario's closed loop, its metrics and figures."""
    _enable_x64(args.float32)
    import jax.numpy as jnp

    from .manoeuvres import SCENARIOS
    from .simulation import baseline_config, config_for, simulate, with_settings

    if args.scenario not in SCENARIOS:
        print(
            f"ampc: error: unknown scenario {args.scenario!r}; expected one of {sorted(SCENARIOS)}",
            file=sys.stderr,
        )
        return 2
    spec = SCENARIOS[args.scenario]
    # argparse checked the values; SimConfig and simulate() check them again for the API
    try:
        cfg = config_for(
            spec,
            formulation=args.formulation,
            disabled=tuple(args.disable or ()),
            warm_start=not args.cold_start,
            shadow=not args.no_shadow,
            tol_primal=args.tol_primal,
            tol_dual=args.tol_dual,
            max_iter=args.max_iter,
            rho_scale=_parse_floats("--rho-scale", args.rho_scale),
            relaxation=args.relaxation,
            integrated_rho_scale=args.integrated_rho_scale,
            warm_shift=args.warm_shift,
            anderson=args.anderson,
        )
        if args.set:
            cfg = with_settings(cfg, **_parse_settings(args.set, cfg.settings))
    except ValueError as exc:
        return _fail(str(exc))
    try:
        base_cfg = baseline_config(cfg) if args.compare else None
    except ValueError as exc:  # "compare: ...", said as the flag
        return _fail(f"--{exc}")
    problem = _output_dir(args.out)
    if problem:
        return _fail(problem)
    out = Path(args.out)
    timing = cfg.formulation == "local_explicit" and not args.no_timing and cfg.shadow
    bar = _bar(5 if base_cfg else 4, args.quiet)
    bar.set_description("compile + run closed loop")
    dtype = jnp.float32 if args.float32 else jnp.float64
    res = simulate(spec, cfg, duration=args.duration, mu=args.mu, dtype=dtype)
    bar.update(1)
    base = None
    if base_cfg is not None:
        bar.set_description("baseline: compile + run")
        base = simulate(spec, base_cfg, duration=args.duration, mu=args.mu, dtype=dtype)
        bar.update(1)
    bar.set_description("replay timing (r_time)")
    if timing:
        import jax

        log = jax.tree.map(jnp.asarray, res.log)
        res.timing = _replay(cfg, log, args.repeats, args.quiet)
    bar.update(1)
    bar.set_description("write csv/json")
    m = res.metrics()
    write_timeseries(res, out / "timeseries.csv")
    write_metrics(m, out / "metrics.json")
    if base is not None:
        mb = base.metrics()
        write_timeseries(base, out / "baseline" / "timeseries.csv")
        write_metrics(mb, out / "baseline" / "metrics.json")
    bar.update(1)
    bar.set_description("figures")
    figs = _figures([res] if base is None else [res, base], out)
    bar.update(1)
    bar.close()
    _summary(m)
    if base is not None:
        _summary(mb)
        print(_comparison(m, mb))
    print(f"wrote {out / 'timeseries.csv'}, {out / 'metrics.json'}")
    if base is not None:
        print(f"baseline in {out / 'baseline'}")
    for p in figs:
        print(f"figure {p}")
    return 0


def _parse_floats(flag: str, text: str | None) -> float | tuple[float, ...] | None:
    """``"0.5"`` -> 0.5, ``"1,0.5"`` -> (1.0, 0.5); None stays None (the example's default)."""
    if text is None:
        return None
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(
            f"{flag} {text}: expected a number or comma-separated numbers (one per objective)"
        ) from None
    return vals[0] if len(vals) == 1 else vals


def _parse_settings(items: list[str], settings: Any) -> dict[str, Any]:
    """``--set horizon=2 --set q_yrt=1e4`` -> fields of the example's settings."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in settings._fields:
            raise ValueError(
                f"--set {item}: expected FIELD=VALUE with FIELD one of {list(settings._fields)}"
            )
        kind = type(getattr(settings, key))
        if kind is bool:
            flag = value.strip().lower()
            if flag not in _TRUE + _FALSE:
                raise ValueError(f"--set {item}: expected true or false, got {value!r}")
            out[key] = flag in _TRUE
        else:
            try:
                out[key] = kind(value)
            except ValueError:
                raise ValueError(
                    f"--set {item}: {value!r} is not a valid {kind.__name__}"
                ) from None
        try:  # the field's range (e.g. q_yrt >= 0, horizon >= 1), named after the item
            settings._replace(**{key: out[key]}).validate()
        except ValueError as exc:
            msg = str(exc).removeprefix(f"{key}: ")
            raise ValueError(f"--set {item}: {msg}") from None
    return out


_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def _summary(m: dict[str, Any]) -> None:
    def f(key: str, fmt: str = ".3g") -> str:
        v = m.get(key)
        return (
            "n/a" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)
        )

    if m["formulation"] == "none":
        who = "driver speed PI" if m.get("example") == "cruise" else "driver alone"
        print(f"{m['scenario']} [none: no MPC, {who}]")
    else:
        print(
            f"{m['scenario']} [{m['formulation']}; {'+'.join(m['objectives'])}; "
            f"N_p={m['horizon']}; {'warm' if m['warm_start'] else 'cold'} start]"
        )
        if m["formulation"] == "integrated":
            scales = f"rho_scale {m['integrated_rho_scale']:g} (integrated)"
        else:
            rs = m.get("rho_scale_enabled", m["rho_scale"])
            rs = ", ".join(f"{x:g}" for x in rs) if isinstance(rs, list) else f"{rs:g}"
            scales = (
                f"rho_scale {rs} ({'+'.join(m['objectives'])}), "
                f"integrated_rho_scale {m['integrated_rho_scale']:g}"
            )
        print(
            f"  solver          eps_r {m['tol_primal']:g}, eps_s {m['tol_dual']:g}, "
            f"relaxation {m['relaxation']:g}, {scales}, warm_shift {m.get('warm_shift', 1)}, "
            f"anderson {m.get('anderson', 0)}"
        )
    if "focus_steps" in m:
        f0, f1 = m["focus_s"]
        note = "; the run ends before it: focus numbers n/a" if m["focus_steps"] == 0 else ""
        print(f"  focus window    {f0:g}..{f1:g} s, {m['focus_steps']} of {m['steps']} steps{note}")
    if m["formulation"] != "none":
        print(
            f"  e_sub (Nm)      p50 {f('e_sub_p50')}  p95 {f('e_sub_p95')}  max {f('e_sub_max')}"
            f"   focus p95 {f('e_sub_p95_focus')}"
        )
        print(
            f"  iterations      p50 {f('iterations_p50')}  p95 {f('iterations_p95')}  "
            f"max {f('iterations_max')}"
        )
        if "r_time_median" in m:
            print(
                f"  r_time          median {f('r_time_median')}  p95 {f('r_time_p95')}  "
                f"(LE {f('t_distributed_median_us', '.0f')} us vs integrated "
                f"{f('t_integrated_median_us', '.0f')} us)"
            )
    print(
        f"  yaw-rate rms    {f('yaw_rms')} rad/s (focus {f('yaw_rms_focus')}),"
        f"  rear |slip| max {f('rear_slip_abs_max')}, fallbacks {m['fallbacks']}"
    )
    print(
        f"  run time        {f('wall_time_s')} s for {f('duration_s')} s simulated "
        f"({f('realtime_factor', '.1f')}x real time; first run {f('first_run_s')} s, "
        f"compile {f('compile_time_s', '.1f')} s)"
    )
    for w in m.get("warnings", ()):
        print(f"  warning: {w}")


def _comparison(m: dict[str, Any], base: dict[str, Any]) -> str:
    """One line: what the run's objectives change against the baseline run ``base``."""

    def arrow(key: str, unit: str) -> str:
        a, b = base.get(key), m.get(key)
        if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)):
            return f"{key} n/a"
        ratio = f" ({a / b:.2f}x lower)" if b > 0 and a >= b else ""
        return f"{a:.4g} -> {b:.4g}{unit}{ratio}"

    who = "+".join(m["objectives"]) if m["formulation"] != "none" else "no MPC"
    was = "+".join(base["objectives"]) if base["formulation"] != "none" else "the driver alone"
    text = f"{who} against {was}: yaw-rate rms (focus) {arrow('yaw_rms_focus', ' rad/s')}"
    if m.get("example") == "stability":
        text += (
            f"; rear |slip| max {arrow('rear_slip_abs_max', '')}"
            f"; rear slip excess rms {arrow('rear_slip_excess_rms', '')}"
        )
    return text


def cmd_demo(args: argparse.Namespace) -> int:
    """``ampc demo``: cruise-control lane change, LST+YRT against LST alone."""
    _enable_x64()
    import jax
    import jax.numpy as jnp

    from .simulation import config_for, simulate

    problem = _output_dir(args.out)
    if problem:
        return _fail(problem)
    out = Path(args.out)
    t_start = time.perf_counter()
    bar = _bar(4, args.quiet)
    bar.set_description("LST+YRT: compile + run")
    both = simulate("cruise_lane_change", config_for("cruise_lane_change"))
    bar.update(1)
    bar.set_description("LST+YRT: replay timing")
    both.timing = _replay(both.config, jax.tree.map(jnp.asarray, both.log), 3, args.quiet)
    bar.update(1)
    bar.set_description("LST only: compile + run")
    lst = simulate("cruise_lane_change", config_for("cruise_lane_change", disabled=("YRT",)))
    bar.update(1)
    bar.set_description("figures")
    mb, ml = both.metrics(), lst.metrics()
    write_timeseries(both, out / "timeseries.csv")
    write_timeseries(lst, out / "lst_only" / "timeseries.csv")
    write_metrics({"LST+YRT": mb, "LST": ml}, out / "metrics.json")
    figs = _figures([both, lst], out)
    bar.update(1)
    bar.close()
    _summary(mb)
    _summary(ml)
    print(_comparison(mb, ml))
    print(f"demo took {time.perf_counter() - t_start:.1f} s; outputs in {out}")
    for p in figs:
        print(f"figure {p}")
    return 0


def add_cli_commands(sub: Any) -> None:
    """Register ``simulate`` and ``demo`` on the ``ampc`` sub-parsers."""
    from .simulation import FORMULATIONS

    p = sub.add_parser("simulate", help="closed-loop vehicle simulation of a test manoeuvre")
    p.add_argument(
        "scenario",
        help="cruise_lane_change, stability_launch_brake or stability_dlc",
    )
    p.add_argument("--formulation", choices=FORMULATIONS, default="local_explicit")
    p.add_argument(
        "--disable",
        action="append",
        metavar="OBJECTIVE",
        help="leave an objective out (LST/YRT or VSC/WSC); repeatable",
    )
    p.add_argument(
        "--mu",
        type=_arg_type(_mu),
        default=None,
        help="road friction in (0, 2] (default: the scenario's)",
    )
    p.add_argument(
        "--duration",
        type=_arg_type(_duration),
        default=None,
        help="simulated seconds, at least one control period (0.05 s); default: the scenario's",
    )
    p.add_argument("--cold-start", action="store_true", help="cold start every step (paper)")
    p.add_argument(
        "--tol-primal",
        type=_arg_type(_positive_finite),
        default=None,
        help="eps_r > 0 (squared, Nm^2)",
    )
    p.add_argument(
        "--tol-dual", type=_arg_type(_positive_finite), default=None, help="eps_s > 0 (squared)"
    )
    p.add_argument(
        "--max-iter",
        type=_arg_type(_at_least_one, int),
        default=None,
        help="controller iteration cap (>= 1)",
    )
    p.add_argument(
        "--rho-scale",
        default=None,
        metavar="S[,S]",
        help="factor(s) on eq.opt_ro's rho* for Local Explicit: one, or one per objective "
        "of the example (LST,YRT or VSC,WSC); default: the example's tuned value",
    )
    p.add_argument(
        "--relaxation",
        type=float,  # SimConfig checks (0, 2): "ampc: error: relaxation: ..." (exit 2)
        default=None,
        help="ADMM over-relaxation in (0, 2) for Local Explicit and the integrated MPC "
        "(1 = the paper); default: the example's tuned value",
    )
    p.add_argument(
        "--warm-shift",
        type=int,
        choices=(0, 1),
        default=None,
        help="warm start: 1 shifts the previous iterate one step along the horizon, "
        "0 holds it; default: the example's tuned value",
    )
    p.add_argument(
        "--anderson",
        type=int,
        choices=(0, 1, 2, 3),
        default=None,
        help="Anderson acceleration memory for Local Explicit and the integrated MPC "
        "(0 = plain ADMM, the paper); default: the example's value",
    )
    p.add_argument(
        "--integrated-rho-scale",
        type=_arg_type(_positive_finite),
        default=None,
        help="factor on rho* of the IntegratedADMM (controller and r_time replay)",
    )
    p.add_argument(
        "--set",
        action="append",
        metavar="FIELD=VALUE",
        help="override a field of the example's settings (e.g. horizon=2, q_yrt=1e4); "
        "horizon >= 1, dt > 0, q_* >= 0, r_* > 0, bounds >= 0",
    )
    p.add_argument(
        "--compare",
        action="store_true",
        help="also run the paper's baseline (cruise: LST alone; stability: the driver "
        "alone) into OUT/baseline and overlay both in the figures",
    )
    p.add_argument("--no-shadow", action="store_true", help="skip the integrated shadow")
    p.add_argument("--no-timing", action="store_true", help="skip the r_time replay")
    p.add_argument(
        "--repeats",
        type=_arg_type(_at_least_one, int),
        default=3,
        help="timing repeats per step (>= 1)",
    )
    p.add_argument("--float32", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--out", default="out", help="output directory")
    p.set_defaults(func=cmd_simulate)

    d = sub.add_parser("demo", help="cruise-control lane change: LST+YRT vs LST alone")
    d.add_argument("--out", default="ampc_demo", help="output directory")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=cmd_demo)
