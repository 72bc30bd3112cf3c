"""Render the docs' benchmark figures from the committed result files.

A benchmark's figures live in one place: its result file,
``bench/results/<script>.json`` (``bench/_meta.py``), and the one doc section
that shows them, generated from that file between two marker comments::

    <!-- bench-result: bench_call_overhead tables=1 -->
    (generated: do not edit; python bench/report.py)
    <!-- /bench-result -->

What a marker selects from the file (options after the file's stem):

* ``tables=1,3`` -- the markdown tables the script printed (``printed``),
  counted from 1, each with the caption line printed just before it;
  ``tables=all`` (the default when the script printed any table);
* ``lines=3:12`` -- printed lines 3 to 12 (from 1, both included) verbatim, as
  a text block (the default when it printed no table); a peer solver's chatter
  and progress bars (:data:`NOISE`) are left out before counting;
* ``rows=KEY`` with ``cols=a,b.c`` -- ``results[KEY]`` (``.``: ``results``
  itself), a list of records or a mapping of name to record, as a table of
  those columns (``b.c``: field ``c`` of field ``b``; all scalar ones by
  default; "-" where a record has none; a mapping's records are named in a
  first column, ``case``, and those with none of the columns are left out).

Every block starts with the run's provenance: UTC date, commit, the exact
command, cores and load average, and a link to the file.

``python bench/report.py`` rewrites every marked block of README.md and
docs/*.md; ``--check`` changes nothing and exits 1 naming each block that
differs from what its file renders (``tests/test_bench_report.py`` runs it).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
BLOCK = re.compile(
    r"(<!-- bench-result: (?P<spec>[^>]*?) -->\n)(?P<body>.*?)(<!-- /bench-result -->)", re.S
)
# what a script's output holds besides its own lines: a peer solver's chatter, progress bars
NOISE = re.compile(r"^Polishing not needed|\d+%\|")
NOTE = "<!-- generated from the result file by python bench/report.py: do not edit -->"

__all__ = ["check", "docs", "render", "update"]


def _clean(printed: list[str]) -> list[str]:
    """The script's own printed lines (:data:`NOISE` left out)."""
    return [line for line in printed if not NOISE.search(line)]


def _caption(printed: list[str], start: int) -> str:
    """The line printed just before a table (one blank line between allowed)."""
    for k in (start - 1, start - 2):
        if k < 0 or printed[k].lstrip().startswith("|"):
            return ""
        if printed[k].strip():
            return printed[k].strip().lstrip("#").strip()
    return ""


def _tables(printed: list[str]) -> list[list[str]]:
    """The markdown tables among ``printed``, each with its caption line (if any)."""
    out: list[list[str]] = []
    k = 0
    while k < len(printed):
        if not printed[k].lstrip().startswith("|"):
            k += 1
            continue
        start = k
        while k < len(printed) and printed[k].lstrip().startswith("|"):
            k += 1
        caption = _caption(printed, start)
        rows = [line.strip() for line in printed[start:k]]
        head = [f"**{caption}**", ""] if caption else []
        out.append(head + rows)
    return out


def _number(x: Any) -> str:
    if isinstance(x, bool) or x is None:
        return str(x)
    if isinstance(x, float):
        return f"{x:.4g}"
    if isinstance(x, list):
        return ", ".join(_number(v) for v in x)
    return str(x)


def _records(results: Any, key: str, cols: list[str] | None) -> list[str]:
    data = results if key == "." else results[key]
    if isinstance(data, dict):
        items = [(name, rec) for name, rec in data.items() if isinstance(rec, dict)]
        rows = [{"case": name, **rec} for name, rec in items]
    else:
        rows = [r for r in data if isinstance(r, dict)]
    if not rows:
        raise ValueError(f"results[{key!r}] holds no records")
    if cols is None:
        cols = [c for c, v in rows[0].items() if not isinstance(v, (dict, list))]
    elif isinstance(data, dict) and "case" not in cols:
        cols = ["case", *cols]
    named = [c for c in cols if c != "case"]
    rows = [r for r in rows if any(_get(r, c) != "-" for c in named)]  # records of another kind
    lines = ["| " + " | ".join(c.split(".")[-1] for c in cols) + " |", "|" + " --- |" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_number(_get(r, c)) for c in cols) + " |")
    return lines


def _get(record: dict[str, Any], path: str) -> Any:
    """``record[a][b]`` for the column ``a.b``; "-" where a record has no such field."""
    for key in path.split("."):
        if not isinstance(record, dict) or key not in record:
            return "-"
        record = record[key]
    return record


def _command(command: str) -> str:
    """The run's command line without its ``--out PATH`` (the link names the file)."""
    words = shlex.split(command)
    keep, skip = [], False
    for w in words:
        if skip:
            skip = False
        elif w == "--out":
            skip = True
        elif not w.startswith("--out="):
            keep.append(w)
    return shlex.join(keep)


def _provenance(doc: dict[str, Any], path: Path, doc_path: Path) -> str:
    meta = doc.get("meta", {})
    date = str(meta.get("date_utc", "?")).replace("T", " ").rstrip("Z")[:16]
    load = meta.get("loadavg_start"), meta.get("loadavg_end")
    loads = " to ".join(f"{x[0]:.2f}" for x in load if x)
    link = os.path.relpath(path, doc_path.parent).replace(os.sep, "/")
    parts = [
        f"Run of {date} UTC at commit {meta.get('commit', '?')}",
        f"`{_command(str(meta.get('command', '?')))}`",
        f"{meta.get('cpu_count', '?')} cores, load {loads or '?'}",
    ]
    affinity = meta.get("cpu_affinity")
    if affinity and len(affinity) < (meta.get("cpu_count") or 0):
        parts.insert(2, f"pinned to core(s) {', '.join(map(str, affinity))}")
    if meta.get("wall_s") is not None:
        parts.append(f"{meta['wall_s']:.0f} s")
    return ", ".join(parts) + f" ([`{path.name}`]({link})):"


def _options(spec: str) -> tuple[str, dict[str, str]]:
    stem, *rest = spec.split()
    opts = dict(item.split("=", 1) for item in rest)
    unknown = set(opts) - {"tables", "lines", "rows", "cols"}
    if unknown:
        raise ValueError(f"bench-result {stem}: unknown option(s) {sorted(unknown)}")
    return stem, opts


def render(spec: str, doc_path: Path) -> str:
    """The block a marker's ``spec`` (``STEM [tables=..|lines=..|rows=.. cols=..]``)
    stands for in the doc at ``doc_path``, from ``bench/results/STEM.json``."""
    stem, opts = _options(spec)
    path = RESULTS / f"{stem}.json"
    doc = json.loads(path.read_text())
    printed = _clean(doc.get("printed") or [])
    body: list[str]
    if "rows" in opts:
        cols = opts["cols"].split(",") if "cols" in opts else None
        body = _records(doc["results"], opts["rows"], cols)
    elif "lines" in opts or not _tables(printed):
        lo, _, hi = opts.get("lines", f"1:{len(printed)}").partition(":")
        body = ["```text", *printed[int(lo) - 1 : int(hi)], "```"]
    else:
        tables = _tables(printed)
        pick = opts.get("tables", "all")
        chosen = tables if pick == "all" else [tables[int(k) - 1] for k in pick.split(",")]
        body = []
        for t in chosen:
            body += [*t, ""]
        body = body[:-1]
    return "\n".join([NOTE, "", _provenance(doc, path, doc_path), "", *body, ""]) + "\n"


def docs() -> list[Path]:
    """The files whose marked blocks this script owns."""
    return [
        ROOT / "README.md",
        ROOT / "can_bridge" / "README.md",
        *sorted((ROOT / "docs").rglob("*.md")),
    ]


def _rendered(text: str, doc_path: Path) -> str:
    return BLOCK.sub(lambda m: m.group(1) + render(m.group("spec"), doc_path) + m.group(4), text)


def check(paths: list[Path] | None = None) -> list[str]:
    """Each marked block (``file: spec``) that differs from what its result file renders."""
    stale = []
    for p in paths or docs():
        text = p.read_text()
        for m in BLOCK.finditer(text):
            if m.group("body") != render(m.group("spec"), p):
                stale.append(f"{p.relative_to(ROOT)}: {m.group('spec')}")
    return stale


def update(paths: list[Path] | None = None) -> list[Path]:
    """Rewrite every marked block from its result file; the files that changed."""
    changed = []
    for p in paths or docs():
        text = p.read_text()
        new = _rendered(text, p)
        if new != text:
            p.write_text(new)
            changed.append(p)
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--check",
        action="store_true",
        help="change nothing; exit 1 if a block differs from its result file (default: rewrite)",
    )
    args = ap.parse_args(argv)
    if args.check:
        stale = check()
        for s in stale:
            print(f"stale: {s} (python bench/report.py rewrites it)")
        return 1 if stale else 0
    for p in update():
        print(f"rewrote {p.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
