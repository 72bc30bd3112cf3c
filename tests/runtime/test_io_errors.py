"""Every I/O error the runtime and its command line report names its file: a
full disk (here a file-size limit, ``RLIMIT_FSIZE`` with SIGXFSZ ignored, in a
subprocess) stopped a run with ``[Errno 27] File too large``, which names none.
Tried on each writer: the tick journal, run.json, ticks.parquet, the plant's
logs and report, `ampc replay`'s outputs and `ampc export`'s artefact."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from rt_procs import ROOT, SCENARIO

from ampc_jax.testing.budget import budget

pytestmark = pytest.mark.timeout(300)

LIMIT = 4096  # bytes: a header and run.json fit, a few dozen ticks do not


def _python(script: str, limit: int = LIMIT) -> subprocess.CompletedProcess:
    """``script`` in a fresh Python whose files may not grow past ``limit`` bytes
    (set first thing in the child: no preexec_fn in a process that runs JAX)."""
    head = (
        "import resource, signal\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill\n"
        f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JAX_ENABLE_X64": "1"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # nothing to compile, nothing to cache
    return subprocess.run(
        [sys.executable, "-c", head + textwrap.dedent(script)],
        capture_output=True,
        text=True,
        timeout=budget(200),
        env=env,
        cwd=ROOT,
    )


WRITERS = """
import json, sys
from pathlib import Path
from ampc_jax.runtime.ticklog import TickJournal, new_row, write_run_json
from ampc_jax.runtime.plant_node import PlantReport, write_report

d = Path(sys.argv[1])
meta = {"scenario": "cruise_lane_change", "formulation": "local_explicit",
        "dtype": "float64", "config_hash": "0" * 64}
out = {}

def attempt(name, fn):
    try:
        fn()
        out[name] = None
    except OSError as exc:
        out[name] = [type(exc).__name__, str(exc)]

(d / "journal").mkdir()
journal = TickJournal(d / "journal", meta)
rows = [new_row(i, 10**9 + i, "state invalid", "state") for i in range(200)]
attempt("journal", lambda: [journal.append(r) for r in rows])
(d / "finish").mkdir()
small = TickJournal(d / "finish", meta)
attempt("finish", lambda: small.finish(rows, {"state": "finished", "pad": "x" * 100}))
(d / "run").mkdir()
attempt("run.json", lambda: write_run_json(d / "run" / "run.json", {"pad": "x" * 10000}))
rep = PlantReport(rows=[{"t": 0.05 * i, "x": float(i)} for i in range(2000)],
                  frames=[], summary={"frames": 0})
attempt("plant", lambda: write_report(rep, d / "plant"))
print(json.dumps(out))
"""


def test_each_writer_names_its_file(tmp_path: Path) -> None:
    p = _python(WRITERS.replace("sys.argv[1]", repr(str(tmp_path))))
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads(p.stdout.strip().splitlines()[-1])
    want = {
        "journal": tmp_path / "journal" / "ticks.jsonl",
        "finish": tmp_path / "finish" / "ticks.parquet.tmp",
        "run.json": tmp_path / "run" / "run.json.tmp",
        "plant": tmp_path / "plant" / "plant.parquet",
    }
    for name, path in want.items():
        assert got[name] is not None, (name, got)
        kind, text = got[name]
        assert kind == "FileError", (name, got[name])
        assert text.startswith(f"{path}: cannot write (") and "File too large" in text, text


def test_replay_names_the_output_it_cannot_write(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "replay"
    p = _python(
        f"""
        import sys
        from ampc_jax.cli import main
        sys.exit(main(["--no-compilation-cache", "replay", {str(run_dir)!r}, "--out", {str(out)!r}]))
        """
    )
    errors = [x for x in p.stderr.splitlines() if x.startswith("ampc: error: ")]
    assert p.returncode == 2 and len(errors) == 1, p.stderr[-3000:]
    assert errors[0].startswith(f"ampc: error: replay: {out / 'replay.parquet'}: cannot write ("), (
        errors[0]
    )
    assert "File too large" in errors[0]


@pytest.mark.slow  # traces the controller once more
def test_export_names_the_artefact_it_cannot_write(tmp_path: Path) -> None:
    path = tmp_path / "step.zip"
    p = _python(
        f"""
        import sys
        from ampc_jax.cli import main
        sys.exit(main(["--no-compilation-cache", "export", "--scenario", {SCENARIO!r},
                       "--out", {str(path)!r}]))
        """
    )
    errors = [x for x in p.stderr.splitlines() if x.startswith("ampc: error: ")]
    assert p.returncode == 1 and len(errors) == 1, p.stderr[-3000:]
    assert errors[0].startswith(f"ampc: error: export: {path}: cannot write ("), errors[0]
