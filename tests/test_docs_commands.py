"""Every command the README and docs name runs: each ``vlm-vpr`` sub-command mentioned resolves
to a real one and its ``--help`` works; each Python script mentioned (benchmarks/, scripts/)
answers ``--help``. The help texts describe the default fusion."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", REPO / "maps" / "README.md", *sorted((REPO / "docs").glob("*.md"))]
_VLM_VPR = re.compile(r"\bvlm-vpr((?:\s+-{1,2}[a-z]+)*)((?:\s+[a-z][a-z0-9-]*)+)")
_SCRIPT = re.compile(r"\b((?:benchmarks|scripts)/[a-z_0-9]+\.py)\b")


def _subcommands(parser) -> dict:
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices
    return {}


def mentioned_commands() -> dict[tuple[str, ...], str]:
    """``vlm-vpr`` sub-command paths named in the docs (longest real prefix of each mention)
    -> where the first mention is; a mention whose first word is no sub-command fails."""
    from vlm_vpr_ros.cli import build_parser

    root = build_parser()
    found: dict[tuple[str, ...], str] = {}
    bad = []
    for doc in DOCS:
        for n, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            for m in _VLM_VPR.finditer(line):
                words, parser, path = m.group(2).split(), root, []
                for w in words:
                    sub = _subcommands(parser)
                    if w not in sub:
                        break
                    parser, path = sub[w], path + [w]
                where = f"{doc.relative_to(REPO)}:{n}"
                if not path:
                    if words[0] not in ("is", "and", "or", "the", "to"):  # prose after the name
                        bad.append(f"{where}: 'vlm-vpr {words[0]}' is not a command")
                    continue
                found.setdefault(tuple(path), where)
    assert not bad, "\n".join(bad)
    return found


def test_docs_name_the_commands():
    found = mentioned_commands()
    for path in [("build-map",), ("localize",), ("evaluate",), ("demo",), ("bag", "make"),
                 ("replay",), ("evaluate-bag",), ("ablate",), ("map", "verify")]:
        assert path in found, path


@pytest.mark.parametrize("path", sorted(mentioned_commands()), ids=" ".join)
def test_help_of_each_command(path, capsys):
    from vlm_vpr_ros.cli import main

    with pytest.raises(SystemExit) as exc:
        main([*path, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: vlm-vpr {' '.join(path)}")


def test_help_describes_the_default_fusion(capsys):
    from vlm_vpr_ros.cli import main

    for path in (["localize"], ["evaluate-bag"], ["ablate"], ["demo"]):
        with pytest.raises(SystemExit):
            main([*path, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "posterior" in text or "default fusion" in text, path
        assert "re-rank by distance to the prior" not in text.split("paper")[0], path


def mentioned_scripts() -> list[str]:
    names = set()
    for doc in DOCS:
        names.update(_SCRIPT.findall(doc.read_text(encoding="utf-8")))
    return sorted(n for n in names if (REPO / n).is_file())


def test_docs_name_existing_scripts():
    names = set()
    for doc in DOCS:
        names.update(_SCRIPT.findall(doc.read_text(encoding="utf-8")))
    missing = sorted(n for n in names if not (REPO / n).is_file())
    assert not missing, f"docs name scripts that do not exist: {missing}"
    assert "scripts/gen_docs.py" in names and "benchmarks/bench_core.py" in names


@pytest.mark.parametrize("script", mentioned_scripts())
def test_help_of_each_script(script):
    res = subprocess.run([sys.executable, str(REPO / script), "--help"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.startswith("usage:"), res.stdout[:200]
