"""docs/api.md: the notebook session runs as written (its code blocks, in order, in a folder
holding the shipped demo's output), and its answers match the ground truth."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def code_blocks(path: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", path.read_text(encoding="utf-8"), re.S | re.M)


def test_api_page_runs(demo_run, tmp_path, monkeypatch):
    from vlm_vpr_ros import Hypothesis
    from vlm_vpr_ros.files.csvio import read_table
    from vlm_vpr_ros.geodesy import haversine_km

    out, _ = demo_run
    (tmp_path / "demo_out").symlink_to(out)  # "from the repository folder, after make demo"
    (tmp_path / "vlm_vpr_ros").symlink_to(REPO / "vlm_vpr_ros")
    monkeypatch.chdir(tmp_path)
    blocks = code_blocks(REPO / "docs" / "api.md")
    assert len(blocks) >= 4
    ns: dict = {}
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        for code in blocks:
            exec(compile(code, "docs/api.md", "exec"), ns)  # noqa: S102 - the doc's own code
    truth = {r["file"]: (float(r["lat"]), float(r["lon"]))
             for r in read_table(out / "queries.csv", ("file", "lat", "lon"))}
    hyp = ns["hyp"]
    assert isinstance(hyp, Hypothesis) and hyp.fusion == "posterior"
    assert haversine_km(hyp.lat, hyp.lon, *truth["546314506564628.jpg"]) < 0.025
    assert ns["answer"].ok and ns["answer"].source == "recorded"
    assert "MapError" in printed.getvalue()  # the error example
    assert printed.getvalue().count("\n") >= 8
