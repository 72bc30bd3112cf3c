"""The exported controller step: serialized StableHLO plus a manifest (``jax.export``).

An artefact is one zip file:

* ``step.stablehlo`` -- ``jax.export`` of :meth:`RuntimeStep.function`
  (``f(leaves, bus) -> (torques, leaves, report)``), serialized;
* ``manifest.json`` -- the format version, jax and jaxlib versions, the
  calling convention's version, the SHA-256 of ``step.stablehlo``, the hash of
  the controller configuration (:func:`~ampc_jax.runtime.step.config_hash`),
  the scenario and example it was made for, the input and output shapes and
  dtypes, and a golden input/output pair: a cold state and the bus vector of
  the scenario's first step in, every output out.

:func:`load_artefact` refuses (:class:`ArtefactError`, naming what differs) a
file whose step does not hash to the manifest's, a calling convention this jax
cannot run, a configuration other than the one expected, or a golden pair the
deserialized step does not reproduce. Rule: nothing is actuated from an
artefact before all four checks pass; reason: a tampered or stale controller
must not reach the wheels.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from os import PathLike
from typing import Any

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
from jax import export

from .step import RuntimeStep

__all__ = ["ARTEFACT_FORMAT", "Artefact", "ArtefactError", "export_step", "load_artefact"]

ARTEFACT_FORMAT = 1
"""Version of the artefact's layout (``manifest.json["format"]``)."""


class ArtefactError(ValueError):
    """An artefact that must not be run (the message says why)."""


def _spec(x: Any) -> dict[str, Any]:
    return {"shape": list(np.shape(x)), "dtype": str(np.asarray(x).dtype)}


def _tolist(x: Any) -> Any:
    a = np.asarray(x)
    return {"dtype": str(a.dtype), "shape": list(a.shape), "data": a.ravel().tolist()}


def _fromlist(d: dict[str, Any]) -> np.ndarray:
    return np.asarray(d["data"], dtype=d["dtype"]).reshape(d["shape"])


def export_step(
    step: RuntimeStep, golden_bus: np.ndarray, path: str | PathLike[str], *, scenario: str
) -> dict[str, Any]:
    """Export ``step`` with its manifest to ``path`` (a zip); returns the manifest."""
    fn = jax.jit(step.function())
    leaves, bus0 = step.example_args()
    exp = export.export(fn)(leaves, bus0)
    blob = exp.serialize()
    bus = jnp.asarray(golden_bus, step.jnp_dtype)
    out = jax.tree.leaves(exp.call(leaves, bus))
    manifest = {
        "format": ARTEFACT_FORMAT,
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "calling_convention_version": exp.calling_convention_version,
        "platforms": list(exp.platforms),
        "step_sha256": hashlib.sha256(blob).hexdigest(),
        "config_hash": step.config_hash(),
        "scenario": scenario,
        "example": step.config.example,
        "formulation": step.config.formulation,
        "dtype": step.dtype,
        "inputs": {"leaves": [_spec(x) for x in leaves], "bus": _spec(bus0)},
        "outputs": [_spec(x) for x in out],
        "golden": {
            "leaves": [_tolist(x) for x in leaves],
            "bus": _tolist(bus),
            "outputs": [_tolist(x) for x in out],
        },
    }
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("step.stablehlo", blob)
        z.writestr("manifest.json", json.dumps(manifest, indent=1))
    return manifest


class Artefact:
    """A loaded and checked artefact: ``call(leaves, bus)`` runs the step."""

    def __init__(self, exported: Any, manifest: dict[str, Any]) -> None:
        self.exported = exported
        self.manifest = manifest
        self._call = jax.jit(exported.call)

    def init_leaves(self) -> tuple[Any, ...]:
        """The cold state the golden pair starts from."""
        return tuple(jnp.asarray(_fromlist(d)) for d in self.manifest["golden"]["leaves"])

    def __call__(self, leaves: tuple[Any, ...], bus: Any) -> Any:
        return self._call(tuple(leaves), bus)

    def compiled(self) -> Any:
        """The deserialized step compiled ahead of time (calls never trace)."""
        bus = jnp.asarray(_fromlist(self.manifest["golden"]["bus"]))
        return self._call.lower(self.init_leaves(), bus).compile()


def load_artefact(
    path: str | PathLike[str],
    expect_config_hash: str | None = None,
    *,
    step: RuntimeStep | None = None,
    golden_bus: np.ndarray | None = None,
) -> Artefact:
    """Load ``path`` and check it (ArtefactError naming the first check that fails).

    ``expect_config_hash``: the configuration the caller means to run
    (:meth:`RuntimeStep.config_hash`); None skips that check. ``step``: the
    in-process step of that configuration (not compiled): the artefact's dtype,
    input shapes and golden cold state must be its own, so a caller can run
    the artefact from ``step.init_leaves()`` and never from numbers the file
    supplies. ``golden_bus``: the golden input the caller expects (the
    scenario's first bus vector).
    """
    try:
        with zipfile.ZipFile(path) as z:
            manifest = json.loads(z.read("manifest.json"))
            blob = z.read("step.stablehlo")
    except (OSError, KeyError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise ArtefactError(f"artefact {path}: not a readable artefact ({exc})") from None
    if not isinstance(manifest, dict):
        raise ArtefactError(f"artefact {path}: manifest.json is not an object")
    if manifest.get("format") != ARTEFACT_FORMAT:
        raise ArtefactError(
            f"artefact {path}: format {manifest.get('format')!r}, expected {ARTEFACT_FORMAT}"
        )
    digest = hashlib.sha256(blob).hexdigest()
    if digest != manifest.get("step_sha256"):
        raise ArtefactError(
            f"artefact {path}: step.stablehlo hashes to {digest[:12]}..., the manifest says "
            f"{str(manifest.get('step_sha256'))[:12]}... (modified after export)"
        )
    ccv = manifest.get("calling_convention_version")
    lo = export.minimum_supported_calling_convention_version
    hi = export.maximum_supported_calling_convention_version
    if not isinstance(ccv, int) or not lo <= ccv <= hi:
        raise ArtefactError(
            f"artefact {path}: calling convention version {ccv!r}; jax {jax.__version__} "
            f"runs {lo}..{hi}"
        )
    if expect_config_hash is not None and manifest.get("config_hash") != expect_config_hash:
        raise ArtefactError(
            f"artefact {path}: made for another controller configuration "
            f"(config_hash {str(manifest.get('config_hash'))[:12]}..., this run's "
            f"{expect_config_hash[:12]}...; scenario {manifest.get('scenario')!r}, "
            f"formulation {manifest.get('formulation')!r}, dtype {manifest.get('dtype')!r})"
        )
    if step is not None:
        leaves, bus0 = step.example_args()
        want_inputs = {"leaves": [_spec(x) for x in leaves], "bus": _spec(bus0)}
        if manifest.get("dtype") != step.dtype or manifest.get("inputs") != want_inputs:
            raise ArtefactError(
                f"artefact {path}: its inputs ({manifest.get('dtype')!r}) are not those of "
                f"this run's step ({step.dtype!r})"
            )
        try:
            cold = [_fromlist(d) for d in manifest["golden"]["leaves"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise ArtefactError(
                f"artefact {path}: the manifest's golden pair is malformed ({exc!r})"
            ) from None
        if len(cold) != len(leaves) or not all(
            np.array_equal(a, np.asarray(b)) for a, b in zip(cold, leaves, strict=True)
        ):
            raise ArtefactError(f"artefact {path}: the golden input's state is not the cold state")
    if golden_bus is not None:
        try:
            gb = _fromlist(manifest["golden"]["bus"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ArtefactError(
                f"artefact {path}: the manifest's golden pair is malformed ({exc!r})"
            ) from None
        if not np.array_equal(gb, np.asarray(golden_bus, gb.dtype)):
            raise ArtefactError(
                f"artefact {path}: the golden input is not the scenario's first bus vector"
            )
    try:
        exp = export.deserialize(bytearray(blob))
    except Exception as exc:  # a blob that hashes right but jax cannot read
        raise ArtefactError(
            f"artefact {path}: step.stablehlo does not deserialize ({exc})"
        ) from None
    art = Artefact(exp, manifest)
    try:
        g = manifest["golden"]
        leaves = art.init_leaves()
        bus = jnp.asarray(_fromlist(g["bus"]))
        want = [_fromlist(d) for d in g["outputs"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ArtefactError(
            f"artefact {path}: the manifest's golden pair is malformed ({exc!r})"
        ) from None
    try:
        got = jax.tree.leaves(art(leaves, bus))
    except Exception as exc:  # noqa: BLE001 -- whatever the deserialized step raises
        raise ArtefactError(f"artefact {path}: the golden input does not run ({exc})") from None
    if len(got) != len(want):
        raise ArtefactError(f"artefact {path}: {len(got)} outputs, the manifest has {len(want)}")
    for i, (a, b) in enumerate(zip(got, want, strict=True)):
        a = np.asarray(a)
        if a.shape != b.shape or a.dtype != b.dtype or not np.array_equal(a, b, equal_nan=True):
            raise ArtefactError(
                f"artefact {path}: output {i} of the golden pair differs "
                f"(got {a.ravel()[:4].tolist()}, manifest {b.ravel()[:4].tolist()})"
            )
    return art
