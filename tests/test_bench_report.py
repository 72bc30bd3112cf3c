"""The docs' benchmark figures are the committed result files' figures.

Each block between ``bench-result`` markers in README.md and docs/*.md is what
``bench/report.py`` renders from ``bench/results/<script>.json``: a run that
replaces a result file and not the doc (or an edit by hand inside a block)
fails here, and ``python bench/report.py`` mends it.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).resolve().parents[1]


def _report():
    spec = importlib.util.spec_from_file_location("bench_report", ROOT / "bench" / "report.py")
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod


report = _report()


def test_every_generated_block_matches_its_result_file():
    assert report.check() == []


def test_the_benchmarks_with_a_result_file_are_shown_somewhere():
    """Every committed result file is rendered by some doc (one place per benchmark)."""
    text = "\n".join(p.read_text() for p in report.docs())
    shown = {m.group("spec").split()[0] for m in report.BLOCK.finditer(text)}
    stems = {p.stem for p in (ROOT / "bench" / "results").glob("*.json")}
    assert stems <= shown, sorted(stems - shown)


def _doc(tmp_path: Path, printed: list[str], results: object = None) -> Path:
    (tmp_path / "r.json").write_text(
        json.dumps(
            {
                "meta": {
                    "commit": "abc1234",
                    "date_utc": "2026-12-01T10:00:00Z",
                    "command": "python bench/SCRIPT.py --out /somewhere/x.json --n 3",
                    "cpu_count": 2,
                    "loadavg_start": [0.5, 0, 0],
                    "loadavg_end": [1.25, 0, 0],
                },
                "results": results or {},
                "printed": printed,
            }
        )
    )
    return tmp_path / "r.json"


def test_render_selects_tables_lines_and_records(tmp_path, monkeypatch):
    monkeypatch.setattr(report, "RESULTS", tmp_path)
    printed = [
        "caption one",
        "| a | b |",
        "| --- | --- |",
        "| 1 | 2 |",
        "Polishing not needed - no active set detected at optimal point",
        "### caption two",
        "",
        "| c |",
        "| --- |",
        "| 3 |",
        "plain line",
    ]
    _doc(tmp_path, printed, {"rows": [{"x": 1.234567, "y": "k"}], "d": {"p": {"v": 2}}})
    doc = tmp_path / "docs" / "d.md"
    out = report.render("r tables=2", doc)
    assert "**caption two**\n\n| c |\n| --- |\n| 3 |" in out and "| a | b |" not in out
    assert "at commit abc1234" in out and "load 0.50 to 1.25" in out
    assert "--out" not in out and "`python bench/SCRIPT.py --n 3`" in out  # the file is the link
    assert "(../r.json)" in out
    assert "| a | b |" in report.render("r", doc) and "| c |" in report.render("r", doc)
    lines = report.render("r lines=4:5", doc)
    assert "```text\n| 1 | 2 |\ncaption two\n```" not in lines  # noise is left out first
    assert "```text\n| 1 | 2 |\n### caption two\n```" in lines
    rows = report.render("r rows=rows cols=x,y", doc)
    assert "| x | y |\n| --- | --- |\n| 1.235 | k |" in rows
    assert "| case | v |\n| --- | --- |\n| p | 2 |" in report.render("r rows=d", doc)
    with pytest.raises(ValueError, match="unknown option"):
        report.render("r table=1", doc)


def test_update_rewrites_a_stale_block_and_check_names_it(tmp_path, monkeypatch):
    monkeypatch.setattr(report, "RESULTS", tmp_path)
    _doc(tmp_path, ["| a |", "| --- |", "| 1 |"])
    doc = tmp_path / "d.md"
    doc.write_text("before\n<!-- bench-result: r -->\nold figures\n<!-- /bench-result -->\nafter\n")
    monkeypatch.setattr(report, "ROOT", tmp_path)
    assert report.check([doc]) == ["d.md: r"]
    assert report.update([doc]) == [doc]
    assert report.check([doc]) == []
    text = doc.read_text()
    assert text.startswith("before\n") and text.endswith("<!-- /bench-result -->\nafter\n")
    assert "old figures" not in text and "| 1 |" in text
