"""``ampc solve``: one MPC step of a problem file, as a table or one JSON object."""

from __future__ import annotations

import argparse
import json
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
    fail,
    flag_error,
    non_negative_finite,
    positive_finite,
    warnings_as_lines,
)

__all__ = ["add_solve_command", "cmd_solve"]

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

MAX_ITER_DEFAULT = 1000
"""``ampc solve --max-iter`` default (the Python API's ``LocalExplicit.max_iter`` is 500)."""

TOL_DEFAULT = 1e-6

_FLAGS = {
    "rho": "--rho",
    "rho_scale": "--rho-scale",
    "relaxation": "--relaxation",
    "anderson": "--anderson",
    "finish": "--finish",
    "max_iter": "--max-iter",
    "tol_primal": "--tol",
    "tol_dual": "--tol",
    "tol_rel": "--tol-rel",
}


def _resolve_problem(path: str) -> Path:
    p = Path(path)
    if not p.exists() and (EXAMPLES / path).exists():
        return EXAMPLES / path
    if not p.exists() and (EXAMPLES / f"{path}.json").exists():
        return EXAMPLES / f"{path}.json"
    return p


def _parse_rho(text: str) -> float | None:
    if text == "auto":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 'auto' or a positive number, got {text!r}"
        ) from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def _scales(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated positive numbers, got {text!r}"
        ) from None
    if not all(v > 0 and v < float("inf") for v in vals):
        raise argparse.ArgumentTypeError(f"expected positive finite numbers, got {text!r}")
    return vals


def _warm_state(path: str, solver: Any, dt: Any) -> Any:
    """Read a previous ``--json`` output's ``warm_state`` and shift it one step."""
    try:
        d = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"--warm-start {path}: cannot read a JSON result ({exc})") from exc
    ws = d.get("warm_state") if isinstance(d, dict) else None
    if not isinstance(ws, dict):
        raise ValueError(
            f"--warm-start {path}: no 'warm_state' object; pass the --json output of a "
            f"previous 'ampc solve --formulation local_explicit'"
        )
    for key in ("U", "Z", "gamma"):
        if key not in ws:
            raise ValueError(f"--warm-start {path}: warm_state has no {key!r}")
        try:
            arrs = (
                [np.asarray(x, float) for x in ws[key]]
                if key != "Z"
                else [np.asarray(ws[key], float)]
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"--warm-start {path}: warm_state.{key}: expected numbers in nested lists ({exc})"
            ) from None
        if not all(np.all(np.isfinite(a)) for a in arrs):
            raise ValueError(
                f"--warm-start {path}: warm_state.{key} contains a null, NaN or inf "
                f"(a result without a usable iterate); start cold instead"
            )
    try:
        state = solver.state_of(ws["U"], ws["Z"], ws["gamma"], dt)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(
            f"--warm-start {path}: warm_state does not match this problem ({exc})"
        ) from exc
    return solver.shift(state)


def _params_file(path: str | None) -> tuple[tuple[float, ...] | None, float | None, Any]:
    """(rho scales, relaxation, learned start) of a tuned-parameters file
    (``--params``), or Nones. Its ``settings`` (an example's weights) do not
    apply to a problem file."""
    if path is None:
        return None, None, None
    from ..io.params_file import read_params

    try:
        tuned = read_params(path)
    except ValueError as exc:
        raise ValueError(f"--params {path}: {exc}") from None
    rs = tuned.rho_scale
    scales = None if rs is None else (tuple(rs) if isinstance(rs, tuple) else (float(rs),))
    return scales, tuned.relaxation, tuned.warm_start


def _timed(fn: Any, *args: Any, repeats: int = 7) -> tuple[Any, float]:
    """Run a compiled function once to warm up, then return its result and median time."""
    import jax

    res = jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return res, float(np.median(times))


def _ignored(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    """(cause, the flags given that it makes unused), one entry per cause
    (``--solver`` is for a formulation that solves the problem whole,
    ``info.decomposed`` False)."""
    from ..formulations import formulation_info

    decomposed = formulation_info(args.formulation).decomposed
    out: list[tuple[str, list[str]]] = []
    if decomposed and args.solver is not None:
        out.append((f"--formulation {args.formulation}", ["--solver"]))
    reference = not decomposed and args.solver in (None, "clarabel", "osqp")
    if reference:
        given = [
            flag
            for flag, on in (
                ("--rho", args.rho is not None),
                ("--rho-scale", args.rho_scale is not None),
                ("--relaxation", args.relaxation is not None),
                ("--anderson", args.anderson is not None),
                ("--finish", args.finish is not None),
                ("--max-iter", args.max_iter is not None),
                ("--tol-rel", args.tol_rel != 0.0),
                ("--float32", args.float32),
            )
            if on
        ]
        if given:
            out.append((f"--solver {args.solver or 'clarabel'}", given))
    elif args.rho is not None and args.rho_scale is not None:
        out.append(("--rho VALUE (used as it is)", ["--rho-scale"]))
    return out


def cmd_solve(args: argparse.Namespace) -> int:
    """``ampc solve``: one MPC step; exit 0 with a solution, 1 without, 2 on bad input."""
    import jax

    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from ..formulations import (
        formulation,
        formulation_info,
        formulation_names,
        formulation_options,
    )
    from ..problem import Problem, ProblemError, merged_data, merged_topology
    from ..reference import solve_reference
    from ..results import Status, status_message, status_name, usable

    info = formulation_info(args.formulation)
    with_file = " or ".join(formulation_names(state_file=True))
    path = _resolve_problem(args.problem)
    if not path.exists():
        shipped = ", ".join(sorted(x.stem for x in EXAMPLES.glob("*.json")))
        return fail(f"{args.problem}: no such problem file, nor a shipped example ({shipped})")
    for cause, flags in _ignored(args):
        print(f"ampc: {', '.join(flags)} ignored by {cause}", file=sys.stderr)
    max_iter = MAX_ITER_DEFAULT if args.max_iter is None else args.max_iter
    try:
        file_scales, file_relaxation, file_start = _params_file(args.params)
    except ValueError as exc:
        return fail(str(exc))
    scales = (
        (file_scales or (1.0,)) if args.rho_scale is None else args.rho_scale
    )  # the explicit flag wins over the file
    relaxation = (
        (1.0 if file_relaxation is None else file_relaxation)
        if args.relaxation is None
        else args.relaxation
    )
    anderson = 0 if args.anderson is None else args.anderson
    if args.params is not None:
        from ..io.params_file import read_params, tuned_for_warning

        running = {
            "formulation": args.formulation,
            "anderson": anderson,
            "relaxation": relaxation,
            "rho_scale": list(scales),
            "dtype": "float32" if args.float32 else "float64",
        }
        line = tuned_for_warning(args.params, read_params(args.params), running)
        if line is not None:
            print(f"ampc: warning: {line}", file=sys.stderr)
    try:
        with warnings_as_lines():
            problem = Problem.from_json(path)
        T = problem.topology
        dtype = jnp.float32 if args.float32 else jnp.float64
        data = problem.data(dtype)
        tol = args.tol
        compile_s = 0.0
        solver: Any = None
        form: Any = None  # the formulation (solver, unless a learned start wraps it)
        if info.decomposed or args.solver == "jax":
            if not info.state_file and args.warm_start:
                return fail(f"--warm-start: applies to --formulation {with_file} only")
            if info.rho == "one" and len(scales) != 1:
                return fail("--rho-scale: the integrated problem has one objective; give one value")
            # the formulation's own defaults (Local Explicit: eq.opt_ro's rho* and the
            # exact finish) unless a flag says otherwise
            extra: dict[str, Any] = {} if args.rho is None else {"rho_method": "given"}
            if args.finish is not None:
                if "finish" not in formulation_options(args.formulation):
                    return fail(f"--finish: --formulation {args.formulation} has no exact finish")
                extra["finish"] = args.finish
            try:
                form = solver = formulation(
                    args.formulation, T, max_iter=max_iter, anderson=anderson, **extra
                )
            except ProblemError as e:  # the topology does not suit the formulation
                return fail(f"{path}: {e}")
            if file_start is not None and info.learned_start:
                from ..admm.learned_start import LearnedStart

                try:
                    solver = LearnedStart(solver, file_start)
                    jax.eval_shape(solver.setup, data)  # its inputs fit this problem
                except ValueError as e:
                    return fail(f"--params {args.params}: {e}")
            elif file_start is not None:
                starts = " or ".join(
                    formulation_info(n).label for n in formulation_names(learned_start=True)
                )
                print(
                    f"ampc: --params {args.params}: warm_start ignored by --formulation "
                    f"{args.formulation} (it starts {starts})",
                    file=sys.stderr,
                )
            try:
                params = solver.params(
                    rho=scales if args.rho is None else args.rho,
                    relaxation=relaxation,
                    tol_primal=tol,
                    tol_dual=tol,
                    tol_rel=args.tol_rel,
                    dtype=dtype,
                )
            except ValueError as e:  # rho comes from --rho, or --rho-scale when auto
                rho_flag = "--rho" if args.rho is not None else "--rho-scale"
                return fail(flag_error(e, {**_FLAGS, "rho": rho_flag}))
            if args.rho is None:
                check = problem.data(_check_dtype(args))
                if info.decomposed:  # their automatic rho needs H_j^-1
                    _check_definite_hessians(T, check)
                else:
                    _check_definite_hessians(merged_topology(T), merged_data(check))
            warm = _warm_state(args.warm_start, form, dtype) if args.warm_start else None
            fn = jax.jit(solver.solve)
            t0 = time.perf_counter()
            compiled = fn.lower(data, params, warm).compile()
            compile_s = time.perf_counter() - t0
            res, solve_s = _timed(compiled, data, params, warm)
            names = (
                T.objective_names if info.rho == "objective" else merged_topology(T).objective_names
            )
            rho_out = {n: float(r) for n, r in zip(names, np.asarray(res.rho), strict=True)}
        else:
            if args.warm_start:
                return fail(f"--warm-start: applies to --formulation {with_file} only")
            res = solve_reference(T, data, args.solver or "clarabel", eps=min(tol, 1e-6))
            solve_s = float(res.stats.solve_time)
            rho_out = {}
    except ProblemError as exc:
        return fail(f"{path}: {exc}")
    except ValueError as exc:
        return fail(str(exc))

    per_agent = res.per_agent(T)
    u = np.asarray(res.u)
    out: dict[str, Any] = {
        "formulation": args.formulation,
        "u0": {k: v[0].tolist() for k, v in per_agent.items()},
        "u": {k: v.tolist() for k, v in per_agent.items()},
        "iterations": int(res.iterations),
        "converged": bool(res.converged),
        "status": status_name(res.status),
        "primal_residual": float(np.max(np.asarray(res.primal_residual))),
        "dual_residual": float(np.max(np.asarray(res.dual_residual))),
        "rho": rho_out,
        "gap": _gap_of(res),
        "error_bound": None,
        "solve_time_s": solve_s,
        "compile_time_s": compile_s,
    }
    cert = res.certificate
    if cert is not None and bool(cert.infeasible):
        out["certificate"] = {
            "step": int(cert.step),
            "y": np.asarray(cert.y).tolist(),
            "Ain_t_y_inf_norm": float(cert.Aty),
            "b_t_y": float(cert.bty),
        }
        print(
            f"ampc: the constraint set is empty at prediction step {int(cert.step)}: "
            f"y >= 0 with ||A_in' y||_inf = {float(cert.Aty):.2g} and b' y = "
            f"{float(cert.bty):.3g} < 0 (the certificate is in the JSON output)",
            file=sys.stderr,
        )
    if info.state_file and form is not None:
        st = res.state
        out["warm_state"] = {
            "U": [np.asarray(x).tolist() for x in form.local_inputs(st)],
            "Z": np.asarray(st.Z).tolist(),
            "gamma": [np.asarray(x).tolist() for x in form.multipliers(st)],
        }
    ok = usable(int(res.status)) and bool(np.all(np.isfinite(u)))
    violation = _violation(data, u) if ok else float("nan")
    out["constraint_violation"] = violation
    if ok and out["gap"] is not None:
        if info.decomposed and not _separable(T, data):
            print(
                "ampc: the objectives' agent groups leave out agents that move their "
                "outputs: the gap bounds the distance to the decomposed problem's optimum, "
                "not the integrated one (no error_bound)",
                file=sys.stderr,
            )
        else:
            out["error_bound"] = _error_bound(T, data, out["gap"], violation)
    at_cap = int(res.status) == Status.MAX_ITER_REACHED
    if ok and at_cap and violation > _violation_limit(args.tol):
        # the last iterate of an unconverged ADMM run that breaks a general row is no
        # input to apply; persistently so is what an infeasible problem looks like
        print(
            f"ampc: stopped at --max-iter {max_iter} with inputs that violate a "
            f"constraint row by {violation:.3g} (primal residual "
            f"{out['primal_residual']:.3g}): the problem may be infeasible "
            f"(--formulation integrated checks), or needs more iterations",
            file=sys.stderr,
        )
        ok = False
    elif ok and at_cap:
        print(
            f"ampc: not converged: stopped at --max-iter {max_iter} with primal "
            f"residual {out['primal_residual']:.3g}, dual {out['dual_residual']:.3g} "
            f"(tolerance {args.tol:g}); u is the last iterate, projected on the bounds",
            file=sys.stderr,
        )
    if not ok:
        # never print a number that is not a solution (an infeasibility
        # certificate, a NaN marker read as a value) as an input
        out["u0"] = {k: None for k in per_agent}
        out["u"] = {k: None for k in per_agent}
        print(
            f"ampc: no solution ({status_name(res.status)}); u and u0 are null: "
            f"{status_message(res.status)}",
            file=sys.stderr,
        )
    out = _finite_or_none(out)  # strict JSON: any NaN or inf left becomes null
    if args.json:
        print(json.dumps(out, allow_nan=False))
    else:
        _print_table(out, T)
    return 0 if ok else 1


def _gap_of(res: Any) -> float | None:
    """The result's duality gap (``stats.gap``), or None where it has none."""
    stats = res.stats
    if stats is None or stats.gap is None:
        return None
    return float(max(float(stats.gap), 0.0))  # a gap is >= 0; below is round-off


def _error_bound(T: Any, data: Any, gap: float, violation: float) -> float | None:
    """||U - U*|| <= sqrt(2 gap / lambda_min(H)) (H the integrated Hessian): the
    distance to the optimum that ``gap`` bounds, for inputs that satisfy every
    row (None when they violate one: the bound then needs the optimum's
    multipliers)."""
    if not (violation <= 0.0 and np.isfinite(gap)):
        return None
    from ..problem import condensed_qp

    H = np.asarray(condensed_qp(T, data).H, dtype=float)
    low = float(np.linalg.eigvalsh(0.5 * (H + H.T))[0])
    return float(np.sqrt(2.0 * gap / low)) if low > 0 else None


def _separable(T: Any, data: Any) -> bool:
    """Whether the objectives' local costs add up to the integrated cost (every
    agent that moves O_j's outputs is in S_j), the premise of reading the gap
    of a decomposed formulation as a distance to the integrated optimum."""
    from ..admm.costs import local_costs
    from ..problem import condensed_qp

    qp = condensed_qp(T, data)
    H_int, E_int = np.asarray(qp.H, float), np.asarray(qp.E, float)
    H, E = np.zeros_like(H_int), np.zeros_like(E_int)
    Hs, Es = local_costs(T, data)
    for j in range(T.n_objectives):
        cols = np.asarray(T.group_columns(j))
        idx = (np.arange(T.horizon)[:, None] * T.n_u + cols[None, :]).ravel()
        H[np.ix_(idx, idx)] += np.asarray(Hs[j], float)
        E[idx] += np.asarray(Es[j], float)
    scale = max(float(np.max(np.abs(H_int))), 1.0)
    return bool(
        np.allclose(H, H_int, rtol=1e-9, atol=1e-12 * scale)
        and np.allclose(E, E_int, rtol=1e-9, atol=1e-12 * max(float(np.max(np.abs(E_int))), 1.0))
    )


def _violation_limit(tol: float) -> float:
    """Largest violation of a constraint row (A_in U^(k) - b_in^(k), in the rows'
    units) of a result stopped at ``--max-iter`` that is still printed as inputs:
    10 sqrt(tol), since a result that converged at ``tol`` (squared residual
    norms) may break a row by up to sqrt(tol); at least 1e-6."""
    return max(1e-6, 10.0 * float(np.sqrt(tol)))


def _violation(data: Any, u: np.ndarray) -> float:
    """max(0, max_k,c (A_in U^(k) - b_in^(k))_c): how far inputs u (N_p, n_u)
    break the constraint rows (all of them; the box rows hold after the
    projection on the bounds, so in practice the general rows decide)."""
    Ain = np.asarray(data.Ain, dtype=float)
    if Ain.shape[0] == 0:
        return 0.0
    excess = np.asarray(u, float) @ Ain.T - np.asarray(data.bin, float)
    return float(max(0.0, np.max(excess)))


def _check_dtype(args: argparse.Namespace) -> Any:
    """float64 for the singular-Hessian check, unless --float32 (x64 off: asking
    for float64 would only warn and give float32)."""
    import jax.numpy as jnp

    return jnp.float32 if args.float32 else jnp.float64


def _check_definite_hessians(T: Any, data: Any) -> None:
    """Refuse a singular H_j (:func:`~ampc_jax.admm.costs.singular_hessians`)
    naming the objective; ``--rho VALUE`` skips the check."""
    from ..admm.costs import singular_hessians

    for j, low, high in singular_hessians(T, data):
        name = f"objectives[{j}] ({T.objective_names[j]})"
        if low <= 1e-14 * high:
            raise ValueError(
                f"{name}: its Hessian H_j is singular (smallest eigenvalue {low:.3g}, "
                f"largest {high:.3g}): some input direction costs nothing in it (R_(i) "
                f"singular and Q_j blind to it), so the automatic rho (eq.opt_ro's rho*, or "
                f"sqrt(lambda_min lambda_max) for Formulations 1 and 2) is undefined; give "
                f"--rho VALUE, or positive weights"
            )
        raise ValueError(
            f"{name}: its Hessian H_j is numerically singular (condition number "
            f"{high / low:.3g} > 1e12; eigenvalues {low:.3g} to {high:.3g}), so the automatic "
            f"rho (which needs H_j^-1) is unreliable; weights Q_j and R_(i) spanning "
            f"about 12 orders of magnitude do this: rescale them, or give --rho VALUE"
        )


def _finite_or_none(x: Any) -> Any:
    """``x`` with every non-finite float (in dicts and lists) replaced by None."""
    if isinstance(x, dict):
        return {k: _finite_or_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite_or_none(v) for v in x]
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


def _print_table(out: dict[str, Any], T: Any) -> None:
    print(f"formulation  {out['formulation']}")
    print(
        f"status       {out['status']} after {out['iterations']} iterations "
        f"(converged: {out['converged']})"
    )

    def num(v: Any) -> str:
        return "n/a" if v is None else f"{v:.3g}"

    print(f"residuals    primal {num(out['primal_residual'])}  dual {num(out['dual_residual'])}")
    if out.get("gap") is not None:
        bound = out.get("error_bound")
        within = (
            ""
            if bound is None
            else f"  (inputs within {num(bound)} of the optimum: the 2-norm over every agent's "
            "inputs and every step of the horizon, in the inputs' own units)"
        )
        print(f"gap          {num(out['gap'])}{within}")
    if out["rho"]:
        print("rho          " + "  ".join(f"{k}={num(v)}" for k, v in out["rho"].items()))
    print(
        f"solve time   {out['solve_time_s'] * 1e3:.3f} ms (compile {out['compile_time_s']:.2f} s)"
    )
    print()
    width = max(len(n) for n in T.agent_names)
    print(f"{'agent':<{width}}  first-step inputs U^(0)")
    for name, vals in out["u0"].items():
        text = "  ".join(f"{v:12.5g}" for v in vals) if vals is not None else "no solution"
        print(f"{name:<{width}}  {text}")


def add_solve_command(sub: Any) -> None:
    """Register ``ampc solve`` on the ``ampc`` sub-parsers."""
    from ..formulations import DEFAULT_FORMULATION, formulation_names

    p = sub.add_parser(
        "solve",
        help="solve one MPC step of a JSON problem file",
        description="Solve one MPC step of a problem file (JSON) or a shipped example.",
    )
    p.add_argument(
        "problem",
        help="problem file (JSON; format in the README), or the name of a shipped "
        "example (cruise_control)",
    )
    p.add_argument(
        "--formulation",
        choices=list(formulation_names()),
        default=DEFAULT_FORMULATION,
        help="Local Explicit (the paper's Formulation 3), Fully Distributed (Formulation "
        "1), Virtual Center Node (Formulation 2), or the integrated MPC "
        "(default: local_explicit)",
    )
    p.add_argument(
        "--solver",
        choices=["clarabel", "osqp", "jax"],
        default=None,
        help="the integrated formulation's solver: Clarabel or OSQP (references), or "
        "jax (the same explicit ADMM on the undecomposed problem) (default: clarabel)",
    )
    p.add_argument(
        "--rho",
        type=_parse_rho,
        default=None,
        metavar="auto|VALUE",
        help="ADMM penalty: 'auto' for Ghadimi's optimal rho (paper eq. opt_ro; for "
        "Formulations 1 and 2 sqrt(lambda_min lambda_max) of each objective's Hessian), "
        "or a value used for every objective as it is (default: auto)",
    )
    p.add_argument(
        "--rho-scale",
        type=_scales,
        default=None,
        metavar="S[,S...]",
        help="factor(s) on the 'auto' rho: one value, or one per "
        "objective comma-separated (default: 1)",
    )
    add_solver_flags(
        p,
        relaxation="ADMM over-relaxation alpha in (0, 2); 1 is the paper's iteration (default: 1)",
        anderson="Anderson acceleration memory of the ADMM iteration; 0 is the paper's "
        "plain iteration (default: 0)",
        max_iter=f"iteration cap (default: {MAX_ITER_DEFAULT})",
        finish="the exact finish of a decomposed formulation that has one (Local Explicit): "
        "active_set (the ADMM iterate's active set solved exactly and KKT-checked) or none "
        "(the paper's iteration alone) (default: active_set)",
    )
    add_params_flag(
        p,
        "a tuned-parameters file (ampc tune's params.json): its solver.rho_scale and "
        "solver.relaxation are used; --rho-scale and --relaxation given here win over it "
        "(default: none)",
    )
    p.add_argument(
        "--tol",
        type=arg_type(positive_finite),
        default=TOL_DEFAULT,
        help="eps_r = eps_s of the stopping rule (paper eq. Convergence), absolute, on "
        f"squared residual norms in the constraint rows' units (default: {TOL_DEFAULT:g})",
    )
    p.add_argument(
        "--tol-rel",
        type=arg_type(non_negative_finite),
        default=0.0,
        help="relative tolerance eps_rel of the stopping rule (after OSQP): a residual "
        "may also be eps_rel times the size of the iterate and right-hand sides it "
        "compares; the result's duality gap (JSON 'gap', 'error_bound') says how close "
        "the inputs are (default: 0, the absolute rule alone)",
    )
    p.add_argument(
        "--warm-start",
        metavar="FILE",
        default=None,
        help="a previous --json result of this problem to shift one step and start "
        "from (default: cold start)",
    )
    add_output_flags(p, float32="solve")
    p.add_argument("--json", action="store_true", help="print one JSON object (default: a table)")
    p.set_defaults(func=cmd_solve)
