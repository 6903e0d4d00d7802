"""The debug view (pure): reference lookup, the side-by-side picture with matches, the
candidate rows; the runtime keeps decoded frames only when asked (no work without it)."""

from __future__ import annotations

import numpy as np
import pytest

from test_node_runtime import frame_of, make, msg_of
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.runtime import debug_view
from vlm_vpr_ros.types import Candidate, Hypothesis

QUERY = "546314506564628.jpg"


def _hyp(ref_id: str = QUERY) -> Hypothesis:
    cands = [Candidate(ref_id, 39.5, 8.8, 0.25, "k1", prior_km=1.5, posterior=0.75),
             Candidate("other.jpg", 39.6, 8.9, 0.5, "k2", posterior=0.25)]
    return Hypothesis(39.5, 8.8, ref_id, "k1", 30.0, candidates=cands)


def test_reference_images_are_found_scaled_and_confined(demo_data, tmp_path):
    refs = debug_view.ReferenceImages(demo_data / "images")
    thumb, scale = refs.load(QUERY)
    assert thumb.shape[0] == debug_view.PANEL_HEIGHT and thumb.dtype == np.uint8
    assert refs.load(QUERY)[0] is thumb  # cached
    assert refs.load("../osv5m_demo/images/" + QUERY) is None  # no way out of the folder
    assert refs.load("/etc/passwd") is None and refs.load("missing.jpg") is None
    assert debug_view.ReferenceImages(None).load(QUERY) is None
    # a teach map keeps its pictures: MAP/<manifest images.folder>
    own = debug_view.ReferenceImages.for_map(tmp_path, {"images": {"folder": "images"}})
    assert own.folder == tmp_path / "images"
    assert debug_view.ReferenceImages.for_map(tmp_path, {}, str(demo_data)).folder == demo_data
    assert debug_view.ReferenceImages.for_map(tmp_path, {}).folder is None


def test_render_puts_query_beside_reference_and_draws_matches(demo_data):
    refs = debug_view.ReferenceImages(demo_data / "images")
    query = np.full((480, 640, 3), 200, np.uint8)
    ref = refs.load(QUERY)
    plain = debug_view.render(query, ref, ["line one", "line two"], "reference x")
    h = debug_view.PANEL_HEIGHT
    assert plain.shape == (h + debug_view.CAPTION_HEIGHT, 480 + ref[0].shape[1], 3)
    assert (plain[h // 2:h - 20, 100:400] == 200).all()  # the (uniform) query, scaled
    # one match from the query's centre to the reference's top-left quarter: a green line
    rh, rw = (np.array(ref[0].shape[:2]) / ref[1]).astype(int)
    m = np.array([[320.0, 240.0, rw / 4, rh / 4]])
    drawn = debug_view.render(query, ref, ["a", "b"], "reference x", matches=m)
    diff = np.any(drawn != plain, axis=2)
    ys, xs = np.nonzero(diff[:h])
    assert len(xs) > 100 and xs.min() <= 245 and xs.max() >= 480 + ref[0].shape[1] // 4 - 3
    assert (drawn[ys, xs, 1] > drawn[ys, xs, 0]).mean() > 0.8  # green
    missing = debug_view.render(query, None, ["a", "b"])
    assert missing.shape[1] == 2 * 480  # a placeholder as wide as the query panel
    jpeg = debug_view.jpeg(drawn)
    assert jpeg[:2] == b"\xff\xd8"


def test_candidate_rows_and_caption():
    hyp = _hyp()
    rows = debug_view.candidate_rows(hyp)
    assert [r["rank"] for r in rows] == ["1", "2"] and rows[0]["ref_id"] == QUERY
    assert rows[0]["posterior"] == "0.7500" and rows[0]["prior_km"] == "1.5"
    assert rows[1]["prior_km"] == "" and rows[0]["inliers"] == ""  # not computed
    assert len(debug_view.candidate_rows(hyp, limit=1)) == 1
    top, second = debug_view.caption(hyp, "STATUS_FIX", 30.0)
    assert top.startswith("STATUS_FIX sigma 30 m") and "posterior 0.75" in top
    assert "no prior" in second and "2 candidates" in second
    assert debug_view.caption(None, "", 0.0, "descriptor failed: x")[0] == \
        "no fix: descriptor failed: x"


@pytest.mark.parametrize("keep", [False, True])
def test_the_runtime_keeps_decoded_frames_only_for_the_debug_view(pipeline, image, keep):
    """Only with keep_images (publish_debug) the outcome carries the frame and the answer's
    verified matches. The frame is a map image itself, so each match joins a point to the same
    point of the reference: equal fractions of the two images, to a pixel (an independent
    check of the coordinates the debug view draws)."""
    rt, col = make(pipeline, create_prior_provider("none"), mode="on_trigger")
    rt.keep_images = keep
    try:
        rt.on_frame(frame_of(msg_of(image), 5))
        out = rt.request_relocalize().wait(20)
    finally:
        rt.stop()
    assert out is not None and (out.rgb is not None) == keep
    assert (out.matches is not None) == keep
    if keep:
        assert out.rgb.shape == image.shape
        hyp, m = out.hypothesis, out.matches
        assert hyp.ref_id == QUERY and "verified" in hyp.flags
        assert m.shape == (len(hyp.matches[0]), 4) and len(m) == hyp.inliers > 50
        h, w = image.shape[:2]
        assert np.median(np.abs(m[:, :2] - m[:, 2:]) * [w, h]) < 1.0
        px = debug_view.match_pixels(m, image.shape, (image[::2, ::2], 0.5))
        assert np.allclose(px[:, :2], m[:, :2] * [w, h]) and np.allclose(px[:, 2:], px[:, :2],
                                                                         atol=4.0)


def test_answer_row_says_status_and_evidence():
    hyp = _hyp()
    row = debug_view.answer_row(hyp, "STATUS_NO_FIX", "unverified", 1234.5)
    assert row["status"] == "STATUS_NO_FIX" and row["status_reason"] == "unverified"
    assert row["p_correct"] == "" and row["inliers"] == "" and row["sigma_m"] == "1234.5"
    hyp.p_correct, hyp.inliers, hyp.inlier_ratio = 0.98612, 274, 12.5
    hyp.verification = "verified"
    row = debug_view.answer_row(hyp, "STATUS_FIX", "", 14.0)
    assert (row["p_correct"], row["inliers"], row["inlier_ratio"]) == ("0.9861", "274", "12.50")
    assert "p_correct 0.986, 274 inliers" in debug_view.caption(hyp, "STATUS_FIX", 14.0)[1]
    assert debug_view.winner_matches(None, None, hyp) is None  # nothing verified: no lines
    assert debug_view.match_pixels(None, (480, 640, 3), None) is None


@pytest.mark.fault("debug_strip_frame")
def test_a_strip_frame_stays_encodable_and_an_oversized_picture_fails_in_one_line(capfd):
    """Issue 28/29: a 10000x10 frame gave 'JPEG encoding failed' plus a raw OpenCV line. The
    panel is at most PANEL_MAX_WIDTH wide, so the picture encodes; a picture JPEG cannot hold
    is refused before OpenCV sees it, with one line naming its size."""
    import cv2
    import numpy as np

    from vlm_vpr_ros.errors import ImageDecodeError
    from vlm_vpr_ros.runtime import debug_view

    strip = np.full((10, 10000, 3), 200, np.uint8)
    pic = debug_view.render(strip, None, ["STATUS_NO_FIX", ""], "reference")
    assert pic.shape[0] == debug_view.PANEL_HEIGHT + debug_view.CAPTION_HEIGHT
    assert pic.shape[1] <= 2 * debug_view.PANEL_MAX_WIDTH
    data = debug_view.jpeg(pic)
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).shape == pic.shape
    with pytest.raises(ImageDecodeError, match=r"70000x2 picture"):
        debug_view.jpeg(np.zeros((2, 70000, 3), np.uint8))
    assert "imencode" not in capfd.readouterr().err
