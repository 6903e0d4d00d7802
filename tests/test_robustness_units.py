"""Unit checks of the robustness building blocks: redaction, output targets, the relocalize
gate of the runtime (no ROS), CSV validation helpers."""

from __future__ import annotations

import concurrent.futures as cf
import threading
import time

import pytest

from vlm_vpr_ros.errors import DataError, OutputError
from vlm_vpr_ros.redact import redact, register_secret


def test_redact_patterns():
    register_secret("Zq9-registered-secret-\nsecond-line-77")
    cases = {
        "GET http://bob:pa55word@host:8/v1": "GET http://***@host:8/v1",
        "Authorization: Bearer abc.def-ghi": "Authorization: ***",
        "{'api_key': 'qwerty123', 'model': 'm'}": "{'api_key': '***', 'model': 'm'}",
        "key sk-proj-ABCDEFGH12345678 here": "key *** here",
        "token=abc123&x=1": "token=***&x=1",
        "x Zq9-registered-secret- y second-line-77": "x *** y ***",
    }
    for text, want in cases.items():
        assert redact(text) == want, text
    assert redact("api_key_env=OPENAI_API_KEY") == "api_key_env=OPENAI_API_KEY"
    assert redact("lat 48.85, lon 2.35 (sigma 25 km)") == "lat 48.85, lon 2.35 (sigma 25 km)"


def test_check_not_inside(tmp_path):
    from vlm_vpr_ros.files.outputs import check_not_inside

    bag = tmp_path / "bag"
    bag.mkdir()
    for out in (bag, bag / "x", tmp_path):
        with pytest.raises(OutputError, match="never written into inputs"):
            check_not_inside(out, [bag])
    check_not_inside(tmp_path / "bag_eval", [bag])
    check_not_inside(bag / "map", [bag], allow_out_inside=True)


def test_staged_output_lock_and_swap(tmp_path):
    from vlm_vpr_ros.files.outputs import StagedOutput

    target = tmp_path / "ev"
    with StagedOutput(target, "evaluation") as s:
        (s.path / "summary.json").write_text("{}")
        (s.path / "frames.csv").write_text("index,stamp,key\n")
        with pytest.raises(OutputError, match="another process"):
            StagedOutput(target, "evaluation", overwrite=True).__enter__()
        s.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ev"]
    with pytest.raises(OutputError, match="pass --overwrite"):
        StagedOutput(target, "evaluation").__enter__()
    with pytest.raises(RuntimeError):  # a failure before commit: old output untouched
        with StagedOutput(target, "evaluation", overwrite=True) as s:
            (s.path / "summary.json").write_text('{"new": 1}')
            raise RuntimeError("boom")
    assert (target / "summary.json").read_text() == "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ev"]
    # an output named like the resumable scratch folder: the two stay apart
    with StagedOutput(tmp_path / "work", "map", resumable=True) as s:
        assert s.work != s.path and s.work.parent == s.path.parent
        s.work.mkdir()
        (s.path / "manifest.json").write_text('{"format": "vlm_vpr_ros.map"}')
        s.commit()
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == ["manifest.json"]


def test_unique_rows_and_ranges(tmp_path):
    from vlm_vpr_ros.files.csvio import parse_latlon, unique_rows

    assert unique_rows([(2, "a", 1), (3, "b", 2), (4, "a", 1)], "x.csv") == {"a": 1, "b": 2}
    with pytest.raises(DataError, match="lines 2 and 4"):
        unique_rows([(2, "a", 1), (3, "b", 2), (4, "a", 5)], "x.csv")
    for lat, lon in (("999", "1"), ("1", "-181"), ("nan", "1"), ("1e400", "0"), ("x", "1")):
        with pytest.raises(DataError, match="f.csv:7"):
            parse_latlon(lat, lon, "f.csv:7")
    assert parse_latlon(" -90 ", "180", "w") == (-90.0, 180.0)


def test_relocalize_gate_answers_every_caller_and_shares_the_query(demo_map, demo_data):
    """20 concurrent callers, a prior that never answers: every caller is answered within
    wait_s that the shared relocalization is scheduled (none hears 'busy'; docs/node.md
    "Relocalize services"); one prior request."""
    from types import SimpleNamespace

    from msg_adapters.image import message_to_rgb
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.priors.provider import PriorProvider
    from vlm_vpr_ros.runtime.worker import Frame, QueryRuntime, RuntimeConfig

    class Hung(PriorProvider):
        name = "hung"

        def __init__(self):
            self.n = 0

        def request(self, query):
            self.n += 1
            return cf.Future()  # never resolved

    rgb = load_image(sorted((demo_data / "images").iterdir())[0])
    h, w = rgb.shape[:2]
    msg = SimpleNamespace(height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3,
                          data=rgb.tobytes())
    prior = Hung()
    rt = QueryRuntime(LocalizationPipeline.open(demo_map), prior,
                      RuntimeConfig(mode="on_trigger", prior_timeout_s=30.0),
                      decode=message_to_rgb, on_outcome=lambda o: None)
    rt.start()
    try:
        rt.on_frame(Frame(msg, 1, "cam"))
        t0 = time.monotonic()
        with cf.ThreadPoolExecutor(20) as pool:
            answers = list(pool.map(lambda _: rt.relocalize(1.5), range(20)))
        took = time.monotonic() - t0
    finally:
        rt.stop(1.0)
    assert len(answers) == 20 and took < 1.5 + 1.0
    busy = [m for ok, m in answers if "busy" in m]
    # issue 29: a caller that gave up is told so; the answer is never published for it later
    waited = [m for ok, m in answers if m.startswith("relocalization gave no result within")
              and m.endswith("[timeout]")]
    assert not busy and len(waited) == 20 and not any(ok for ok, _ in answers)
    assert prior.n == 1  # one shared query
    assert threading.active_count() < 50
