"""``evaluate-bag``: frames read from a bag give exactly what ``localize`` gives on the image
files; ground-truth pairing; bad encodings and truncated bags keep partial results."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from vlm_vpr_ros.bags.evaluate import BagEvalConfig, evaluate_bag
from vlm_vpr_ros.bags.make import make_bag
from vlm_vpr_ros.bags.messages import IMAGE, NAVSATFIX, image_msg, navsatfix_msg
from vlm_vpr_ros.bags.reader import deserialize, open_bag
from vlm_vpr_ros.bags.writer import BagWriter, bag_files
from vlm_vpr_ros.errors import BagError
from vlm_vpr_ros.priors import create_prior_provider
from msg_adapters.navsat import K68, K95

N = 12
T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def queries(demo_data, tmp_path_factory) -> Path:
    lines = (demo_data / "coords.csv").read_text().splitlines()
    idx = [0] + list(range(1, len(lines), (len(lines) - 1) // N))[:N]
    path = tmp_path_factory.mktemp("q") / "queries.csv"
    path.write_text("\n".join(lines[i] for i in idx) + "\n")
    return path


@pytest.fixture(scope="module")
def pipe(demo_map):
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    return LocalizationPipeline.open(demo_map)


@pytest.fixture(scope="module")
def cbag(demo_data, queries, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("cb") / "bag"
    make_bag(demo_data / "images", queries, out, rate_hz=2.0, compressed=True,
             start_time_ns=T0, progress=False)
    return out


def _priors(demo_data):
    return create_prior_provider("recorded",
                                 {"path": str(demo_data / "priors_osv5m_baseline.csv")})


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def test_bag_equals_localize_on_files(cbag, pipe, demo_data, queries, tmp_path):
    from vlm_vpr_ros.localization.batch import localize_files
    from vlm_vpr_ros.evaluation.results_csv import evaluate_results_csv
    from vlm_vpr_ros.files.csvio import read_file_column
    from vlm_vpr_ros.files.csvio import write_csv_atomic
    from vlm_vpr_ros.localization.batch import RESULT_FIELDS

    res = evaluate_bag(open_bag(cbag), pipe, _priors(demo_data), tmp_path / "ev",
                       progress=False)
    files = read_file_column(queries)
    ref = list(localize_files(pipe, _priors(demo_data), demo_data / "images", files))
    write_csv_atomic(tmp_path / "ref.csv", RESULT_FIELDS, ref)
    ref_summary, _ = evaluate_results_csv(tmp_path / "ref.csv", queries)
    rows = _rows(tmp_path / "ev" / "frames.csv")
    assert [r["key"] for r in rows] == files  # frames.csv of bag make maps stamps to files
    for r, q in zip(rows, ref):
        for k in ("lat", "lon", "ref_id", "submap", "prior_lat", "flags", "uncertainty_m"):
            assert r[k] == q[k], k
    assert {k: res[k] for k in ("n", "accuracy", "median_km")} == ref_summary
    d = res["details"]
    assert (d["frames"], d["frames_scored"], d["frames_failed"]) == (len(files), len(files), 0)
    assert d["bag_complete"] and json.loads((tmp_path / "ev/summary.json").read_text()) == res
    for key in ("world_map_png", "error_cdf_png"):
        assert Path(d["outputs"][key]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    est = open_bag(d["outputs"]["estimates_bag"])
    fixes = [(m.log_time_ns, deserialize(m)) for m in est.messages(["/vlm_vpr/fix"])]
    assert [t for t, _ in fixes] == [T0 + i * 500_000_000 for i in range(len(files))]
    assert [(f"{m.latitude:.7f}", f"{m.longitude:.7f}") for _, m in fixes] == \
        [(r["lat"], r["lon"]) for r in rows]
    for (_, m), r in zip(fixes, rows):  # the node's NavSatFix policy (msg_adapters.navsat)
        sigma = max(float(r["uncertainty_m"]) / K68, float(r["radius95_m"]) / K95)
        assert m.status.status == (0 if r["status"] == "fix" else -1)  # the core's status rule
        assert r["status"] != "fix" or sigma <= 50.0
        # radii in the CSV have 0.1 m: a verified fix's ~21 m radius carries ~0.5 % rounding
        assert m.position_covariance[0] == pytest.approx(sigma ** 2, rel=1e-2)
    assert est.topics["/vlm_vpr/ground_truth"].count == len(files)


def _custom_bag(path: Path, frames: list[tuple[str, np.ndarray]], gt_offset_ns: int = 0,
                demo_coords: list | None = None) -> Path:
    with BagWriter(path) as bag:
        bag.add_topic("/cam/image_raw", IMAGE)
        bag.add_topic("/fix", NAVSATFIX)
        for i, (enc, rgb) in enumerate(frames):
            t = T0 + i * 1_000_000_000
            lat, lon = demo_coords[i] if demo_coords else (10.0 + i, 20.0)
            bag.write("/fix", navsatfix_msg(lat, lon, t + gt_offset_ns), t + gt_offset_ns)
            msg = image_msg(rgb, t)
            if enc == "bgr8":
                msg.encoding = "bgr8"
                msg.data = np.ascontiguousarray(rgb[:, :, ::-1]).tobytes()
            elif enc != "rgb8":
                msg.encoding = enc
            bag.write("/cam/image_raw", msg, t)
    return path


def test_unsupported_encoding_keeps_other_frames(pipe, demo_data, tmp_path):
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    rows = read_coords_csv(demo_data / "coords.csv")[:4]
    imgs = [load_image(demo_data / "images" / f) for f, _, _ in rows]
    frames = [("rgb8", imgs[0]), ("32FC1", imgs[1]), ("bgr8", imgs[2]), ("32FC1", imgs[3])]
    bag = _custom_bag(tmp_path / "mixed", frames, demo_coords=[(a, b) for _, a, b in rows])
    res = evaluate_bag(open_bag(bag), pipe, create_prior_provider("none"), tmp_path / "ev",
                       progress=False)
    d = res["details"]
    assert (d["frames"], d["frames_failed"], res["n"]) == (4, 2, 4)
    out = _rows(tmp_path / "ev" / "frames.csv")
    assert [r["flags"] == "image_error" for r in out] == [False, True, False, True]
    assert "unsupported Image encoding '32FC1'" in out[1]["prior_reason"]
    # bgr8 is decoded to the same pixels: the frame localizes exactly like its rgb8 twin
    direct = pipe.localize_image(imgs[2])
    assert out[2]["ref_id"] == direct.ref_id and out[2]["lat"] == f"{direct.lat:.7f}"
    assert res["accuracy"]["2500km"] <= 50.0  # the failed frames count as misses
    bad = _custom_bag(tmp_path / "allbad", [("32FC1", imgs[0]), ("16UC3", imgs[1])])
    with pytest.raises(BagError, match=r"none of the 2 frames.*unsupported Image encoding"):
        evaluate_bag(open_bag(bad), pipe, create_prior_provider("none"), tmp_path / "ev2",
                     progress=False)
    assert len(_rows(tmp_path / "ev2" / "frames.csv")) == 2  # per-frame reasons are kept


def test_ground_truth_pairing_gap(pipe, tmp_path):
    rng = np.random.default_rng(0)
    frames = [("rgb8", rng.integers(0, 255, (64, 80, 3), dtype=np.uint8)) for _ in range(3)]
    bag = open_bag(_custom_bag(tmp_path / "gap", frames, gt_offset_ns=300_000_000))
    none = create_prior_provider("none")
    res = evaluate_bag(bag, pipe, none, tmp_path / "a", BagEvalConfig(max_gt_gap_s=0.1),
                       progress=False)
    assert res["n"] == 0 and res["details"]["frames_without_gt"] == 3
    res = evaluate_bag(bag, pipe, none, tmp_path / "b", BagEvalConfig(max_gt_gap_s=0.5),
                       progress=False, plots=False)
    rows = _rows(tmp_path / "b" / "frames.csv")
    assert res["n"] == 3 and [r["gt_gap_s"] for r in rows] == ["0.300"] * 3
    assert [float(r["gt_lat"]) for r in rows] == [10.0, 11.0, 12.0]


def test_truncated_bag_partial_results(pipe, demo_data, tmp_path):
    lines = (demo_data / "coords.csv").read_text().splitlines()[:6]
    (tmp_path / "c.csv").write_text("\n".join(lines) + "\n")
    raw = make_bag(demo_data / "images", tmp_path / "c.csv", tmp_path / "raw", rate_hz=2.0,
                   start_time_ns=T0, progress=False)["bag"]  # 1 MB frames: a chunk each
    data = bag_files(raw)[0].read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[:int(len(data) * 0.6)])
    res = evaluate_bag(open_bag(tmp_path / "cut.mcap"), pipe, create_prior_provider("none"),
                       tmp_path / "ev", progress=False)
    d = res["details"]
    assert not d["bag_complete"] and "truncated" in " ".join(d["warnings"])
    assert 1 <= d["frames"] < 5 and res["n"] == d["frames"]
    assert len(_rows(tmp_path / "ev" / "frames.csv")) == d["frames"]


def test_cli_json_only_and_max_frames(cbag, demo_map, demo_data, tmp_path, capsys):
    from vlm_vpr_ros.cli import main

    rc = main(["evaluate-bag", str(cbag), "--map", str(demo_map), "--out", str(tmp_path / "e"),
               "--priors", str(demo_data / "priors_osv5m_baseline.csv"), "--max-frames", "3",
               "--json", "--no-plots"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)  # stdout is exactly one JSON object
    assert out["n"] == 3 and set(out["accuracy"]) == {"1km", "25km", "200km", "750km",
                                                       "2500km"}
    assert "world_map_png" not in out["details"]["outputs"]


def test_run_bag_demo(demo_map, demo_data, queries, tmp_path):
    from vlm_vpr_ros.bags.bag_demo import run_bag_demo

    info = run_bag_demo(tmp_path / "demo", demo_map, demo_data / "images", queries,
                        demo_data / "priors_osv5m_baseline.csv")
    for key in ("bag", "frames_csv", "world_map_png", "error_cdf_png", "estimates_bag"):
        assert Path(info[key]).exists(), key
    frames = _rows(Path(info["frames_csv"]))
    assert info["summary"]["n"] == len(frames)
    # the fix rate counts the frames published as STATUS_FIX; each is the query's own place
    fixes = [r for r in frames if r["status"] == "fix"]
    assert info["summary"]["fixes"]["n"] == len(fixes) > 0
    assert all(float(r["error_km"]) * 1000 <= 25 for r in fixes)
    # a second run replaces its own evaluation (every `make demo` after the first does this)
    again = run_bag_demo(tmp_path / "demo", demo_map, demo_data / "images", queries,
                         demo_data / "priors_osv5m_baseline.csv")
    assert again["summary"] == info["summary"]


def test_frames_csv_stamps_are_exact(demo_data, queries, pipe, tmp_path):
    """Stamps whose nanoseconds a float cannot hold (…712635803 became …712635994) are written
    exactly, as ``sec.nanosec`` and integer ns, and join with the bag's own frames.csv."""
    start = 1_795_391_409_712_635_803
    assert int(start / 1e9 * 1e9) != start  # the old float path would change it
    bag = tmp_path / "bag"
    make_bag(demo_data / "images", queries, bag, rate_hz=3.0, start_time_ns=start,
             progress=False)
    evaluate_bag(open_bag(bag), pipe, create_prior_provider("none", {}), tmp_path / "ev",
                 BagEvalConfig(max_frames=3), progress=False, plots=False)
    rows = _rows(tmp_path / "ev" / "frames.csv")
    made = {int(r["stamp_ns"]) for r in _rows(bag / "frames.csv")}
    assert rows[0]["stamp"] == "1795391409.712635803"
    assert rows[0]["stamp_ns"] == str(start)
    for r in rows:
        sec, nsec = r["stamp"].split(".")
        assert int(sec) * 1_000_000_000 + int(nsec) == int(r["stamp_ns"])
        assert int(r["stamp_ns"]) in made
