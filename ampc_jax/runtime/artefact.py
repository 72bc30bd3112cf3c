"""The exported controller step: serialized StableHLO plus a manifest (``jax.export``).

An artefact is one zip file:

* ``step.stablehlo`` -- ``jax.export`` of :meth:`RuntimeStep.function`
  (``f(leaves, bus) -> (torques, leaves, report)``), serialized;
* ``manifest.json`` -- the format version, jax and jaxlib versions, the
  calling convention's version, the platforms, the SHA-256 of
  ``step.stablehlo``, the hash of the controller configuration
  (:func:`~ampc_jax.runtime.step.config_hash`), the scenario and example it was
  made for, the input and output shapes and dtypes, a golden input/output pair
  (a cold state and the bus vector of the scenario's first step in, every
  output out), and ``manifest_sha256``: the SHA-256 of all the rest
  (:func:`manifest_digest`), so that an edit of any field is seen.

:func:`read_artefact` refuses (:class:`ArtefactError`, naming what differs),
before anything compiles, a file that is not a readable zip of the two, a
manifest edited after export, a step that does not hash to the manifest's, a
calling convention this jax cannot run, a configuration, scenario,
formulation, dtype or cold state other than the run's, a manifest whose
platforms, calling convention and shapes are not those of the deserialized
step, and a step whose StableHLO module does not deserialize or whose
``@main`` takes or returns other types than its description; :meth:`Artefact.compiled`
compiles the step and refuses it when it does not compile or does not
reproduce the golden pair bit for bit (``ampc run`` makes every check before
its channel opens). Rule: nothing is actuated from an
artefact before every check passes; reason: a tampered or stale controller
must not reach the wheels. The manifest is not signed: a forger who re-exports
(or reseals) gets past the hashes, never past the checks against the step and
the run's own configuration.

The artefact holds StableHLO, not a compiled executable, so a run from it
still compiles (XLA, for this machine's CPU): ``jax.experimental.
serialize_executable`` would skip that, but loading a serialized executable
unpickles it and may run arbitrary code (JAX's documentation says so), and it
is tied to one jaxlib and CPU. What the artefact saves is tracing the
controller; a machine-local compilation cache (``JAX_COMPILATION_CACHE_DIR``)
saves the compilation on the next start (docs/runtime.md, "Export").
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import sys
import tempfile
import zipfile
from collections.abc import Iterator
from os import PathLike
from typing import Any

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
from jax import export

from .files import named
from .step import RuntimeStep

__all__ = [
    "ARTEFACT_FORMAT",
    "Artefact",
    "ArtefactError",
    "export_step",
    "load_artefact",
    "manifest_digest",
    "read_artefact",
    "seal_manifest",
]

ARTEFACT_FORMAT = 2
"""Version of the artefact's layout (``manifest.json["format"]``; 2: the manifest
carries its own digest)."""

# Largest members a reader decompresses (the step is ~70 kB, the manifest ~6 kB).
_MAX_STEP_BYTES = 256 << 20
_MAX_MANIFEST_BYTES = 16 << 20
_DTYPES = ("float64", "float32", "int64", "int32", "bool")


class ArtefactError(ValueError):
    """An artefact that must not be run (the message says why)."""


def manifest_digest(manifest: dict[str, Any]) -> str:
    """SHA-256 of the manifest other than its ``manifest_sha256`` (keys sorted)."""
    rest = {k: v for k, v in manifest.items() if k != "manifest_sha256"}
    text = json.dumps(rest, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def seal_manifest(manifest: dict[str, Any]) -> dict[str, Any]:
    """The manifest with its ``manifest_sha256`` (over what JSON reads back)."""
    plain = json.loads(json.dumps({k: v for k, v in manifest.items() if k != "manifest_sha256"}))
    return {**plain, "manifest_sha256": manifest_digest(plain)}


def _spec(x: Any) -> dict[str, Any]:
    return {"shape": list(np.shape(x)), "dtype": str(np.asarray(x).dtype)}


def _tolist(x: Any) -> Any:
    a = np.asarray(x)
    return {"dtype": str(a.dtype), "shape": list(a.shape), "data": a.ravel().tolist()}


def _fromlist(d: Any) -> np.ndarray:
    """An array of the manifest ({dtype, shape, data}); ValueError if it is not one."""
    if not isinstance(d, dict) or set(d) != {"dtype", "shape", "data"}:
        raise ValueError("not an array record {dtype, shape, data}")
    dtype, shape, data = d["dtype"], d["shape"], d["data"]
    if dtype not in _DTYPES:
        raise ValueError(f"dtype {dtype!r:.40}")
    if not (isinstance(shape, list) and all(type(n) is int and 0 <= n for n in shape)):
        raise ValueError(f"shape {shape!r:.40}")
    size = math.prod(shape)
    if not isinstance(data, list) or len(data) != size:
        raise ValueError(
            f"{len(data) if isinstance(data, list) else data!r:.40} values for shape {shape}"
        )
    if not all(type(x) in (int, float, bool) for x in data):
        raise ValueError("values that are not numbers")
    try:
        return np.asarray(data, dtype=dtype).reshape(shape)
    except (OverflowError, ValueError, TypeError) as exc:  # 10**400 as a float64, ...
        raise ValueError(f"values that are not {dtype} ({exc})") from None


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
    manifest = seal_manifest(
        {
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
    )
    with named(path), zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("step.stablehlo", blob)
        z.writestr("manifest.json", json.dumps(manifest, indent=1))
    return manifest


class Artefact:
    """A read and checked artefact (:func:`read_artefact`): :meth:`compiled` compiles
    its step and checks the golden pair; ``art(leaves, bus)`` runs it."""

    def __init__(self, exported: Any, manifest: dict[str, Any], path: str = "") -> None:
        self.exported = exported
        self.manifest = manifest
        self.path = path
        self._compiled: Any = None

    def init_leaves(self) -> tuple[Any, ...]:
        """The cold state the golden pair starts from."""
        return tuple(jnp.asarray(_fromlist(d)) for d in self.manifest["golden"]["leaves"])

    def __call__(self, leaves: tuple[Any, ...], bus: Any) -> Any:
        return self.compiled()(tuple(leaves), bus)

    def compiled(self) -> Any:
        """The deserialized step compiled ahead of time (calls never trace), once it
        has reproduced the golden outputs bit for bit (ArtefactError otherwise)."""
        if self._compiled is None:
            g = self.manifest["golden"]
            bus = jnp.asarray(_fromlist(g["bus"]))
            leaves = self.init_leaves()
            with _native_errors(self.path, "does not compile") as said:
                fn = jax.jit(self.exported.call).lower(leaves, bus).compile()
            said.replay()
            _check_golden(fn, leaves, bus, [_fromlist(d) for d in g["outputs"]], self.path)
            self._compiled = fn
        return self._compiled


class _Captured:
    """What native code wrote to the process's stderr while captured."""

    def __init__(self) -> None:
        self.text = ""

    def replay(self) -> None:
        """Write it to stderr after all (what a step that passed said: warnings)."""
        if self.text:
            sys.stderr.write(self.text)
            sys.stderr.flush()

    def first_line(self) -> str:
        lines = [x.strip() for x in self.text.splitlines() if x.strip()]
        return lines[0][:200] if lines else ""


@contextlib.contextmanager
def _native_errors(path: Any, doing: str) -> Iterator[_Captured]:
    """Run MLIR/XLA on the artefact's step with file descriptor 2 captured, and
    turn any failure into one ArtefactError ``artefact PATH: step.stablehlo DOING
    (error; first diagnostic)``. Rule: a step that does not parse or compile is
    refused in one line; reason: MLIR's diagnostics go to the process's stderr
    from C++ (raw MLIR, several lines), which ``ampc``'s one-error-line rule and
    a user reading the refusal both need kept out."""
    said = _Captured()
    sys.stderr.flush()
    saved = os.dup(2)
    failure: BaseException | None = None
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield said
        except ArtefactError:
            raise
        except Exception as exc:  # noqa: BLE001 -- whatever jax/MLIR/XLA raise on a bad module
            failure = exc
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            said.text = tmp.read(1 << 16).decode("utf-8", "replace")
    if failure is not None:
        first = str(failure).strip().splitlines()[0][:200] if str(failure).strip() else ""
        why = "; ".join(x for x in (first or type(failure).__name__, said.first_line()) if x)
        raise ArtefactError(f"artefact {path}: step.stablehlo {doing} ({why})") from None


_TENSOR = re.compile(r"tensor<[^<>]*>")
_IR_DTYPES = {
    "float64": "f64",
    "float32": "f32",
    "int64": "i64",
    "int32": "i32",
    "bool": "i1",
}


def _ir_type(aval: Any) -> str:
    dims = "".join(f"{n}x" for n in aval.shape)
    return f"tensor<{dims}{_IR_DTYPES.get(str(aval.dtype), str(aval.dtype))}>"


def _main_signature(module_text: str) -> tuple[list[str], list[str]] | None:
    """The argument and result types of the module's ``@main`` (None: no ``@main``)."""
    m = re.search(r"func\.func public @main\((.*?)\) -> \((.*?)\) \{\n", module_text)
    if m is None:
        m1 = re.search(r"func\.func public @main\((.*?)\) -> (tensor<[^<>]*>)", module_text)
        if m1 is None:
            return None
        m = m1
    args = re.findall(r"%arg\d+: (tensor<[^<>]*>)", m.group(1))
    return args, _TENSOR.findall(m.group(2))


def _check_module(exp: Any, path: Any) -> None:
    """The step's StableHLO module deserializes (MLIR bytecode: a flipped byte that
    the manifest's resealed digest covers shows here, not at the compilation) and
    its ``@main`` takes and returns what the step says it does (``in_avals``,
    ``out_avals``): a module whose signature was changed under a kept
    description is refused before anything compiles."""
    with _native_errors(path, "does not deserialize as StableHLO") as said:
        text = exp.mlir_module()
    said.replay()
    sig = _main_signature(text)
    if sig is None:
        raise ArtefactError(f"artefact {path}: step.stablehlo has no public @main function")
    args, results = sig
    if exp.ordered_effects or len(exp.platforms) != 1:
        raise ArtefactError(
            f"artefact {path}: step.stablehlo has effects or several platforms "
            f"({list(exp.ordered_effects)}, {list(exp.platforms)}); a controller step has neither"
        )
    kept = [exp.in_avals[i] for i in exp.module_kept_var_idx if 0 <= i < len(exp.in_avals)]
    want_args = [_ir_type(a) for a in kept]
    if len(kept) != len(exp.module_kept_var_idx) or args != want_args:
        raise ArtefactError(
            f"artefact {path}: step.stablehlo's @main takes {args[:6]}, its description says "
            f"{want_args[:6]}"
        )
    want_results = [_ir_type(a) for a in exp.out_avals]
    if results != want_results:
        raise ArtefactError(
            f"artefact {path}: step.stablehlo's @main returns {results[:6]}, its description "
            f"says {want_results[:6]}"
        )


def _check_golden(fn: Any, leaves: Any, bus: Any, want: list[np.ndarray], path: str) -> None:
    try:
        got = jax.tree.leaves(fn(leaves, bus))
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


def _read_zip(path: str | PathLike[str]) -> tuple[bytes, bytes]:
    """The two members' bytes; ArtefactError for anything else."""
    try:
        with zipfile.ZipFile(path) as z:
            infos = {i.filename: i for i in z.infolist()}
            for name, cap in (
                ("manifest.json", _MAX_MANIFEST_BYTES),
                ("step.stablehlo", _MAX_STEP_BYTES),
            ):
                if name not in infos:
                    raise ArtefactError(f"artefact {path}: not a readable artefact (no {name})")
                if infos[name].file_size > cap:
                    raise ArtefactError(
                        f"artefact {path}: not a readable artefact ({name} of "
                        f"{infos[name].file_size} bytes, at most {cap})"
                    )
            return z.read("manifest.json"), z.read("step.stablehlo")
    except ArtefactError:
        raise
    # zipfile raises many kinds on damaged bytes (BadZipFile, zlib.error, EOFError,
    # struct.error, NotImplementedError, UnicodeDecodeError, ...): all mean the same here
    except Exception as exc:  # noqa: BLE001
        raise ArtefactError(f"artefact {path}: not a readable artefact ({exc})") from None


def _read_manifest(text: bytes, path: str | PathLike[str]) -> dict[str, Any]:
    try:
        manifest = json.loads(text)
    except RecursionError:
        raise ArtefactError(
            f"artefact {path}: not a readable artefact (manifest.json: nested too deeply)"
        ) from None
    except (ValueError, TypeError) as exc:  # JSONDecodeError, UnicodeDecodeError
        raise ArtefactError(
            f"artefact {path}: not a readable artefact (manifest.json: not JSON: {exc})"
        ) from None
    if not isinstance(manifest, dict):
        raise ArtefactError(f"artefact {path}: manifest.json is not an object")
    if manifest.get("format") != ARTEFACT_FORMAT:
        raise ArtefactError(
            f"artefact {path}: format {manifest.get('format')!r:.40}, expected {ARTEFACT_FORMAT}"
        )
    try:
        digest = manifest_digest(manifest)
    except (ValueError, TypeError, RecursionError):
        digest = ""
    if digest != manifest.get("manifest_sha256"):
        raise ArtefactError(
            f"artefact {path}: manifest.json was modified after export (its content does not "
            "hash to its manifest_sha256)"
        )
    return manifest


def _need(manifest: dict[str, Any], path: Any, key: str, ok: Any, expected: str) -> Any:
    v = manifest.get(key)
    if not ok(v):
        raise ArtefactError(
            f"artefact {path}: manifest.json: {key!r}: expected {expected}, got {v!r:.60}"
        )
    return v


def read_artefact(
    path: str | PathLike[str],
    expect_config_hash: str | None = None,
    *,
    step: RuntimeStep | None = None,
    golden_bus: np.ndarray | None = None,
    scenario: str | None = None,
) -> Artefact:
    """Read ``path`` and check it without compiling (ArtefactError naming the first
    check that fails); :meth:`Artefact.compiled` compiles and checks the golden pair.

    ``expect_config_hash``: the configuration the caller means to run
    (:meth:`RuntimeStep.config_hash`); None skips that check. ``step``: the
    in-process step of that configuration (not compiled): the artefact's dtype,
    formulation, example, input shapes and golden cold state must be its own, so
    a caller can run the artefact from ``step.init_leaves()`` and never from
    numbers the file supplies. ``golden_bus``: the golden input the caller
    expects (the scenario's first bus vector). ``scenario``: the scenario the
    caller runs.
    """
    text, blob = _read_zip(path)
    manifest = _read_manifest(text, path)
    digest = hashlib.sha256(blob).hexdigest()
    if digest != manifest.get("step_sha256"):
        raise ArtefactError(
            f"artefact {path}: step.stablehlo hashes to {digest[:12]}..., the manifest says "
            f"{str(manifest.get('step_sha256'))[:12]}... (modified after export)"
        )
    ccv = manifest.get("calling_convention_version")
    lo = export.minimum_supported_calling_convention_version
    hi = export.maximum_supported_calling_convention_version
    if type(ccv) is not int or not lo <= ccv <= hi:
        raise ArtefactError(
            f"artefact {path}: calling convention version {ccv!r:.40}; jax {jax.__version__} "
            f"runs {lo}..{hi}"
        )
    is_str = lambda x: isinstance(x, str)  # noqa: E731
    for key in ("config_hash", "scenario", "example", "formulation", "dtype"):
        _need(manifest, path, key, is_str, "a string")
    platforms = _need(
        manifest, path, "platforms", lambda x: isinstance(x, list) and all(map(is_str, x)), "names"
    )
    if expect_config_hash is not None and manifest["config_hash"] != expect_config_hash:
        raise ArtefactError(
            f"artefact {path}: made for another controller configuration "
            f"(config_hash {manifest['config_hash'][:12]}..., this run's "
            f"{expect_config_hash[:12]}...; scenario {manifest['scenario']!r:.40}, "
            f"formulation {manifest['formulation']!r:.40}, dtype {manifest['dtype']!r:.20})"
        )
    if scenario is not None and manifest["scenario"] != scenario:
        raise ArtefactError(
            f"artefact {path}: made for scenario {manifest['scenario']!r:.40}, this run's is "
            f"{scenario!r}"
        )
    try:
        g = manifest["golden"]
        golden = {
            "leaves": [_fromlist(d) for d in g["leaves"]],
            "bus": _fromlist(g["bus"]),
            "outputs": [_fromlist(d) for d in g["outputs"]],
        }
    except (KeyError, TypeError, ValueError) as exc:
        raise ArtefactError(
            f"artefact {path}: the manifest's golden pair is malformed ({exc!s:.80})"
        ) from None
    if step is not None:
        leaves, bus0 = step.example_args()
        want_inputs = {"leaves": [_spec(x) for x in leaves], "bus": _spec(bus0)}
        if manifest["dtype"] != step.dtype or manifest.get("inputs") != want_inputs:
            raise ArtefactError(
                f"artefact {path}: its inputs ({manifest['dtype']!r:.20}) are not those of "
                f"this run's step ({step.dtype!r})"
            )
        for key, mine in (
            ("formulation", step.config.formulation),
            ("example", step.config.example),
        ):
            if manifest[key] != mine:
                raise ArtefactError(
                    f"artefact {path}: made for {key} {manifest[key]!r:.40}, this run's is {mine!r}"
                )
        cold = golden["leaves"]
        if len(cold) != len(leaves) or not all(
            np.array_equal(a, np.asarray(b)) for a, b in zip(cold, leaves, strict=True)
        ):
            raise ArtefactError(f"artefact {path}: the golden input's state is not the cold state")
    if golden_bus is not None:
        gb = golden["bus"]
        if gb.shape != np.shape(golden_bus) or not np.array_equal(
            gb, np.asarray(golden_bus, gb.dtype)
        ):
            raise ArtefactError(
                f"artefact {path}: the golden input is not the scenario's first bus vector"
            )
    try:
        exp = export.deserialize(bytearray(blob))
    except Exception as exc:  # noqa: BLE001 -- a blob that hashes right but jax cannot read
        raise ArtefactError(
            f"artefact {path}: step.stablehlo does not deserialize ({exc!s:.200})"
        ) from None
    # the manifest's description of the step against the step itself
    _check_module(exp, path)
    if platforms != list(exp.platforms):
        raise ArtefactError(
            f"artefact {path}: the manifest's platforms {platforms} are not the step's "
            f"{list(exp.platforms)}"
        )
    if ccv != exp.calling_convention_version:
        raise ArtefactError(
            f"artefact {path}: the manifest's calling convention version {ccv} is not the "
            f"step's {exp.calling_convention_version}"
        )
    if "cpu" not in exp.platforms:
        raise ArtefactError(f"artefact {path}: exported for {list(exp.platforms)}, not for cpu")
    avals = lambda xs: [{"shape": list(a.shape), "dtype": str(a.dtype)} for a in xs]  # noqa: E731
    inputs = manifest.get("inputs")
    if not (
        isinstance(inputs, dict)
        and isinstance(inputs.get("leaves"), list)
        and [*inputs["leaves"], inputs.get("bus")] == avals(exp.in_avals)
    ):
        raise ArtefactError(f"artefact {path}: the manifest's inputs are not the step's")
    if manifest.get("outputs") != avals(exp.out_avals) or [
        _spec(x) for x in golden["outputs"]
    ] != avals(exp.out_avals):
        raise ArtefactError(f"artefact {path}: the manifest's outputs are not the step's")
    return Artefact(exp, manifest, str(path))


def load_artefact(
    path: str | PathLike[str],
    expect_config_hash: str | None = None,
    *,
    step: RuntimeStep | None = None,
    golden_bus: np.ndarray | None = None,
    scenario: str | None = None,
) -> Artefact:
    """:func:`read_artefact`, then compile the step and check its golden pair
    (:meth:`Artefact.compiled`): every check, as ``ampc run --artefact`` makes them."""
    art = read_artefact(
        path, expect_config_hash, step=step, golden_bus=golden_bus, scenario=scenario
    )
    art.compiled()
    return art
