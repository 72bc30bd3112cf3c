"""A :class:`~.network.StartModel` as a JSON document (the ``warm_start`` entry of a
tuned-parameters file): written by :func:`model_document`, read and validated
field by field by :func:`model_from_document`."""

from __future__ import annotations

from typing import Any

import numpy as np

from .network import StartModel

__all__ = ["model_document", "model_from_document"]

_ARRAY_FIELDS = (
    ("input_mean", 1),
    ("input_scale", 1),
    ("out_mean", 1),
    ("out_scale", 1),
    ("out_mask", 1),
    ("schedule_rho", 2),
    ("schedule_relaxation", 1),
)
_DOC_KEYS = ("kind", "layers", *(k for k, _ in _ARRAY_FIELDS), "n_point", "objectives", "horizon")


def model_document(model: StartModel) -> dict[str, Any]:
    """``model`` as a JSON-ready object (arrays as nested lists of floats):
    the ``warm_start`` entry of a tuned-parameters file."""
    doc: dict[str, Any] = {
        "kind": model.kind,
        "layers": [{"W": W.tolist(), "b": b.tolist()} for W, b in model.layers],
    }
    for name, _ in _ARRAY_FIELDS:
        doc[name] = getattr(model, name).tolist()
    if model.schedule_length == 0:  # (0, J) has no list form that keeps J
        doc["schedule_rho"] = []
    doc.update(n_point=model.n_point, objectives=list(model.objectives), horizon=model.horizon)
    return doc


def _doc_array(name: str, value: Any, ndim: int) -> np.ndarray:
    def numbers(x: Any) -> bool:
        if isinstance(x, (list, tuple)):
            return all(numbers(y) for y in x)
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    if not isinstance(value, (list, tuple)) or not numbers(value):
        raise ValueError(
            f"{name}: expected a list of numbers ({ndim}-D), got a {type(value).__name__}"
        )
    try:
        a = np.asarray(value, dtype=np.float64)
    except (ValueError, OverflowError):
        raise ValueError(f"{name}: expected a rectangular {ndim}-D list of numbers") from None
    if a.ndim != ndim and not (a.size == 0 and ndim == 2):
        raise ValueError(f"{name}: expected a {ndim}-D list of numbers, got {a.ndim}-D")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite numbers")
    return a


def model_from_document(doc: Any, name: str = "warm_start") -> StartModel:
    """The :class:`StartModel` of a :func:`model_document` object (ValueError naming
    the field, ``warm_start.layers[1].W: ...``)."""
    from collections.abc import Mapping

    if not isinstance(doc, Mapping):
        raise ValueError(f"{name}: expected an object, got a {type(doc).__name__}")
    for key in doc:
        if key not in _DOC_KEYS:
            raise ValueError(f"{name}: unknown field {str(key)[:40]!r}; expected {list(_DOC_KEYS)}")
    for key in _DOC_KEYS:
        if key not in doc:
            raise ValueError(f"{name}.{key}: missing")
    layers = doc["layers"]
    if not isinstance(layers, (list, tuple)) or not layers:
        raise ValueError(f"{name}.layers: expected a non-empty list of {{W, b}} objects")
    parsed = []
    for k, layer in enumerate(layers):
        if not isinstance(layer, Mapping) or set(layer) != {"W", "b"}:
            raise ValueError(f"{name}.layers[{k}]: expected an object with W and b")
        parsed.append(
            (
                _doc_array(f"{name}.layers[{k}].W", layer["W"], 2),
                _doc_array(f"{name}.layers[{k}].b", layer["b"], 1),
            )
        )
    arrays = {k: _doc_array(f"{name}.{k}", doc[k], nd) for k, nd in _ARRAY_FIELDS}
    objectives = doc["objectives"]
    if not isinstance(objectives, (list, tuple)) or not all(isinstance(o, str) for o in objectives):
        raise ValueError(f"{name}.objectives: expected a list of objective names")
    if arrays["schedule_rho"].size == 0:
        arrays["schedule_rho"] = np.zeros((0, len(objectives)))
    for key in ("n_point", "horizon"):
        v = doc[key]
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name}.{key}: expected an integer >= 1, got {str(v)[:40]}")
    try:
        return StartModel(
            kind=doc["kind"],
            layers=tuple(parsed),
            n_point=doc["n_point"],
            objectives=tuple(objectives),
            horizon=doc["horizon"],
            **arrays,
        )
    except ValueError as exc:
        raise ValueError(f"{name}.{exc}") from None
