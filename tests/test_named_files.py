"""Every repository file the tracked text names exists.

A docstring, comment or document that points to a file (``ampc_jax/...py``,
``bench/...py``, ``tests/...py``, ``docs/...md``, the crate's ``src/...rs``)
points to one that is there: a pointer to a benchmark or a test is how a
comment gives its reason, and a stale one sends the reader nowhere. A name is
looked for from the repository root, from the naming file's folder, and, for
the crate's paths, from ``can_bridge/`` and ``can_bridge/python/``. Names with
a placeholder in capitals (``notebooks/NAME.ipynb``) and the folders commands
write into (``notebook_output``) are not files of the repository.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()
NAMED = re.compile(
    r"(?<![\w./-])((?:ampc_jax|bench|tests|docs|notebooks|can_bridge|src|python|\.ci)"
    r"/[\w./-]*\w\.(?:py|pyi|rs|md|ipynb|toml|sh|json|png|dbc))\b"
)
WRITTEN = ("notebook_output",)  # folders that commands create
BASES = (ROOT, ROOT / "can_bridge", ROOT / "can_bridge" / "python")


def _tracked() -> dict[str, str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True)
    texts = {}
    for raw in out.stdout.split(b"\0"):
        path = ROOT / raw.decode()
        if not raw or not path.is_file() or path.resolve() == THIS:
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue
        try:
            texts[raw.decode()] = data.decode("utf-8")
        except UnicodeDecodeError:
            continue
    return texts


def _missing(name: str, text: str) -> list[str]:
    here = (ROOT / name).parent
    bad = []
    for k, line in enumerate(text.splitlines(), 1):
        for m in NAMED.finditer(line):
            path = m.group(1)
            if re.search(r"\b[A-Z]{3,}\b", path) or any(w in path for w in WRITTEN):
                continue
            if not any((base / path).exists() for base in (here, *BASES)):
                bad.append(f"{name}:{k}: {path}")
    return bad


def test_every_named_repository_file_exists():
    bad = [b for name, text in _tracked().items() for b in _missing(name, text)]
    assert not bad, bad


def test_the_pattern_finds_a_stale_name():
    assert _missing("x.py", "see ``src/python.rs`` and `bench/no_such_bench.py`") == [
        "x.py:1: src/python.rs",
        "x.py:1: bench/no_such_bench.py",
    ]
    assert _missing("x.py", "see `can_bridge/src/python/mod.rs`, notebooks/NAME.ipynb") == []
