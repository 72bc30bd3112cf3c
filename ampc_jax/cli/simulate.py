"""``ampc simulate`` and ``ampc demo``: closed loops, their CSV/JSON outputs and figures.

``ampc simulate SCENARIO --out DIR`` writes ``DIR/timeseries.csv`` (one row per
control step), ``DIR/metrics.json`` and the figures; with ``--compare`` it also
runs the paper's baseline (LST alone for cruise control, the driver alone for
stability control) into ``DIR/baseline/`` (the same two files) and overlays
both runs in the figures. ``ampc demo`` is ``ampc simulate cruise_lane_change
--compare`` with the r_time replay, and prints the key numbers.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .args import (
    add_output_flags,
    add_params_flag,
    add_solver_flags,
    arg_type,
    at_least_one,
    fail,
    flag_error,
    positive_finite,
    progress_disabled,
    with_params_file,
)
from .outdir import add_force, claim_dir

__all__ = ["add_simulate_commands", "cmd_demo", "cmd_simulate"]

_FLAGS = {
    "formulation": "--formulation",
    "disable": "--disable",
    "tol_primal": "--tol-primal",
    "tol_dual": "--tol-dual",
    "max_iter": "--max-iter",
    "rho_scale": "--rho-scale",
    "relaxation": "--relaxation",
    "integrated_rho_scale": "--integrated-rho-scale",
    "warm_shift": "--warm-shift",
    "anderson": "--anderson",
    "compare": "--compare",
    "duration": "--duration",
    "mu": "--mu",
    "actuators": "--actuators",
}


def _duration(value: float) -> None:
    from ..closed_loop import check_duration

    check_duration(value)


def _mu(value: float) -> None:
    from ..closed_loop import check_mu

    check_mu(value)


def _enable_x64(float32: bool = False) -> None:
    import jax

    if not float32:
        jax.config.update("jax_enable_x64", True)


def _bar(total: int, quiet: bool) -> Any:
    from tqdm import tqdm

    return tqdm(
        total=total,
        disable=progress_disabled(quiet),
        bar_format="{desc:<28}{bar:20}| {n_fmt}/{total_fmt}",
    )


def _note(text: str, quiet: bool) -> None:
    """One progress line on stderr (not with ``--quiet``): the compile of a closed
    loop takes seconds, and without a terminal no bar shows that it started."""
    if not quiet:
        from tqdm import tqdm

        tqdm.write(text, file=sys.stderr)  # above a bar on a terminal, not through it
        sys.stderr.flush()


def _ran(res: Any) -> str:
    """What a compiled closed loop took: its compile and its (warm) run."""
    wall = res.wall_time
    speed = f" ({res.duration / wall:.0f}x real time)" if wall > 0 else ""
    return (
        f"compiled in {res.compile_time:.1f} s; {res.duration:g} s simulated in {wall:.2f} s{speed}"
    )


def _replay(cfg: Any, log: Any, repeats: int, quiet: bool) -> dict:
    """:func:`~ampc_jax.closed_loop.replay_timing` with a bar over the replayed steps."""
    from tqdm import tqdm

    from ..closed_loop import replay_timing

    n = int(np.shape(log.t)[0])
    with tqdm(
        total=n,
        disable=progress_disabled(quiet),
        leave=False,
        unit="step",
        bar_format="  {desc}{bar:20}| {n_fmt}/{total_fmt} steps [{elapsed}<{remaining}]",
        desc="replayed ",
    ) as steps:
        return replay_timing(cfg, log, repeats=repeats, progress=steps.update)


def _run(
    spec: Any,
    cfg: Any,
    base_cfg: Any,
    out: Path,
    *,
    duration: float | None,
    mu: float | None,
    float32: bool,
    timing: bool,
    repeats: int,
    quiet: bool,
) -> tuple[dict[str, Any], dict[str, Any] | None, list[Path]]:
    """Run, replay, write and draw one run and its baseline: (metrics, baseline's, figures)."""
    import jax
    import jax.numpy as jnp

    from ..closed_loop import simulate
    from ..io.reports import write_figures, write_run

    bar = _bar(5 if base_cfg else 4, quiet)
    bar.set_description("compile + run closed loop")
    dtype = jnp.float32 if float32 else jnp.float64
    _note("compiling the closed loop ...", quiet)
    res = simulate(spec, cfg, duration=duration, mu=mu, dtype=dtype)
    _note(_ran(res), quiet)
    bar.update(1)
    base = None
    if base_cfg is not None:
        bar.set_description("baseline: compile + run")
        _note("compiling the baseline's closed loop ...", quiet)
        base = simulate(spec, base_cfg, duration=duration, mu=mu, dtype=dtype)
        _note("baseline: " + _ran(base), quiet)
        bar.update(1)
    bar.set_description("replay timing (r_time)")
    if timing:
        _note(f"replaying {len(res.log.t)} control steps for r_time (eq.t_ratio) ...", quiet)
        t0 = time.perf_counter()
        res.timing = _replay(cfg, jax.tree.map(jnp.asarray, res.log), repeats, quiet)
        _note(f"replayed in {time.perf_counter() - t0:.1f} s", quiet)
    bar.update(1)
    bar.set_description("write csv/json")
    write_run(res, out)
    if base is not None:
        write_run(base, out / "baseline")
    bar.update(1)
    bar.set_description("figures")
    figs = write_figures([res] if base is None else [res, base], out)
    bar.update(1)
    bar.close()
    return res.metrics(), (base.metrics() if base is not None else None), figs


def _report(m: dict[str, Any], mb: dict[str, Any] | None, out: Path, figs: list[Path]) -> None:
    from ..io.reports import comparison_line, summary_lines

    for line in summary_lines(m):
        print(line)
    if mb is not None:
        for line in summary_lines(mb):
            print(line)
        print(comparison_line(m, mb))
    print(f"wrote {out / 'timeseries.csv'}, {out / 'metrics.json'}")
    if mb is not None:
        print(f"baseline in {out / 'baseline'}")
    for p in figs:
        print(f"figure {p}")


def cmd_simulate(args: argparse.Namespace) -> int:
    """``ampc simulate``: one scenario's closed loop, its metrics and figures."""
    _enable_x64(args.float32)
    from ..closed_loop import baseline_config, config_for, with_settings
    from ..vehicle import SCENARIOS

    if args.scenario not in SCENARIOS:
        return fail(f"unknown scenario {args.scenario!r}; expected one of {sorted(SCENARIOS)}")
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
            actuators=args.actuators,
        )
        given = tuple(
            k
            for k, v in (("rho_scale", args.rho_scale), ("relaxation", args.relaxation))
            if v is not None
        )
        cfg = with_params_file(cfg, args.params, keep=given)
        if args.set:
            cfg = with_settings(cfg, **_parse_settings(args.set, cfg.settings, cfg.example))
        if args.params is not None:
            _warn_tuned_for(args.params, cfg, "float32" if args.float32 else "float64")
        base_cfg = baseline_config(cfg) if args.compare else None
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    print(_header(args.scenario, cfg))
    out = Path(args.out)
    decomposed = cfg.mpc and cfg.formulation_info.decomposed  # r_time: against the integrated
    timing = decomposed and not args.no_timing and cfg.shadow
    m, mb, figs = _run(
        spec,
        cfg,
        base_cfg,
        out,
        duration=args.duration,
        mu=args.mu,
        float32=args.float32,
        timing=timing,
        repeats=args.repeats,
        quiet=args.quiet,
    )
    _report(m, mb, out, figs)
    return 0


def _parse_floats(flag: str, text: str | None) -> float | tuple[float, ...] | None:
    """``"0.5"`` -> 0.5, ``"1,0.5"`` -> (1.0, 0.5); None stays None (the example's default)."""
    if text is None:
        return None
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(
            f"{flag}: expected a number or comma-separated numbers (one per objective), "
            f"got {text!r}"
        ) from None
    return vals[0] if len(vals) == 1 else vals


def _header(scenario: str, cfg: Any) -> str:
    """The first line printed: the scenario and the solver settings it runs (the
    example's ``solver_defaults`` where no flag or file gave one)."""
    if not cfg.mpc:
        return f"ampc simulate: {scenario}, no MPC"
    o = cfg.solver_options()
    rs = o["rho_scale"]
    rs = ", ".join(f"{x:g}" for x in rs) if isinstance(rs, list) else f"{rs:g}"
    start = ", learned start" if cfg.learned_start is not None else ""
    return (
        f"ampc simulate: {scenario}, {cfg.formulation}, rho scale ({rs}), relaxation "
        f"{o['relaxation']:g}, Anderson {o['anderson']}{start} (the {cfg.example} example's "
        f"defaults where no flag or --params gave one)"
    )


def _warn_tuned_for(path: str, cfg: Any, dtype: str) -> None:
    """One warning line on stderr when the file was tuned under other solver
    settings than ``cfg`` runs (its ``tuned_for``)."""
    from ..io.params_file import read_params, tuned_for_warning

    running = {
        "formulation": cfg.formulation,
        "dtype": dtype,
        "tol": cfg.tol_primal,
        **cfg.solver_options(),
    }
    line = tuned_for_warning(path, read_params(path), running)
    if line is not None:
        print(f"ampc: warning: {line}", file=sys.stderr)


def _parse_settings(items: list[str], settings: Any, example: str | None = None) -> dict[str, Any]:
    """``--set horizon=2 --set q_yrt=1e4`` -> fields of the example's settings, each
    within the tuned-parameters file's bounds (a factor 1e6 of the default, the
    horizon's 10 s of prediction)."""
    from ..io.params_file import check_settings_bounds

    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in settings.field_names():
            raise ValueError(
                f"--set {item}: expected FIELD=VALUE with FIELD one of {list(settings.field_names())}"
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
            settings.replace(**{key: out[key]}).validate()
        except ValueError as exc:
            msg = str(exc).removeprefix(f"{key}: ")
            raise ValueError(f"--set {item}: {msg}") from None
        if example is not None:
            try:
                check_settings_bounds(settings, {key: out[key]}, example)
            except ValueError as exc:
                msg = str(exc).removeprefix(f"settings.{key}: ")
                raise ValueError(f"--set {item}: {msg}") from None
    return out


_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def cmd_demo(args: argparse.Namespace) -> int:
    """``ampc demo``: the cruise-control lane change, LST+YRT against LST alone."""
    _enable_x64()
    from ..closed_loop import baseline_config, config_for
    from ..vehicle import SCENARIOS

    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    out = Path(args.out)
    t_start = time.perf_counter()
    spec = SCENARIOS["cruise_lane_change"]
    cfg = config_for(spec)
    m, mb, figs = _run(
        spec,
        cfg,
        baseline_config(cfg),
        out,
        duration=None,
        mu=None,
        float32=False,
        timing=True,
        repeats=3,
        quiet=args.quiet,
    )
    _report(m, mb, out, figs)
    print(f"demo took {time.perf_counter() - t_start:.1f} s; outputs in {out}")
    return 0


def add_simulate_commands(sub: Any) -> None:
    """Register ``ampc simulate`` and ``ampc demo`` on the ``ampc`` sub-parsers."""
    from ..closed_loop import loop_formulations
    from ..formulations import DEFAULT_FORMULATION
    from ..vehicle import SCENARIOS

    p = sub.add_parser(
        "simulate",
        help="closed-loop vehicle simulation of a test manoeuvre",
        description="Closed-loop simulation of one of the paper's manoeuvres on the "
        "nonlinear plant, with the integrated MPC in shadow.",
    )
    p.add_argument("scenario", help="the manoeuvre: " + ", ".join(sorted(SCENARIOS)))
    p.add_argument(
        "--formulation",
        choices=loop_formulations(),
        default=DEFAULT_FORMULATION,
        help="the controller: Local Explicit (the paper's Formulation 3), Fully "
        "Distributed (1), Virtual Center Node (2), the integrated MPC, or none (the "
        "driver alone) (default: local_explicit)",
    )
    p.add_argument(
        "--disable",
        action="append",
        metavar="OBJECTIVE",
        help="leave an objective out (LST/YRT or VSC/WSC); repeatable (default: none)",
    )
    p.add_argument(
        "--mu",
        type=arg_type(_mu),
        default=None,
        help="road friction in (0, 2] (default: the scenario's)",
    )
    p.add_argument(
        "--duration",
        type=arg_type(_duration),
        default=None,
        help="simulated seconds, at least one control period (0.05 s) (default: the scenario's)",
    )
    p.add_argument(
        "--cold-start",
        action="store_true",
        help="cold start every step, as the paper (default: warm start)",
    )
    p.add_argument(
        "--tol-primal",
        type=arg_type(positive_finite),
        default=None,
        help="eps_r of the stopping rule (paper eq. Convergence), squared, Nm^2 (default: 1)",
    )
    p.add_argument(
        "--tol-dual",
        type=arg_type(positive_finite),
        default=None,
        help="eps_s of the stopping rule, squared, Nm^2 (default: 1)",
    )
    p.add_argument(
        "--rho-scale",
        default=None,
        metavar="S[,S]",
        help="factor(s) on the automatic rho: Ghadimi's optimal rho (paper eq. opt_ro) for "
        "Local Explicit, sqrt(lambda_min lambda_max) of each objective's Hessian for "
        "Formulations 1 and 2: one, or one per objective of the example (LST,YRT or "
        "VSC,WSC) (default: the example's tuned value, for Local Explicit 1,0.5 for "
        "cruise and 0.3,3 for stability, for Formulations 1 and 2 1)",
    )
    p.add_argument(
        "--warm-shift",
        type=int,
        choices=(0, 1),
        default=None,
        help="warm start: 1 shifts the previous iterate one step along the horizon, "
        "0 holds it (default: the example's tuned value, 1 for cruise, 0 for stability)",
    )
    add_solver_flags(
        p,
        relaxation="ADMM over-relaxation in (0, 2) for the controller and the integrated "
        "MPC; 1 is the paper's iteration (default: the example's tuned value, 1.5)",
        anderson="Anderson acceleration memory for the controller and the integrated MPC; "
        "0 is plain ADMM, the paper (default: the example's value, 3)",
        max_iter="the controller's iteration cap (default: 200)",
    )
    p.add_argument(
        "--integrated-rho-scale",
        type=arg_type(positive_finite),
        default=None,
        help="factor on the integrated MPC's optimal rho (controller and r_time replay) "
        "(default: the example's tuned value, 0.3 for cruise, 1.2 for stability)",
    )
    add_params_flag(p)
    p.add_argument(
        "--set",
        action="append",
        metavar="FIELD=VALUE",
        help="override a field of the example's settings (e.g. horizon=2, q_yrt=1e4); "
        "horizon >= 1, dt > 0, q_* >= 0, r_* > 0, bounds >= 0 (default: the example's "
        "settings)",
    )
    p.add_argument(
        "--compare",
        action="store_true",
        help="also run the paper's baseline (cruise: LST alone; stability: the driver "
        "alone) into OUT/baseline and overlay both in the figures (default: off)",
    )
    p.add_argument(
        "--actuators",
        choices=("ideal", "bridge"),
        default="ideal",
        help="between controller and plant: 'ideal' (the commanded torques) or 'bridge' "
        "(the CAN bridge's ranges, rates and 2 Nm steps, as `ampc run` applies them) "
        "(default: ideal)",
    )
    p.add_argument(
        "--no-shadow",
        action="store_true",
        help="skip the integrated MPC in shadow, so no e_sub (default: shadow on)",
    )
    p.add_argument(
        "--no-timing",
        action="store_true",
        help="skip the r_time replay (paper eq. t_ratio) (default: replay on)",
    )
    p.add_argument(
        "--repeats",
        type=arg_type(at_least_one, int),
        default=3,
        help="timing repeats per replayed step (default: 3)",
    )
    add_output_flags(
        p, float32="simulate", quiet="no progress bar (default: a bar on a terminal)", out="out"
    )
    add_force(p)
    p.set_defaults(func=cmd_simulate)

    d = sub.add_parser(
        "demo",
        help="the cruise-control lane change: LST+YRT against LST alone",
        description="The main job: the paper's cruise-control lane change on the nonlinear "
        "plant, LST+YRT against LST alone, with e_sub, iterations and r_time.",
    )
    d.add_argument("--out", default="demo", help="output directory (default: demo)")
    add_force(d)
    d.add_argument(
        "--quiet", action="store_true", help="no progress bar (default: a bar on a terminal)"
    )
    d.set_defaults(func=cmd_demo)
