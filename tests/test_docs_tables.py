"""Docs that cannot go stale: scripts/gen_docs.py (tables between markers, from JSON) and the
"how it works" picture names only stages that exist (scripts/draw_stages.py); that the README's
and docs' demo tables equal what the shipped demo produces is tested with the demo
(tests/test_demo.py)."""

from __future__ import annotations

import json
import re

import cv2
import pytest

from repo_scripts import REPO, load


gen_docs = load("scripts/gen_docs.py")
draw_stages = load("scripts/draw_stages.py")


@pytest.fixture
def tiny_repo(tmp_path):
    """A repository with a README, one docs page and a JSON source."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "res.json").write_text(json.dumps({
        "tables": {"t": {"title": "T", "columns": ["", "n", "acc"],
                         "rows": [["a|b", 3, "50.00%"], ["c", 4, None]]}},
        "bench": {"latency": [{"case": "x", "ms": 1.23456}, {"case": "y", "ms": 2.0,
                                                             "note": "z"}]}}))
    (tmp_path / "README.md").write_text("intro\n<!-- table: res.json t -->\nold\n"
                                        "<!-- /table -->\ntail\n")
    (tmp_path / "docs" / "p.md").write_text("<!-- table: res.json bench.latency -->\n"
                                            "<!-- /table -->\n")
    return tmp_path


def test_render_columns_rows_and_records(tiny_repo):
    doc = json.loads((tiny_repo / "res.json").read_text())
    assert gen_docs.render(doc["tables"]["t"], "x") == (
        "*T*\n\n|  | n | acc |\n|:---|---:|---:|\n| a\\|b | 3 | 50.00% |\n| c | 4 | – |\n")
    assert gen_docs.render(doc["bench"]["latency"], "x", digits=1) == (
        "| case | ms | note |\n|:---|---:|---:|\n| x | 1.2 | – |\n| y | 2.0 | z |\n")
    with pytest.raises(gen_docs.DocsError, match="one value per column"):
        gen_docs.render({"columns": ["a", "b"], "rows": [[1]]}, "x")
    with pytest.raises(gen_docs.DocsError, match="not a table"):
        gen_docs.render({"x": 1}, "x")


def test_update_check_and_idempotence(tiny_repo):
    diffs, _ = gen_docs.run(tiny_repo, check=True)
    assert len(diffs) == 2 and "-old" in diffs[0]  # stale: reported, nothing written
    assert "old" in (tiny_repo / "README.md").read_text()
    diffs, _ = gen_docs.run(tiny_repo)
    text = (tiny_repo / "README.md").read_text()
    assert text.startswith("intro\n<!-- table: res.json t -->\n*T*\n") and text.endswith(
        "| c | 4 | – |\n<!-- /table -->\ntail\n")
    assert gen_docs.run(tiny_repo, check=True)[0] == []  # now up to date
    assert gen_docs.run(tiny_repo)[0] == []  # and a second run changes nothing


def test_errors_name_the_problem(tiny_repo):
    (tiny_repo / "docs" / "p.md").write_text("<!-- table: res.json nope -->\n<!-- /table -->\n")
    with pytest.raises(gen_docs.DocsError, match=r"no table 'nope' \(has: t\)"):
        gen_docs.run(tiny_repo, check=True)
    (tiny_repo / "docs" / "p.md").write_text("<!-- table: mystery t -->\n<!-- /table -->\n")
    with pytest.raises(gen_docs.DocsError, match="unknown source 'mystery'"):
        gen_docs.run(tiny_repo, check=True)
    (tiny_repo / "docs" / "p.md").write_text("<!-- table: gone.json t -->\n<!-- /table -->\n")
    _, notes = gen_docs.run(tiny_repo, check=True)
    assert any("gone.json" in n and "not found" in n for n in notes)
    with pytest.raises(gen_docs.DocsError, match="not found"):
        gen_docs.run(tiny_repo, check=True, strict=True)


def test_every_marker_names_a_known_source_and_is_filled():
    found = {}
    for path in gen_docs.doc_files(REPO):
        for m in gen_docs.BLOCK.finditer(path.read_text(encoding="utf-8")):
            source = m.group("source")
            assert source in gen_docs.SOURCES or source.endswith(".json"), (path, source)
            assert m.group("body").count("\n|") >= 2, f"{path.name}: empty table {source}"
            found.setdefault(source, []).append(m.group("key"))
    assert sorted(found["demo"]) == ["bag", "fixes", "fixes", "integrity.table", "lookalike",
                                     "lookalike", "map"]
    text = (REPO / "README.md").read_text(encoding="utf-8")
    assert "<!-- table: demo lookalike -->" in text and "<!-- table: demo fixes -->" in text
    # a stray opening marker (no closing one) would silently never be generated
    for path in gen_docs.doc_files(REPO):
        t = path.read_text(encoding="utf-8")
        assert len(re.findall(r"<!-- table: ", t)) == len(re.findall(r"<!-- /table -->", t))


def test_demo_figures_are_in_docs():
    for dest in gen_docs.FIGURES["demo"].values():
        img = cv2.imread(str(REPO / dest), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[1] > 500, dest
    assert "](docs/demo_contact_sheet.png)" in (REPO / "README.md").read_text()


def test_how_it_works_names_exist_and_draws(tmp_path):
    assert draw_stages.main(["--check"]) == 0
    names = [s.target for s in draw_stages.present(draw_stages.QUERY + draw_stages.BUILD)]
    assert "vlm_vpr_ros.localization.fusion.posterior:fuse" in names
    gone = draw_stages.Stage("vlm_vpr_ros.localization.localizer:Localizer.no_such", "x")
    with pytest.raises(AttributeError):
        draw_stages.resolve(gone)
    optional = draw_stages.Stage("vlm_vpr_ros.not_built_yet:thing", "x", optional=True)
    assert draw_stages.resolve(optional) is None
    png = draw_stages.draw(tmp_path / "h.png")
    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert img is not None and img.shape[1] > 1000
    assert (REPO / "docs" / "how_it_works.png").is_file()
