"""The tuned-parameters file: solver numbers and example settings, as JSON.

Format ``ampc-params/1``::

    {
      "format": "ampc-params/1",
      "example": "cruise" | null,
      "formulation": "local_explicit",
      "solver": {"rho_scale": [f_1, ..., f_J] | f | null, "relaxation": alpha | null},
      "settings": {"q_yrt": 1.0, ...},          (optional: the example's weights)
      "warm_start": {"kind": "step", "layers": [{"W": [[...]], "b": [...]}, ...], ...},
                                                (optional: a learned start network)
      "tuned_for": {"anderson": 3, "relaxation": 1.5, ...},
                                                (optional: the solver settings it was tuned under)
      "provenance": {...}                       (optional: how it was made)
    }

``rho_scale`` is the factor on eq.opt_ro's rho_j* per objective (one number for
every objective, or one per objective of the example in its order);
``relaxation`` is the over-relaxation alpha in (0, 2). A ``null`` (or missing)
entry leaves the default in place. ``settings`` replaces fields of the
example's settings (weights and bounds, by name). ``warm_start`` is a trained
:class:`~ampc_jax.admm.learned_start.StartModel`
(:func:`~ampc_jax.admm.learned_start.model_document`: its arrays as JSON lists),
validated on reading. ``tuned_for`` records the solver settings the numbers were
tuned under (``anderson``, ``relaxation``, ``rho_scale``, ``kkt``, ``dtype``,
``tol``, ``formulation``): a command applying the file under other settings
warns (:func:`tuned_for_differences`).

Bounds, each with its reason in the refusal: ``rho_scale`` within
[1e-6, 1e6] (:data:`RHO_SCALE_RANGE`); every numeric setting within a factor
1e6 of the example's default (:data:`SETTINGS_FACTOR`; 0 where the field
allows it); ``horizon`` at most 10 s of prediction (:data:`PREDICTION_MAX_S`). ``ampc simulate``, ``ampc
solve``, ``ampc run`` and ``ampc export`` read it with ``--params FILE``.
Every field is validated on reading (ValueError naming the field).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

from ..validation import check_relaxation

__all__ = [
    "PARAMS_FORMAT",
    "PREDICTION_MAX_S",
    "RHO_SCALE_RANGE",
    "SETTINGS_FACTOR",
    "TunedParams",
    "apply_params",
    "check_settings_bounds",
    "read_params",
    "validate_params",
    "tuned_for_differences",
    "tuned_for_warning",
    "write_params",
]

PARAMS_FORMAT = "ampc-params/1"
"""The ``format`` tag of a tuned-parameters file."""

RHO_SCALE_RANGE = (1e-6, 1e6)
"""The factors on eq.opt_ro's rho_j* a file may hold. Reason: rho_j* =
sqrt(lambda_min lambda_max) / 2 of H_j, so beyond 1e6 either way one of rho_j I
and H_j is under 1e-6 of the other in the local step's K_j = H_j + rho_j I
(well-conditioned H_j), a few float32 ulps (eps 1.2e-7): the step ignores its
objective (too large: a 'converged' first iterate far from the optimum, as
1e308 gave) or the consensus (too small: no iteration cap is reached)."""

SETTINGS_FACTOR = 1e6
"""How far a numeric setting may move from the example's default, either way.
Reason: the examples' weights are scaled so a unit tracking error or a
full-range torque costs about 1 (R_(i) = 1/T_max^2); a factor f moves the
conditioning of H_j by up to f, and beyond 1e6 that is past what float32
(eps 1.2e-7) resolves; a torque bound 1e6 times the actuator's is no actuator."""

PREDICTION_MAX_S = 10.0
"""Longest prediction, N_p dt in seconds. Reason: the examples' models are
linearised at the current operating point (eq.CC_system, eq.VSC_system), which
a vehicle leaves within seconds, and the condensed forms grow as N_p^3
(:func:`~ampc_jax.problem.limits.condensed_bytes`)."""

_KEYS = (
    "format",
    "example",
    "formulation",
    "solver",
    "settings",
    "warm_start",
    "tuned_for",
    "provenance",
)
TUNED_FOR_KEYS = ("formulation", "anderson", "relaxation", "rho_scale", "kkt", "dtype", "tol")
"""What ``tuned_for`` may record: the solver settings tuning ran under."""


class TunedParams(NamedTuple):
    """The contents of a tuned-parameters file (``None``: not given, the default stays).

    example : the vehicle example the numbers were tuned for, or None (any problem).
    formulation : the formulation they are for (default ``"local_explicit"``).
    rho_scale : factor on eq.opt_ro's rho_j*: a float or a tuple, one per objective.
    relaxation : over-relaxation alpha in (0, 2).
    settings : the example's settings fields to replace (name -> number or numbers).
    provenance : free-form record of how the numbers were found.
    warm_start : a learned start (:class:`~ampc_jax.admm.learned_start.StartModel`).
    tuned_for : the solver settings the numbers were tuned under (:data:`TUNED_FOR_KEYS`).
    """

    example: str | None = None
    formulation: str = "local_explicit"
    rho_scale: float | tuple[float, ...] | None = None
    relaxation: float | None = None
    settings: dict[str, Any] | None = None
    provenance: dict[str, Any] | None = None
    warm_start: Any = None
    tuned_for: dict[str, Any] | None = None


def _show(value: Any, width: int = 80) -> str:
    """``repr(value)`` cut to ``width``; safe for integers beyond Python's
    4,300-digit limit and for nesting past the recursion limit."""
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        return f"<a {type(value).__name__} too large to print>"
    return text if len(text) <= width else text[: width - 3] + "..."


_NAME = re.compile(r"[A-Za-z_]\w{0,63}")
"""A field name as the messages print it (a key otherwise is shown quoted)."""


def _field(key: Any, parent: str = "") -> str:
    """``parent.key`` for a plain name; ``parent`` (or ``params``) and the key quoted
    for anything else (an unknown key is the user's text)."""
    if isinstance(key, str) and _NAME.fullmatch(key):
        return f"{parent}.{key}" if parent else key
    return f"{parent or 'params'}: {_show(key, 60)}"


def _number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name}: expected a number, got {_show(value)}")
    try:
        v = float(value)
    except OverflowError:
        raise ValueError(
            f"{name}: expected a finite number, got an integer beyond float64's range"
        ) from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    return v


def _rho_scale(value: Any) -> float | tuple[float, ...] | None:
    name = "solver.rho_scale"
    if value is None:
        return None
    if hasattr(value, "tolist"):  # numpy / jax arrays
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        if not value:
            raise ValueError(f"{name}: expected a number or a non-empty list, got []")
        vals = tuple(_number(f"{name}[{k}]", v) for k, v in enumerate(value))
    else:
        vals = (_number(name, value),)
    lo, hi = RHO_SCALE_RANGE
    for k, v in enumerate(vals):
        where = name if not isinstance(value, (list, tuple)) else f"{name}[{k}]"
        if v <= 0:
            raise ValueError(f"{where}: expected a positive number, got {v!r}")
        if not lo <= v <= hi:
            raise ValueError(
                f"{where}: expected a factor in [{lo:.0e}, {hi:.0e}] on eq.opt_ro's rho_j*, "
                f"got {v:.3g}: beyond 1e6 either way one of rho_j I and H_j is under 1e-6 of "
                f"the other in the local step (a few float32 ulps, eps 1.2e-7), so the step "
                f"ignores its objective and stops at once far from the optimum (too large) or "
                f"ignores the consensus and never converges (too small)"
            )
    return vals[0] if not isinstance(value, (list, tuple)) else vals


def _relaxation(value: Any) -> float | None:
    if value is None:
        return None
    if hasattr(value, "item"):
        value = value.item()
    return check_relaxation(_number("solver.relaxation", value), "solver.relaxation")


def _settings(value: Any) -> dict[str, Any] | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise ValueError(f"settings: expected an object (name -> number), got {_show(value)}")
    out: dict[str, Any] = {}
    for key, v in value.items():
        if not isinstance(key, str) or not _NAME.fullmatch(key):
            raise ValueError(f"settings: expected field names, got {_show(key)}")
        name = f"settings.{key}"
        if hasattr(v, "tolist"):
            v = v.tolist()
        if isinstance(v, (list, tuple)):
            out[key] = [_number(f"{name}[{k}]", x) for k, x in enumerate(v)]
        else:
            out[key] = _number(name, v)
    return out


def validate_params(doc: Any) -> TunedParams:
    """A :class:`TunedParams` from a decoded file ``doc`` (ValueError naming the field)."""
    if not isinstance(doc, Mapping):
        raise ValueError(f"params: expected a JSON object, got {type(doc).__name__}")
    unknown = sorted((k for k in doc if k not in _KEYS), key=str)
    if unknown:
        raise ValueError(f"{_field(unknown[0])}: unknown field; expected only {list(_KEYS)}")
    if doc.get("format") != PARAMS_FORMAT:
        raise ValueError(f"format: expected {PARAMS_FORMAT!r}, got {_show(doc.get('format'))}")
    ex = doc.get("example")
    if ex is not None and (not isinstance(ex, str) or not ex):
        raise ValueError(f"example: expected an example name or null, got {_show(ex)}")
    from ..closed_loop.config import NO_MPC
    from ..formulations import DEFAULT_FORMULATION, formulation_names

    form = doc.get("formulation", DEFAULT_FORMULATION)
    names = [*formulation_names(), NO_MPC]
    if form not in names:
        raise ValueError(f"formulation: expected one of {names}, got {_show(form)}")
    solver = doc.get("solver", {})
    if solver is None:
        solver = {}
    if not isinstance(solver, Mapping):
        raise ValueError(f"solver: expected an object, got {_show(solver)}")
    extra = sorted((k for k in solver if k not in ("rho_scale", "relaxation")), key=str)
    if extra:
        raise ValueError(
            f"{_field(extra[0], 'solver')}: unknown field; expected rho_scale, relaxation"
        )
    prov = doc.get("provenance")
    if prov is not None and not isinstance(prov, Mapping):
        raise ValueError(f"provenance: expected an object, got {_show(prov)}")
    ws = doc.get("warm_start")
    if ws is not None:
        from ..admm.learned_start import StartModel, model_from_document

        if not isinstance(ws, StartModel):
            ws = model_from_document(ws, "warm_start")
    return TunedParams(
        example=ex,
        formulation=form,
        rho_scale=_rho_scale(solver.get("rho_scale")),
        relaxation=_relaxation(solver.get("relaxation")),
        settings=_settings(doc.get("settings")),
        provenance=None if prov is None else dict(prov),
        warm_start=ws,
        tuned_for=_tuned_for(doc.get("tuned_for")),
    )


def _tuned_for(value: Any) -> dict[str, Any] | None:
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise ValueError(f"tuned_for: expected an object, got {_show(value)}")
    out: dict[str, Any] = {}
    for key, v in value.items():
        if key not in TUNED_FOR_KEYS:
            raise ValueError(
                f"{_field(key, 'tuned_for')}: unknown field; expected {list(TUNED_FOR_KEYS)}"
            )
        name = f"tuned_for.{key}"
        if key in ("formulation", "kkt", "dtype"):
            if not isinstance(v, str):
                raise ValueError(f"{name}: expected a name, got {_show(v)}")
            out[key] = v
        elif key == "anderson":
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"{name}: expected an integer >= 0, got {_show(v)}")
            out[key] = v
        elif key == "rho_scale":
            rs = _rho_scale(v)
            out[key] = list(rs) if isinstance(rs, tuple) else rs
        else:
            out[key] = _number(name, v)
    return out


def tuned_for_differences(tuned: TunedParams, running: Mapping[str, Any]) -> list[str]:
    """``name: tuned X, running Y`` for every setting of ``tuned.tuned_for`` that
    ``running`` (the command's solver settings, same keys) gives otherwise;
    rho scales and relaxation compare to 1e-9 relative."""
    if not tuned.tuned_for:
        return []
    out = []
    for key, want in tuned.tuned_for.items():
        if key not in running or running[key] is None:
            continue
        have = running[key]
        if key in ("rho_scale", "relaxation", "tol"):
            a = [float(x) for x in (want if isinstance(want, list) else [want])]
            b = [float(x) for x in (have if isinstance(have, (list, tuple)) else [have])]
            if len(a) == 1:
                a = a * len(b)
            if len(b) == 1:
                b = b * len(a)
            same = len(a) == len(b) and all(
                abs(x - y) <= 1e-9 * max(abs(x), abs(y)) for x, y in zip(a, b, strict=True)
            )
        else:
            same = want == have
        if not same:
            out.append(f"{key}: tuned {want}, running {_plain_value(have)}")
    return out


def tuned_for_warning(path: Any, tuned: TunedParams, running: Mapping[str, Any]) -> str | None:
    """The one warning line for a file tuned under other solver settings than the
    command's ``running`` ones (:func:`tuned_for_differences`), or None."""
    diff = tuned_for_differences(tuned, running)
    if not diff:
        return None
    return (
        f"--params {path} was tuned for other solver settings than this command runs "
        f"({'; '.join(diff)}): its numbers may not pay off here"
    )


def _plain_value(v: Any) -> Any:
    if isinstance(v, tuple):
        return [float(x) for x in v]
    return v


def params_document(params: TunedParams) -> dict[str, Any]:
    """The JSON document of ``params`` (validated)."""
    rs = params.rho_scale
    doc: dict[str, Any] = {
        "format": PARAMS_FORMAT,
        "example": params.example,
        "formulation": params.formulation,
        "solver": {
            "rho_scale": list(rs) if isinstance(rs, (tuple, list)) else rs,
            "relaxation": params.relaxation,
        },
    }
    if params.settings is not None:
        doc["settings"] = dict(params.settings)
    if params.warm_start is not None:
        from ..admm.learned_start import model_document

        doc["warm_start"] = model_document(params.warm_start)
    if params.tuned_for is not None:
        doc["tuned_for"] = dict(params.tuned_for)
    if params.provenance is not None:
        doc["provenance"] = dict(params.provenance)
    validate_params(doc)
    return doc


def write_params(
    path: str | Path,
    *,
    example: str | None = None,
    formulation: str = "local_explicit",
    rho_scale: Any = None,
    relaxation: Any = None,
    settings: Mapping[str, Any] | None = None,
    provenance: Mapping[str, Any] | None = None,
    warm_start: Any = None,
    tuned_for: Mapping[str, Any] | None = None,
) -> TunedParams:
    """Write a tuned-parameters file at ``path``; returns what was written.

    ``rho_scale``: a float or one per objective (arrays accepted); ``relaxation``
    in (0, 2); ``settings``: example settings fields by name; ``provenance``:
    any JSON-serialisable record; ``warm_start``: a
    :class:`~ampc_jax.admm.learned_start.StartModel`; ``tuned_for``: the solver
    settings it was tuned under (:data:`TUNED_FOR_KEYS`). ValueError naming the
    field on a bad value (nothing is written then).
    """
    doc = {
        "format": PARAMS_FORMAT,
        "example": example,
        "formulation": formulation,
        "solver": {"rho_scale": rho_scale, "relaxation": relaxation},
        "settings": None if settings is None else dict(settings),
        "provenance": None if provenance is None else dict(provenance),
        "warm_start": warm_start,
        "tuned_for": None if tuned_for is None else dict(tuned_for),
    }
    tuned = validate_params(doc)
    full = params_document(tuned)
    ws = full.pop("warm_start", None)
    text = json.dumps(full, indent=2, default=_jsonable)
    if ws is not None:  # the network's arrays on one line: thousands of numbers
        text = text[: text.rindex("}")].rstrip() + ',\n  "warm_start": ' + json.dumps(ws) + "\n}"
    text += "\n"
    Path(path).write_text(text)
    return tuned


def read_params(path: str | Path) -> TunedParams:
    """Read and validate a tuned-parameters file (ValueError naming the field;
    ``params: cannot read ...`` when the file is missing or not JSON)."""
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ValueError(f"params: cannot read {path} ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"params: {path} is not UTF-8 text ({exc.reason})") from None
    try:
        doc = json.loads(text)
    except RecursionError:
        raise ValueError(
            f"params: {path} nests lists or objects deeper than a JSON reader follows "
            f"(a field is a number, a list of numbers or an object of them)"
        ) from None
    except ValueError as exc:  # JSONDecodeError, or an integer of over 4,300 digits
        raise ValueError(f"params: {path} is not JSON ({exc})") from None
    return validate_params(doc)


def apply_params(config: Any, tuned: TunedParams, *, keep: tuple[str, ...] = ()) -> Any:
    """``config`` (a :class:`~ampc_jax.closed_loop.SimConfig`) with the file's numbers.

    ``rho_scale`` and ``relaxation`` replace the config's unless named in ``keep``
    (what the caller set explicitly, which wins); ``settings`` replace fields of
    the example's settings (an integer or boolean field takes an integral
    number or 0/1). ValueError naming the field when the file was tuned for
    another example, or a value does not fit.
    """
    from dataclasses import replace

    if tuned.example is not None and tuned.example != config.example:
        raise ValueError(
            f"example: the file was tuned for the {tuned.example} example, not {config.example}"
        )
    changes: dict[str, Any] = {}
    if tuned.rho_scale is not None and "rho_scale" not in keep:
        changes["rho_scale"] = tuned.rho_scale
    if tuned.relaxation is not None and "relaxation" not in keep:
        changes["relaxation"] = tuned.relaxation
    try:
        out = replace(config, **changes) if changes else config
    except ValueError as exc:
        raise ValueError(f"solver.{exc}") from None
    if tuned.settings:
        out = _apply_settings(out, tuned, config.example)
    if tuned.warm_start is not None and "warm_start" not in keep:
        out = _apply_warm_start(out, tuned.warm_start)
    return out


def _apply_warm_start(config: Any, model: Any) -> Any:
    """``config`` started by ``model`` (ValueError ``warm_start: ...`` when it
    does not fit the configuration's formulation or problem)."""
    from dataclasses import replace

    from ..closed_loop.controller import controller_for
    from ..formulations import formulation_names

    if not config.mpc or not config.formulation_info.learned_start:
        raise ValueError(
            f"warm_start: the start network is for {' or '.join(formulation_names(learned_start=True))}, "
            f"not formulation {config.formulation!r}"
        )
    try:
        out = replace(config, learned_start=model)
        controller_for(out)
    except ValueError as exc:
        raise ValueError(f"warm_start: {exc}") from None
    return out


def _apply_settings(config: Any, tuned: TunedParams, example_name: str) -> Any:
    from dataclasses import replace

    out = config
    settings = out.settings
    fields: dict[str, Any] = {}
    for key, value in tuned.settings.items():
        if key not in settings.field_names():
            raise ValueError(
                f"settings.{key}: not a field of the {config.example} example's settings "
                f"(fields: {', '.join(settings.field_names())})"
            )
        kind = type(getattr(settings, key))
        if kind in (bool, int) and not isinstance(value, list):
            if float(value) != int(value):
                raise ValueError(f"settings.{key}: expected an integer, got {value!r}")
            value = kind(int(value))
        fields[key] = value
    check_settings_bounds(settings, fields, config.example)
    try:
        new = settings.replace(**fields)
        new.validate()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"settings.{exc}") from None
    return replace(out, settings=new)


def check_settings_bounds(settings: Any, fields: dict[str, Any], example: str) -> None:
    """ValueError naming ``settings.<field>`` for a value outside its bound, with
    the reason: numbers within :data:`SETTINGS_FACTOR` of the example's default
    (0 stays allowed: the example's own validation says where), the horizon
    within :data:`PREDICTION_MAX_S` of prediction."""
    default = type(settings)()
    dt = float(fields.get("dt", settings.dt))
    for key, value in fields.items():
        base = getattr(default, key)
        if isinstance(value, list) or isinstance(base, bool) or not isinstance(value, (int, float)):
            continue  # the example's validation names a wrong kind
        if key == "horizon":
            steps = int(PREDICTION_MAX_S / dt) if dt > 0 else 0
            if value > steps:
                raise ValueError(
                    f"settings.horizon: expected N_p with N_p dt <= {PREDICTION_MAX_S:g} s "
                    f"({steps} steps of {dt:g} s), got {_show(value)}: the {example} example's "
                    f"model is linearised at the current operating point, so a longer "
                    f"prediction means nothing, and the condensed forms grow as N_p^3"
                )
            continue
        base = float(base)
        if value == 0 or base == 0 or not math.isfinite(float(value)):
            continue
        if not base / SETTINGS_FACTOR <= abs(float(value)) <= base * SETTINGS_FACTOR:
            raise ValueError(
                f"settings.{key}: expected a value within a factor {SETTINGS_FACTOR:.0e} of "
                f"the {example} example's {base:.3g}, got {float(value):.3g}: its weights are "
                f"scaled so a unit error or a full-range torque costs about 1, a factor beyond "
                f"1e6 moves the conditioning of H_j past what float32 (eps 1.2e-7) resolves, "
                f"and a torque bound beyond it is no actuator"
            )


def _jsonable(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"provenance: {type(value).__name__} is not JSON serialisable")
