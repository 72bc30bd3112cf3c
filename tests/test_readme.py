"""The README stays a front page: at most 300 lines, the two setup-from-scratch
commands (one runs the demo, one passes the tests) each with its measured time,
and a headline table of the five figures a user decides on, each linking the
one doc that holds that benchmark's figures (docs/benchmarks.md names the doc
of every other benchmark)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(30)

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
DEMO = "python -m pip install --upgrade pip && python -m pip install ./can_bridge -e . && ampc demo --out demo"
TESTS = "bash .ci/run"


def _section(title: str) -> str:
    return README.split(f"\n## {title}\n", 1)[1].split("\n## ", 1)[0]


def test_the_readme_is_at_most_300_lines():
    assert len(README.splitlines()) <= 300


def test_the_two_commands_and_their_times():
    two = _section("Two commands")
    for command in (DEMO, TESTS):
        block = f"```bash\n{command}\n```"
        assert block in two, command
        before = two.split(block)[0].rsplit("```", 1)[-1]
        assert re.search(r"\d+ (?:min|s)\b", before), f"no time stated before {command!r}"
        assert re.search(r"commit [0-9a-f]{7}", before), f"no commit named before {command!r}"


def test_five_headline_figures_each_linking_its_doc():
    rows = [
        line
        for line in _section("Headline figures").splitlines()
        if line.startswith("| ") and not line.startswith(("| what ", "| --- "))
    ]
    assert len(rows) == 5, rows
    for row in rows:
        links = re.findall(r"\]\((docs/[\w.-]+\.md)(?:#[\w-]+)?\)", row.rsplit(" | ", 1)[-1])
        assert len(links) == 1 and (ROOT / links[0]).is_file(), row
