"""``ampc run``, ``ampc plant``, ``ampc export``: deployment (``ampc replay``:
:mod:`.replay`).

``ampc run --channel URI --scenario NAME --out DIR`` runs the compiled
controller at 20 Hz next to the CAN bridge (``--with-plant`` also starts
``ampc plant`` on the bridge's fresh pseudo-terminal: the whole demo in one
line); ``ampc plant`` is the simulated vehicle on the other end of the bus;
``ampc export`` writes the controller step as a ``jax.export`` artefact that
``ampc run --artefact`` checks and runs (docs/runtime.md).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import extras
from .args import (
    PARAMS_HELP,
    arg_type,
    enable_x64,
    fail,
    flag_error,
    positive_finite,
    with_params_file,
)
from .outdir import add_force, claim_dir, claim_file
from .replay import add_replay_command

__all__ = ["add_runtime_commands"]

_FLAGS = {
    "formulation": "--formulation",
    "duration": "--duration",
    "scenario": "--scenario",
    "fault": "--fault",
}


def _commit() -> str | None:
    try:
        root = Path(__file__).resolve().parents[2]
        out = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _config(args: argparse.Namespace) -> Any:
    from ..closed_loop import config_for
    from ..vehicle import SCENARIOS

    if args.scenario not in SCENARIOS:
        raise ValueError(
            f"scenario: unknown scenario {args.scenario!r}; expected one of {sorted(SCENARIOS)}"
        )
    kw: dict[str, Any] = {"shadow": False}
    if args.formulation is not None:
        kw["formulation"] = args.formulation
    return with_params_file(
        config_for(SCENARIOS[args.scenario], **kw), getattr(args, "params", None)
    )


def _faults(texts: list[str] | None, kinds: tuple[str, ...]) -> tuple[Any, ...]:
    from ..runtime.faults import parse_fault

    try:
        return tuple(parse_fault(t, kinds) for t in texts or ())
    except ValueError as exc:
        raise ValueError(f"fault: {exc}") from None


def _golden_bus(spec: Any) -> np.ndarray:
    """The bus vector of the scenario's first step (the golden input of an artefact):
    the plant's initial state and the driver's first step as one compiled program,
    not op by op (a compilation per operation), since it is on ``run --artefact``'s
    way to opening the channel."""
    import jax
    import jax.numpy as jnp

    from ..runtime.signals import bus_vector
    from ..vehicle.manoeuvres import (
        DriverParams,
        driver_step,
        initial_driver_state,
        initial_plant_state,
    )
    from ..vehicle.params import VehicleParams

    sc = spec.scenario

    def first() -> Any:
        ps = initial_plant_state(sc, VehicleParams(), jnp.float64)
        _, steer, T, v_ref = driver_step(
            initial_driver_state(jnp.float64), ps, 0.0, sc, DriverParams()
        )
        return ps, steer, T, v_ref

    ps, steer, T, v_ref = jax.jit(first)()
    return bus_vector(ps, steer, T, v_ref, float(sc.mu))


def _rt_priority(text: str) -> int:
    try:
        p = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 0 (off) or an integer 2..99, got {text!r}"
        ) from None
    if not (p == 0 or 2 <= p <= 99):
        raise argparse.ArgumentTypeError(f"expected 0 (off) or an integer 2..99, got {p}")
    return p


def _scheduling(flag: int | None) -> tuple[int | None, str | None, str | None]:
    """(the SCHED_FIFO priority to run at or None, a warning line, an error):
    ``--rt-priority`` given and refused is an error; the default refused runs at
    normal scheduling with one warning line saying what that costs."""
    from ..runtime.runner import RT_PRIORITY, fifo_refusal

    if flag == 0:
        return None, None, None
    priority = RT_PRIORITY if flag is None else flag
    why = fifo_refusal(priority)
    if why is None:
        return priority, None, None
    if flag is not None:
        return None, None, f"--rt-priority {flag}: SCHED_FIFO refused ({why})"
    return (
        None,
        f"real-time scheduling refused (SCHED_FIFO {priority}: {why}): the bridge ticks at "
        "normal priority, where its period error seen by the receiver reached 3 to 5 ms "
        "at p99 on a busy machine against 0.04 ms for the bridge itself under SCHED_FIFO "
        '(docs/runtime.md, "Timing"); --rt-priority 0 says normal scheduling is meant',
        None,
    )


def _cpu_list(text: str) -> tuple[int, ...]:
    import os

    try:
        cpus = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected CPU numbers like 0 or 1,2, got {text!r}"
        ) from None
    have = os.sched_getaffinity(0)
    if not cpus or any(c not in have for c in cpus):
        raise argparse.ArgumentTypeError(f"expected CPUs among {sorted(have)}, got {text!r}")
    return cpus


def cmd_run(args: argparse.Namespace) -> int:
    """``ampc run``: the controller at 20 Hz next to the bridge.

    Order: the flags checked, an artefact read, compiled and its golden pair
    checked (exit 2, nothing started), the channel opened (a missing device:
    exit 2 at once), the plant started, the in-process step compiled, the loop."""
    import os

    needs = extras.BRIDGE + (extras.EXPORT if args.artefact else ())
    missing = extras.missing_message("run", needs + (extras.PLANT if args.with_plant else ()))
    if missing:
        return fail(missing)
    if args.cpus:
        os.sched_setaffinity(0, args.cpus)
    rt_priority, rt_warning, rt_error = _scheduling(args.rt_priority)
    if rt_error:
        return fail(rt_error)
    if rt_warning:
        print(f"ampc: warning: {rt_warning}", file=sys.stderr)
    enable_x64()
    if rt_priority is not None:
        import jax

        # the step then runs in the (real-time) calling thread, not a worker's
        jax.config.update("jax_cpu_enable_async_dispatch", False)

    from ..runtime.artefact import ArtefactError, read_artefact
    from ..runtime.faults import CONTROLLER_FAULTS
    from ..runtime.runner import ChannelError, Prepared, RunOptions, run_controller
    from ..runtime.step import RuntimeStep
    from ..vehicle import SCENARIOS

    try:
        cfg = _config(args)
        faults = _faults(args.fault, CONTROLLER_FAULTS)
        step = RuntimeStep(cfg, "float32" if args.float32 else "float64")
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    if args.with_plant and args.channel != "slcan-pty:":
        return fail("--with-plant: needs --channel slcan-pty: (the plant opens its pty)")
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    out = Path(args.out)
    duration = _run_duration(args)
    try:
        options = RunOptions(
            duration=duration, lead_ms=args.lead_ms, faults=faults, rt_priority=rt_priority
        )
    except ValueError as exc:
        return fail(flag_error(exc, {"lead_ms": "--lead-ms", "duration": "--duration"}))
    art_fn = None
    if args.artefact:
        # Rule: every check of an artefact, its compilation and golden pair
        # included, before the channel opens; reason: a file one received must
        # not get as far as an open bus (a forged step that resealed its digests
        # is only seen by deserializing, compiling and running it).
        try:
            art = read_artefact(
                args.artefact,
                step.config_hash(),
                step=step,
                golden_bus=_golden_bus(SCENARIOS[args.scenario]),
                scenario=args.scenario,
            )
            t0 = time.perf_counter()
            art_fn = art.compiled()
        except ArtefactError as exc:
            return fail(f"--artefact: {exc}")
        art_s = time.perf_counter() - t0
    source = f"artefact {args.artefact}" if art_fn is not None else "compiled in process"

    def prepare() -> Prepared:
        t0 = time.perf_counter()
        # the state starts from this process's cold state, never from the file
        fn = art_fn if art_fn is not None else step.compiled()
        took = art_s if art_fn is not None else time.perf_counter() - t0
        print(f"controller step ready ({source}, {took:.1f} s)", flush=True)
        return Prepared(fn, step.init_leaves(), step.jnp_dtype)

    plant_cmd = None
    if args.with_plant:
        plant_cmd = [
            sys.executable,
            "-m",
            "ampc_jax.cli",
            "plant",
            "--channel",
            "slcan:{pty}",
            "--scenario",
            args.scenario,
            "--duration",
            f"{duration:g}",
            "--out",
            str(out / "plant"),
            "--quiet",
            "--force",  # OUT is this run's (claimed above), OUT/plant too
        ]
        for f in args.plant_fault or ():
            plant_cmd += ["--fault", f]
        if duration > SCENARIOS[args.scenario].duration:
            plant_cmd.append("--repeat")
        if args.plant_cpus:
            plant_cmd = ["taskset", "-c", ",".join(map(str, args.plant_cpus)), *plant_cmd]
    meta = {
        "scenario": args.scenario,
        "formulation": cfg.formulation,
        "dtype": step.dtype,
        "config_hash": step.config_hash(),
        "source": source,
        "channel": args.channel,
        "duration_s": duration,
        "faults": list(args.fault or ()),
        "scheduling": {
            "rt_priority": rt_priority,
            "refused": rt_warning is not None,
        },
        "commit": _commit(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }
    progress = None if args.quiet else (lambda line: print(line, flush=True))
    try:
        log = run_controller(
            prepare,
            args.channel,
            out,
            options,
            meta=meta,
            plant_cmd=plant_cmd,
            plant_out=out / "plant" if plant_cmd is not None else None,
            progress=progress,
        )
    except ChannelError as exc:
        return fail(f"--channel: {exc}")
    except ArtefactError as exc:
        return fail(f"--artefact: {exc}")
    except (TimeoutError, RuntimeError, OSError, ValueError) as exc:
        return fail(f"run: {exc}", 1)
    s = log.summary
    print(_run_line(s))
    print(f"wrote {out / 'ticks.parquet'}, {out / 'run.json'}, {out / 'bridge.log'}")
    if s["state"] == "error":
        return fail(f"run: {s['error']} (logs written to {out})", 1)
    if s.get("stopped_by") == "SIGINT":
        return fail(f"interrupted (logs written to {out})", 130)
    return 0


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _run_line(s: dict[str, Any]) -> str:
    """``ampc run``'s closing line: the counts and the compute times, formatted."""
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(s["skipped"].items())) or "none"
    b = s["bridge"]
    rx = s.get("receive_period")
    sched = s.get("scheduling") or {}
    prio = sched.get("rt_priority")
    line = (
        f"ran {s['ticks']} ticks: sent {s['sent']}, misses {s['misses']}, skipped {skipped}; "
        f"compute median {_ms(s['compute_ms_median'])} ms, p99 {_ms(s['compute_ms_p99'])} ms; "
        f"bridge {b['safety_state']}, "
        f"{f'SCHED_FIFO {prio}' if prio else 'normal scheduling'}, "
        f"tick lateness p99 {_ms(b.get('lateness_p99_ms'))} ms"
    )
    if rx and rx.get("error_ms_p99") is not None:
        line += (
            f"; received period {_ms(rx['period_ms_median'])} ms, |error| p50 "
            f"{_ms(rx['error_ms_p50'])} ms, p99 {_ms(rx['error_ms_p99'])} ms "
            f"({rx['frames']} frames at the plant)"
        )
    return line


def _run_duration(args: argparse.Namespace) -> float:
    """``--duration``, or the scenario's duration."""
    from ..vehicle import SCENARIOS

    return float(args.duration if args.duration is not None else SCENARIOS[args.scenario].duration)


def cmd_plant(args: argparse.Namespace) -> int:
    """``ampc plant``: the simulated vehicle on the bus."""
    missing = extras.missing_message("plant", extras.PLANT)
    if missing:
        return fail(missing)
    enable_x64()
    from ..runtime.faults import SENSOR_FAULTS
    from ..runtime.plant_node import write_report
    from ..vehicle import SCENARIOS

    if args.scenario not in SCENARIOS:
        return fail(
            f"--scenario: unknown scenario {args.scenario!r}; expected one of {sorted(SCENARIOS)}"
        )
    try:
        faults = _faults(args.fault, SENSOR_FAULTS)
    except ValueError as exc:
        return fail(flag_error(exc, {"fault": "--fault"}))
    problem = claim_dir(args.out, args.force)
    if problem:
        return fail(problem)
    out = Path(args.out)
    try:
        node = _plant_node(args, faults, out)
    except ValueError as exc:
        return fail(flag_error(exc, {"channel": "--channel"}))
    progress = None if args.quiet else (lambda t: print(f"plant t {t:5.1f} s", flush=True))
    try:
        rep = node.run(progress)
        write_report(rep, out)
    except (TimeoutError, OSError) as exc:
        return fail(f"plant: {exc}", 1)
    s = rep.summary
    print(
        f"plant: {s['frames']} torque frames ({s['frames_bad']} bad), modes {s['modes']}, "
        f"period p99 deviation {s['period_dev_ms_p99']} ms; wrote {out}"
    )
    return 0


def _plant_node(args: argparse.Namespace, faults: tuple[Any, ...], out: Path) -> Any:
    from ..runtime.plant_node import PlantNode

    return PlantNode(
        args.channel,
        args.scenario,
        args.duration,
        # None: the actuator contract's timeout (ampc_jax.vehicle.actuators)
        **({} if args.cmd_timeout_ms is None else {"cmd_timeout_ms": args.cmd_timeout_ms}),
        faults=faults,
        log_path=out / "plant_bus.log",
        repeat=args.repeat,
    )


def cmd_export(args: argparse.Namespace) -> int:
    """``ampc export``: the controller step as a jax.export artefact."""
    missing = extras.missing_message("export", extras.EXPORT)
    if missing:
        return fail(missing)
    enable_x64()
    from ..runtime.artefact import export_step
    from ..runtime.step import RuntimeStep
    from ..vehicle import SCENARIOS

    try:
        cfg = _config(args)
        step = RuntimeStep(cfg, "float32" if args.float32 else "float64")
    except ValueError as exc:
        return fail(flag_error(exc, _FLAGS))
    problem = claim_file(args.out, args.force)
    if problem:
        return fail(problem)
    path = Path(args.out)
    try:
        m = export_step(step, _golden_bus(SCENARIOS[args.scenario]), path, scenario=args.scenario)
    except OSError as exc:  # a FileError: names the file
        return fail(f"export: {exc}", 1)
    print(
        f"wrote {path}: {m['formulation']} {m['dtype']}, config {m['config_hash'][:12]}, "
        f"calling convention {m['calling_convention_version']}, jax {m['jax']}"
    )
    return 0


def add_runtime_commands(sub: Any) -> None:
    """Register ``run``, ``plant``, ``export`` and ``replay``."""
    from ..formulations import formulation_names
    from ..runtime.faults import CONTROLLER_FAULTS, SENSOR_FAULTS

    forms = list(formulation_names(closed_loop=True))
    r = sub.add_parser(
        "run",
        help="the controller at 20 Hz next to the CAN bridge",
        description="Run the compiled controller every 50 ms next to can_bridge: latest "
        "valid state in, first-step torques out; nothing new is sent on a stale or invalid "
        "state or a failed step (the bridge's watchdog then holds and releases).",
    )
    r.add_argument(
        "--channel",
        required=True,
        help="the bridge's channel: socketcan:IFACE, slcan:PATH[@BAUD], slcan-pty: or "
        "socketcand:HOST:PORT/BUS (required)",
    )
    r.add_argument(
        "--scenario", required=True, help="the scenario the controller is set up for (required)"
    )
    r.add_argument(
        "--formulation",
        choices=forms,
        default=None,
        help="the controller's formulation (default: the scenario's, local_explicit)",
    )
    r.add_argument(
        "--duration",
        type=arg_type(positive_finite),
        default=None,
        help="seconds of actuation (default: the scenario's duration)",
    )
    r.add_argument(
        "--artefact",
        default=None,
        help="run an `ampc export` artefact (default: compile in process)",
    )
    r.add_argument("--float32", action="store_true", help="float32 step (default: float64)")
    r.add_argument("--params", metavar="FILE", default=None, help=PARAMS_HELP)
    r.add_argument(
        "--with-plant",
        action="store_true",
        help="also start `ampc plant` on the bridge's pseudo-terminal (needs "
        "--channel slcan-pty:; its logs go to OUT/plant) (default: off)",
    )
    r.add_argument(
        "--lead-ms",
        type=arg_type(positive_finite),
        default=25.0,
        help="start each tick this long before the bridge's tick, in ms: room for the "
        "state read, the step and the hand-over (default: 25)",
    )
    r.add_argument(
        "--fault",
        action="append",
        metavar="KIND@START:END",
        help=f"inject a controller fault, KIND one of {', '.join(CONTROLLER_FAULTS)}, "
        "START and END in seconds of actuation; repeatable (default: none)",
    )
    r.add_argument(
        "--plant-fault",
        action="append",
        metavar="KIND@START:END",
        help=f"with --with-plant: a sensor fault of the plant, KIND one of "
        f"{', '.join(SENSOR_FAULTS)} (default: none)",
    )
    r.add_argument(
        "--rt-priority",
        type=_rt_priority,
        default=None,
        help="SCHED_FIFO priority 2..99 for the bridge's transmit thread (the loop gets one "
        "less; needs root, CAP_SYS_NICE or RLIMIT_RTPRIO), 0 for normal scheduling; given "
        "and refused, an error (default: 50 where the system allows it, else normal "
        "scheduling with one warning line)",
    )
    r.add_argument(
        "--cpus",
        type=_cpu_list,
        default=None,
        help="pin the runtime (controller and bridge) to these CPUs, e.g. 1 or 2,3 "
        "(default: no pinning)",
    )
    r.add_argument(
        "--plant-cpus",
        type=_cpu_list,
        default=None,
        help="with --with-plant: pin the plant to these CPUs (default: no pinning)",
    )
    r.add_argument("--quiet", action="store_true", help="no progress line (default: one a second)")
    r.add_argument("--out", default="run", help="output directory (default: run)")
    add_force(r)
    r.set_defaults(func=cmd_run)

    p = sub.add_parser(
        "plant",
        help="the simulated vehicle on the other end of the bus (python-can, cantools)",
        description="Integrate the nonlinear plant in real time with the scenario's driver, "
        "publish the state messages every 20 ms with E2E protection, apply the torque "
        "frames received (zero after --cmd-timeout-ms of silence).",
    )
    p.add_argument(
        "--channel", required=True, help="slcan:PATH, the pty or serial device (required)"
    )
    p.add_argument("--scenario", required=True, help="the manoeuvre (required)")
    p.add_argument(
        "--duration",
        type=arg_type(positive_finite),
        default=None,
        help="seconds of manoeuvre (default: the scenario's duration)",
    )
    p.add_argument(
        "--cmd-timeout-ms",
        type=arg_type(positive_finite),
        default=None,
        help="silence after which the plant applies zero torque (default: the actuator "
        "contract's 200, which the bridge's vehicle.toml shares as actuator_timeout_ms)",
    )
    p.add_argument(
        "--fault",
        action="append",
        metavar="KIND@START:END",
        help=f"inject a sensor fault, KIND one of {', '.join(SENSOR_FAULTS)}, START and END "
        "in seconds of manoeuvre; repeatable (default: none)",
    )
    p.add_argument(
        "--repeat",
        action="store_true",
        help="start the manoeuvre again from its initial state whenever it ends before "
        "--duration (long timing runs) (default: off)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress line (default: one a second)")
    p.add_argument("--out", default="plant", help="output directory (default: plant)")
    add_force(p)
    p.set_defaults(func=cmd_plant)

    e = sub.add_parser(
        "export",
        help="the controller step as a jax.export artefact with a manifest",
        description="Write the compiled controller step (serialized StableHLO) and a "
        "manifest (versions, configuration hash, shapes, a golden input/output pair).",
    )
    e.add_argument(
        "--scenario", required=True, help="the scenario the controller is set up for (required)"
    )
    e.add_argument("--formulation", choices=forms, default=None, help="(default: local_explicit)")
    e.add_argument("--float32", action="store_true", help="float32 step (default: float64)")
    e.add_argument("--params", metavar="FILE", default=None, help=PARAMS_HELP)
    e.add_argument("--out", required=True, help="the artefact file to write (required)")
    add_force(e, "replace an --out file that exists (default: refuse it)")
    e.set_defaults(func=cmd_export)
    add_replay_command(sub, forms)
