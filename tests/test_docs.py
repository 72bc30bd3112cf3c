"""The repository's text stands alone: no absolute path of a development machine,
no reference to a file outside the repository, every relative Markdown link
resolves inside it, and every reference to an item of the notes on the paper
("paper-notes item N", or the older "NOTES item N") names an item that
``docs/paper-notes.md`` has, whose tests exist.

The tracked files are those ``git ls-files`` lists (skipped outside a git
checkout); binary files are left out.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).parents[1]
NOTES = ROOT / "docs" / "paper-notes.md"
THIS = Path(__file__).resolve()

# the patterns are assembled from parts, so that this file does not match them
_SEP = "/"
# a development machine's home and work folders, anywhere in the tracked text; an
# absolute path starts after a space, a quote, a bracket or a line start (not
# inside a relative path such as docs/work/...)
_LEAD = r"(?<![\w.~/-])"
ABSOLUTE = re.compile(_LEAD + _SEP + r"(?:work|home|root|Users)" + _SEP + r"[\w.-]")
# a temporary folder is a real path in commands a reader copies from the docs
TEMPORARY = re.compile(_LEAD + _SEP + "tmp" + _SEP)
# files of the development environment that a user of the repository does not have
OUTSIDE = re.compile(
    r"\.\." + _SEP + "shared"
    + "|" + r"\bshared" + _SEP + r"(?:paper|docs)\b"
    + "|" + r"\bNOTES\.md\b"
    + "|" + r"multi-objective-ampc\.tex"
)  # fmt: skip
# "NOTES item 14", "NOTES items 8, 18, 19", "NOTES 1-4, 9, 11", "paper-notes item 7",
# "NOTES items 12 and 15"
ITEM_REF = re.compile(
    r"\b(?:paper-notes|NOTES)\s+(?:items?\s+)?"
    r"(\d+(?:\s*(?:-|,|and|to)\s*\d+)*)"
)
LINK = re.compile(r"\]\(([^)\s]+)\)")
ANCHOR = re.compile(r'<a id="item-(\d+)"></a>\s*\n###\s+(\d+)\.')
TEST_REF = re.compile(r"`(tests/[\w/]+\.py)::(test_\w+)`")
MODULE_REF = re.compile(r"`((?:ampc_jax|bench)/[\w/]+\.py)`")


def _tracked() -> dict[str, str]:
    """Text of every tracked file, by repository path (binary files left out)."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    names = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout.split(b"\0")
    out = {}
    for raw in names:
        name = raw.decode()
        path = ROOT / name
        if not name or not path.is_file() or path.resolve() == THIS:
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue
        try:
            out[name] = data.decode("utf-8")
        except UnicodeDecodeError:
            continue
    return out


@pytest.fixture(scope="module")
def tracked() -> dict[str, str]:
    return _tracked()


def _hits(text: str, pattern: re.Pattern) -> list[str]:
    hits = []
    for k, line in enumerate(text.splitlines(), 1):
        for m in pattern.finditer(line):
            hits.append(f"{k}: {line.strip()[:120]}  [{m.group(0)}]")
    return hits


def _items() -> set[int]:
    return {int(a) for a, _ in ANCHOR.findall(NOTES.read_text())}


def _numbers(spec: str) -> list[int]:
    """'8, 18, 19' -> [8, 18, 19]; '1-4, 9' -> [1, 2, 3, 4, 9]; '12 and 15' -> [12, 15]."""
    out: list[int] = []
    for part in re.split(r"\s*(?:,|and)\s*", spec):
        lo, _, hi = re.sub(r"\s*to\s*", "-", part).partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def test_no_absolute_path_of_a_development_machine(tracked):
    bad = {name: h for name, text in tracked.items() if (h := _hits(text, ABSOLUTE))}
    assert not bad, bad


def test_docs_name_no_temporary_folder(tracked):
    """A command in the docs writes where the reader runs it, not into /tmp."""
    docs = {n: t for n, t in tracked.items() if n.endswith(".md")}
    bad = {name: h for name, text in docs.items() if (h := _hits(text, TEMPORARY))}
    assert not bad, bad


def test_no_reference_to_a_file_outside_the_repository(tracked):
    bad = {name: h for name, text in tracked.items() if (h := _hits(text, OUTSIDE))}
    assert not bad, bad


def test_relative_markdown_links_resolve_inside_the_repository(tracked):
    root = ROOT.resolve()
    bad = []
    for name, text in tracked.items():
        if not name.endswith(".md"):
            continue
        for m in LINK.finditer(text):
            target = m.group(1)
            if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                continue  # a URL, or an anchor on the same page
            path = (ROOT / name).parent / target.split("#")[0]
            resolved = path.resolve()
            if not resolved.exists() or (resolved != root and root not in resolved.parents):
                bad.append(f"{name}: {target}")
    assert not bad, bad


def test_paper_notes_items_are_numbered_in_order():
    text = NOTES.read_text()
    pairs = [(int(a), int(h)) for a, h in ANCHOR.findall(text)]
    assert pairs, "no items found"
    assert all(a == h for a, h in pairs), pairs  # each anchor sits on its own heading
    assert [a for a, _ in pairs] == list(range(1, len(pairs) + 1))
    assert "10.1109/TITS.2025.3612984" in text  # the paper, cited by its DOI


def test_every_item_reference_names_an_existing_item(tracked):
    items = _items()
    files = dict(tracked)
    files.setdefault("docs/paper-notes.md", NOTES.read_text())
    bad, seen = [], 0
    for name, text in files.items():
        for m in ITEM_REF.finditer(text):
            seen += 1
            missing = [n for n in _numbers(m.group(1)) if n not in items]
            if missing:
                bad.append(f"{name}: {m.group(0)!r} -> {missing}")
        for m in re.finditer(r"paper-notes\.md#item-(\d+)", text):
            seen += 1
            if int(m.group(1)) not in items:
                bad.append(f"{name}: {m.group(0)}")
        if name == "docs/paper-notes.md":
            for m in re.finditer(r"\(#item-(\d+)\)", text):
                if int(m.group(1)) not in items:
                    bad.append(f"{name}: {m.group(0)}")
    assert seen > 0  # the patterns still find the references
    assert not bad, bad


def test_the_tests_and_modules_named_in_the_paper_notes_exist():
    text = NOTES.read_text()
    refs = TEST_REF.findall(text)
    assert len(refs) >= 23  # at least one per item
    missing = []
    for path, test in refs:
        f = ROOT / path
        if not f.is_file() or not re.search(rf"^\s*def {test}\(", f.read_text(), re.M):
            missing.append(f"{path}::{test}")
    for path in MODULE_REF.findall(text):
        if not (ROOT / path).is_file():
            missing.append(path)
    assert not missing, missing
    # every item names at least one test
    for block in re.split(r'<a id="item-\d+"></a>', text)[1:]:
        block = block.split("\n## ")[0]
        assert TEST_REF.search(block), block[:80]


@pytest.mark.parametrize(
    ("spec", "numbers"),
    [("14", [14]), ("8, 18, 19", [8, 18, 19]), ("1-4, 9, 11", [1, 2, 3, 4, 9, 11]),
     ("12 and 15", [12, 15]), ("6, 17", [6, 17])],
)  # fmt: skip
def test_item_lists_are_read_as_written(spec, numbers):
    assert _numbers(spec) == numbers
    m = ITEM_REF.search(f"(NOTES items {spec}).")
    assert m is not None and _numbers(m.group(1)) == numbers


def test_the_patterns_find_what_they_are_for():
    """Each check flags the kind of text it is meant to flag, and leaves alone
    relative paths and words that only look like one."""
    sep = _SEP
    assert ABSOLUTE.search(f"see {sep}work{sep}x{sep}NOTES")
    assert ABSOLUTE.search(f"`{sep}home{sep}me{sep}f.py`")
    assert not ABSOLUTE.search(f"docs{sep}work{sep}plan.md and ~{sep}home{sep}x")
    assert TEMPORARY.search(f"--out {sep}tmp{sep}big")
    assert not TEMPORARY.search(f"--out out{sep}tmp{sep}big")
    assert OUTSIDE.search("the paper's " + "NOTES" + ".md")
    assert OUTSIDE.search(".." + sep + "shared" + sep + "paper")
    assert not OUTSIDE.search("a shared agent, shared/owned")


def test_layout_names_every_module():
    """docs/layout.md has not drifted from the code: every module of the package and
    every source file of the bridge is named there."""
    text = (ROOT / "docs" / "layout.md").read_text()
    files = sorted((ROOT / "ampc_jax").rglob("*.py")) + sorted(
        (ROOT / "can_bridge" / "src").rglob("*.rs")
    )
    skip = {"__init__.py", "__main__.py", "lib.rs", "mod.rs"}
    missing = [
        str(f.relative_to(ROOT)) for f in files if f.name not in skip and f"`{f.name}`" not in text
    ]
    assert not missing, f"docs/layout.md does not name: {missing}"
