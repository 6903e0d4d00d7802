#!/usr/bin/env python3
"""Regenerate the tables of measured numbers in README.md and docs/*.md from JSON outputs.

A generated table sits between two marker comments in the Markdown::

    <!-- table: SOURCE KEY -->
    ...generated, do not edit...
    <!-- /table -->

SOURCE is a registered name (``demo`` → ``demo_out/demo.json``, written by ``make demo``) or a
JSON file relative to the repository (e.g. a benchmark's ``--json`` output); KEY is the table in
that file: a key of its ``"tables"`` object, or a dotted path (``results.latency``). A table is
``{"columns": [...], "rows": [[...], ...]}`` (optional ``"title"``, shown in italics above it) or
a list of records (``[{"col": value, ...}, ...]``, columns in first-seen order); the first column
is left-aligned, the others right-aligned; floats are written with ``--digits`` decimals.

Usage::

    python scripts/gen_docs.py                 # rewrite the tables, copy the demo's figures
    python scripts/gen_docs.py --check         # exit 1 and show a diff where a table is stale
    python scripts/gen_docs.py --source demo=/tmp/d/demo.json --only demo --check

Sources that do not exist are skipped with a note (``--strict``: an error). Only this script
writes between the markers; edit the JSON's producer (the demo or a benchmark), never the table.
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from pathlib import Path
from typing import Any

from vlm_vpr_ros.files.atomic import atomic_write_bytes, atomic_write_text

REPO = Path(__file__).resolve().parents[1]
#: registered sources: name -> JSON file (relative to the repository)
SOURCES = {"demo": "demo_out/demo.json",  # make demo
           "ablation": "demo_out/ablation/ablation.json"}  # docs/evaluation.md, ablate
#: figures copied into docs/ with their source's tables: source -> {JSON "figures" key: file}
FIGURES = {"demo": {"lookalike_contact_sheet_png": "docs/demo_contact_sheet.png",
                    "lookalike_error_cdf_png": "docs/demo_error_cdf.png",
                    "world_map_png": "docs/demo_world_map.png",
                    # the integrity step's Stanford diagram (docs/evaluation.md "Integrity")
                    "stanford_png": "docs/demo_stanford.png"}}
BLOCK = re.compile(r"(?P<open><!-- table: (?P<source>\S+) (?P<key>\S+) -->)\n"
                   r"(?P<body>.*?)(?P<close><!-- /table -->)", re.S)


class DocsError(Exception):
    """A marker, source or table that cannot be used (one line for the user)."""


def doc_files(repo: Path = REPO) -> list[Path]:
    return [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]


def find_table(doc: Any, key: str, where: str) -> Any:
    """The table ``key`` of a JSON document: ``doc["tables"][key]`` or a dotted path."""
    tables = doc.get("tables") if isinstance(doc, dict) else None
    if isinstance(tables, dict) and key in tables:
        return tables[key]
    node = doc
    for part in key.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            have = sorted(tables) if isinstance(tables, dict) else (
                sorted(doc) if isinstance(doc, dict) else [])
            raise DocsError(f"{where}: no table {key!r} (has: {', '.join(have) or 'nothing'})")
    return node


def _cell(value: Any, digits: int) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value).replace("|", "\\|").replace("\n", " ")


def render(table: Any, where: str, digits: int = 2) -> str:
    """Markdown for one table (title line, header, alignment row, rows)."""
    title = ""
    if isinstance(table, dict) and "rows" in table:
        title = table.get("title") or ""
        columns, rows = list(table.get("columns") or []), list(table["rows"])
        if rows and isinstance(rows[0], dict):
            table = rows
        elif not columns or any(len(r) != len(columns) for r in rows):
            raise DocsError(f"{where}: every row needs one value per column")
    if isinstance(table, list) and all(isinstance(r, dict) for r in table):
        columns = list(dict.fromkeys(k for r in table for k in r))
        rows = [[r.get(c) for c in columns] for r in table]
    elif not isinstance(table, dict) or "rows" not in table:
        raise DocsError(f"{where}: not a table (expected columns + rows, or a list of records)")
    out = [f"*{title}*", ""] if title else []
    out.append("| " + " | ".join(_cell(c, digits) for c in columns) + " |")
    out.append("|" + "|".join([":---"] + ["---:"] * (len(columns) - 1)) + "|")
    out += ["| " + " | ".join(_cell(v, digits) for v in r) + " |" for r in rows]
    return "\n".join(out) + "\n"


class Sources:
    """JSON documents by source name or path, read once."""

    def __init__(self, repo: Path, overrides: dict[str, str]) -> None:
        self.repo, self.overrides, self.cache = repo, overrides, {}

    def path(self, source: str) -> Path:
        rel = self.overrides.get(source) or SOURCES.get(source) or source
        return (self.repo / rel).resolve()

    def load(self, source: str) -> Any | None:
        if source not in self.cache:
            path = self.path(source)
            if source not in SOURCES and source not in self.overrides and \
                    not source.endswith(".json"):
                raise DocsError(f"unknown source {source!r}: a registered name "
                                f"({', '.join(SOURCES)}) or a .json file")
            try:
                self.cache[source] = json.loads(path.read_text(encoding="utf-8"))
            except FileNotFoundError:
                self.cache[source] = None
            except (OSError, ValueError) as exc:
                raise DocsError(f"{path}: unreadable JSON ({exc})") from None
        return self.cache[source]


def update_text(text: str, name: str, sources: Sources, only: set[str] | None,
                strict: bool, digits: int, notes: list[str]) -> str:
    """``text`` with every selected table regenerated."""
    def replace(m: re.Match) -> str:
        source, key = m.group("source"), m.group("key")
        if only is not None and source not in only:
            return m.group(0)
        doc = sources.load(source)
        if doc is None:
            msg = f"{name}: source {source} ({sources.path(source)}) not found"
            if strict:
                raise DocsError(msg)
            notes.append(msg + "; table left as it is")
            return m.group(0)
        body = render(find_table(doc, key, f"{name}: {source} {key}"), f"{name}: {key}",
                      digits)
        return f"{m.group('open')}\n{body}{m.group('close')}"

    return BLOCK.sub(replace, text)


def run(repo: Path = REPO, check: bool = False, overrides: dict[str, str] | None = None,
        only: set[str] | None = None, strict: bool = False, digits: int = 2,
        figures: bool = True) -> tuple[list[str], list[str]]:
    """Regenerate (or with ``check`` compare) every doc; returns (stale-or-changed diffs,
    notes)."""
    sources = Sources(repo, overrides or {})
    diffs, notes = [], []
    for path in doc_files(repo):
        old = path.read_text(encoding="utf-8")
        name = str(path.relative_to(repo))
        new = update_text(old, name, sources, only, strict, digits, notes)
        if new != old:
            diffs.append("".join(difflib.unified_diff(
                old.splitlines(True), new.splitlines(True), f"{name} (in the docs)",
                f"{name} (generated)", n=1)))
            if not check:
                atomic_write_text(path, new)
    if figures and not check:
        notes += copy_figures(repo, sources, only)
    return diffs, notes


def copy_figures(repo: Path, sources: Sources, only: set[str] | None) -> list[str]:
    notes = []
    for source, figs in FIGURES.items():
        doc = sources.load(source) if only is None or source in only else None
        for key, dest in figs.items():
            src = (doc or {}).get("figures", {}).get(key)
            if src and Path(src).is_file():
                atomic_write_bytes(repo / dest, Path(src).read_bytes())
                notes.append(f"copied {src} -> {dest}")
    return notes


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Regenerate the measured-number tables of "
                                            "README.md and docs/*.md from JSON outputs (the "
                                            "demo's demo_out/demo.json, benchmark --json files).")
    p.add_argument("--check", action="store_true",
                   help="change nothing; exit 1 and print a diff when a table is stale")
    p.add_argument("--source", action="append", default=[], metavar="NAME=PATH",
                   help="read source NAME from PATH (e.g. demo=/tmp/run/demo.json)")
    p.add_argument("--only", action="append", default=None, metavar="NAME",
                   help="only the tables of these sources (repeatable)")
    p.add_argument("--strict", action="store_true", help="a missing source is an error")
    p.add_argument("--digits", type=int, default=2, help="decimals of float cells (default 2)")
    args = p.parse_args(argv)
    overrides = {}
    for item in args.source:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            p.error(f"--source wants NAME=PATH, got {item!r}")
        overrides[name] = str(Path(path).resolve())
    try:
        diffs, notes = run(REPO, args.check, overrides, set(args.only) if args.only else None,
                           args.strict, args.digits)
    except DocsError as exc:
        print(f"gen_docs: {exc}", file=sys.stderr)
        return 2
    for note in notes:
        print(f"gen_docs: {note}", file=sys.stderr)
    if args.check:
        sys.stdout.write("".join(diffs))
        print(f"gen_docs: {len(diffs)} file(s) with stale tables" if diffs
              else "gen_docs: every generated table is up to date", file=sys.stderr)
        return 1 if diffs else 0
    print(f"gen_docs: {len(diffs)} file(s) updated", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
