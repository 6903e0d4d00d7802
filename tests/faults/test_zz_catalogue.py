"""The catalogue is complete: one marked test per case, and docs/robustness.md lists exactly the
catalogue (case -> behaviour) with its counts."""

from __future__ import annotations

import re
from pathlib import Path

from faults.catalogue import CATALOGUE

DOC = Path(__file__).resolve().parents[2] / "docs" / "robustness.md"


SUITE = {"test_faults_map.py", "test_faults_outputs.py", "test_faults_vlm.py",
         "test_faults_node.py", "test_faults_writers.py",
         "test_faults_content.py", "test_faults_inputs.py", "test_faults_stores.py",
         "test_faults_answers.py", "test_faults_scoring.py"}


def test_every_case_has_exactly_one_test(request):
    marked: dict[str, list[str]] = {}
    files = set()
    for item in request.session.items:
        if Path(str(item.fspath)).parent == Path(__file__).parent:
            files.add(Path(str(item.fspath)).name)
        for m in item.iter_markers("fault"):
            marked.setdefault(m.args[0], []).append(item.nodeid)
    unknown = sorted(set(marked) - set(CATALOGUE))
    assert not unknown, f"marked cases missing from the catalogue: {unknown}"
    if SUITE <= files:  # the whole suite was collected (not a -k selection)
        missing = sorted(set(CATALOGUE) - set(marked))
        assert not missing, f"catalogue cases without a test: {missing}"
        twice = {k: v for k, v in marked.items() if len(v) > 1}
        assert not twice, twice


def test_docs_table_matches_catalogue():
    text = DOC.read_text(encoding="utf-8")
    rows = re.findall(r"^\| `([a-z0-9_]+)` \|", text, re.M)
    assert rows == list(CATALOGUE), "docs/robustness.md table != tests/faults/catalogue.py"
    for cid, (_, case, behaviour) in CATALOGUE.items():
        assert f"| `{cid}` | {case} | {behaviour} |" in text, cid
    m = re.search(r"cases tried: (\d+), crashes: (\d+), data lost: (\d+), secrets leaked: (\d+)",
                  text)
    assert m and [int(g) for g in m.groups()] == [len(CATALOGUE), 0, 0, 0]
