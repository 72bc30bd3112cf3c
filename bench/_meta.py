"""What every benchmark result file carries, and where it goes.

Each script in ``bench/`` writes one current result file,
``bench/results/<script stem>.json``, replaced by every full run: a result is
named by its date and commit (recorded inside), and older results live in the
git history. The file holds

* ``meta``: git commit (``git rev-parse --short HEAD``, ``+dirty`` when the
  work tree has changes, untracked files included), UTC date, Python, jax,
  jaxlib and numpy versions, the CPU model (``/proc/cpuinfo``), the machine's
  core count and this process's CPU affinity (``taskset -c 1`` shows as
  ``[1]``), ``XLA_FLAGS``, the exact command line, the run's wall time and
  ``os.getloadavg()`` at its start and end: the load is machine-wide, and a
  load near or above the core count means other processes shared the cores
  (timings are then slower and noisier than on an idle machine);
* ``results``: the numbers the printed tables show;
* ``printed``: the lines the script printed on stdout (its tables, verbatim).

Where it goes (:func:`add_out_argument`, :func:`output_path`): ``--out PATH``,
default ``bench/results/<stem>.json``; a ``--smoke`` run writes nowhere unless
``--out`` is given, so that the smoke tests (``tests/test_bench.py``) leave
the repository as it was.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"

__all__ = ["Run", "add_out_argument", "metadata", "output_path"]


def _git(*args: str) -> str:
    try:
        r = subprocess.run(
            ["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30, check=False
        )
    except (OSError, subprocess.SubprocessError):
        return ""
    return r.stdout.strip() if r.returncode == 0 else ""


def git_commit() -> str:
    """Short HEAD commit, ``+dirty`` when the work tree differs from it ("unknown" outside git)."""
    head = _git("rev-parse", "--short", "HEAD")
    if not head:
        return "unknown"
    return head + ("+dirty" if _git("status", "--porcelain") else "")


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _version(name: str) -> str:
    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


def _affinity() -> list[int] | None:
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None


def metadata(argv: list[str] | None = None) -> dict[str, Any]:
    """The run's metadata (see the module docstring); ``argv`` default ``sys.argv``."""
    argv = sys.argv if argv is None else argv
    return {
        "commit": git_commit(),
        "date_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "python": platform.python_version(),
        "jax": _version("jax"),
        "jaxlib": _version("jaxlib"),
        "numpy": _version("numpy"),
        "cpu_model": cpu_model(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": _affinity(),
        "loadavg_start": [round(x, 2) for x in os.getloadavg()],
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "command": shlex.join(["python", *argv]),
    }


def add_out_argument(ap: argparse.ArgumentParser, stem: str) -> None:
    """``--out PATH`` (default ``bench/results/<stem>.json``; ``--smoke``: nowhere)."""
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"the result file (default bench/results/{stem}.json; a --smoke run writes "
        "nowhere unless given)",
    )


def output_path(args: argparse.Namespace, stem: str) -> Path | None:
    """Where this run's result goes: ``--out``, else the default unless ``--smoke``."""
    if getattr(args, "out", None) is not None:
        return Path(args.out)
    if getattr(args, "smoke", False):
        return None
    return RESULTS / f"{stem}.json"


class _Tee(io.TextIOBase):
    def __init__(self, stream: Any) -> None:
        self.stream = stream
        self.buffer_text = io.StringIO()

    def write(self, s: str) -> int:
        self.buffer_text.write(s)
        return self.stream.write(s)

    def flush(self) -> None:
        self.stream.flush()


class Run:
    """One benchmark run: metadata taken at the start, stdout recorded, one file at the end.

    ::

        run = Run(output_path(args, STEM))   # starts recording stdout
        ...print tables, fill run.results...
        run.finish()                         # writes the file (if any) and says where
    """

    def __init__(self, path: Path | None, argv: list[str] | None = None) -> None:
        self.path = path
        self.meta = metadata(argv)
        self.results: dict[str, Any] = {}
        self._t0 = time.perf_counter()
        self._tee = _Tee(sys.stdout)
        sys.stdout = self._tee

    def finish(self) -> Path | None:
        """Stop recording, write ``{meta, results, printed}`` to the path (if any)."""
        if sys.stdout is self._tee:
            sys.stdout = self._tee.stream
        self.meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
        self.meta["wall_s"] = round(time.perf_counter() - self._t0, 1)
        if self.path is None:
            print("smoke run: no result file written (--out PATH writes one)")
            return None
        doc = {
            "meta": self.meta,
            "results": self.results,
            "printed": self._tee.buffer_text.getvalue().splitlines(),
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(doc, indent=1, default=_jsonable) + "\n")
        print(f"wrote {self.path}")
        return self.path


def _jsonable(x: Any) -> Any:
    """numpy scalars and arrays, tuples in odd places: as JSON values."""
    try:
        import numpy as np

        if isinstance(x, np.generic):
            return x.item()
        if isinstance(x, np.ndarray):
            return x.tolist()
    except ImportError:
        pass
    return str(x)
