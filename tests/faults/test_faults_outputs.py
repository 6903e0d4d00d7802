"""Images, bags, weights, output safety, partial results, full disk and kill -9: nothing the
user had is lost, every failure is one line (or a flagged row)."""

from __future__ import annotations

import csv
import errno
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from faults.conftest import exit2, sha_tree

FAST = ("--descriptor", "vlad_rootsift_fast", "--partition", "none")


def _subset(tmp_path, demo_data, n, name="c.csv"):
    rows = (demo_data / "coords.csv").read_text().splitlines()
    p = tmp_path / name
    p.write_text("\n".join(rows[: n + 1]) + "\n")
    return p, [r.split(",")[0] for r in rows[1: n + 1]]


def _png_header_only(w, h):
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


# -- images --------------------------------------------------------------------------------------
@pytest.mark.fault("image_tiny_reference")
def test_tiny_and_huge_reference_skipped(cli, tmp_path, demo_data):
    images = tmp_path / "images"
    shutil.copytree(demo_data / "images", images)
    coords, names = _subset(tmp_path, demo_data, 10)
    ok, buf = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))
    (images / names[0]).write_bytes(buf.tobytes())
    (images / names[1]).write_bytes(_png_header_only(10001, 10001))
    rc, out, _ = cli("build-map", "--images", images, "--coords", coords, "--out",
                     tmp_path / "m", *FAST)
    assert rc == 0 and "8 references" in out
    assert f"{images / names[0]}: unusable size 4x4 (too small" in cli.text
    assert f"{images / names[1]}: unusable size 10001x10001 (too large" in cli.text
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    assert ReferenceMap.load(tmp_path / "m").manifest["source"]["skipped"] == names[:2]


@pytest.mark.fault("image_huge_reference")
def test_huge_image_refused_before_decoding(monkeypatch):
    from vlm_vpr_ros.files import images as imageio
    from vlm_vpr_ros.errors import ImageDecodeError

    def no_decode(*a, **k):
        raise AssertionError("decoded a 1e8-pixel image")

    monkeypatch.setattr(imageio.cv2, "imdecode", no_decode)
    with pytest.raises(ImageDecodeError, match=r"big\.png: unusable size 20000x6000 \(too large"):
        imageio.decode_image_bytes(_png_header_only(20000, 6000), "big.png")


@pytest.mark.fault("image_truncated_query")
def test_truncated_query_flagged(cli, tmp_path, demo_data, demo_map):
    images = tmp_path / "q"
    images.mkdir()
    names = sorted(p.name for p in (demo_data / "images").iterdir())[:3]
    for n in names:
        shutil.copy(demo_data / "images" / n, images / n)
    data = (images / names[1]).read_bytes()
    (images / names[1]).write_bytes(data[: len(data) // 3])
    (tmp_path / "q.csv").write_text("file\n" + "\n".join(names) + "\n")
    rc, _, _ = cli("localize", "--map", demo_map, "--images", images, "--queries",
                   tmp_path / "q.csv", "--out", tmp_path / "r.csv")
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert rc == 0 and [r["file"] for r in rows] == names
    assert [bool(r["flags"]) for r in rows][1] and "image_error" in rows[1]["flags"]


@pytest.mark.fault("image_featureless_query")
def test_featureless_queries_are_never_fixes(cli, tmp_path, demo_map):
    """What a camera sends when it sees nothing (lens cap, overexposed, grey, a gradient, a
    4000x8 strip): `localize` answers every one, none with STATUS_FIX (issue 19's silently wrong
    case: before verification these were real places at 25 m, confidence 1.0)."""
    images = tmp_path / "q"
    images.mkdir()
    grad = np.repeat(np.linspace(0, 255, 640, dtype=np.uint8)[None, :, None], 480, 0)
    frames = {"black.png": np.zeros((480, 640, 3), np.uint8),
              "white.png": np.full((480, 640, 3), 255, np.uint8),
              "grey.png": np.full((480, 640, 3), 128, np.uint8),
              "gradient.png": np.repeat(grad, 3, 2),
              "strip.png": np.full((8, 4000, 3), 90, np.uint8)}
    for name, rgb in frames.items():
        cv2.imwrite(str(images / name), rgb)
    (tmp_path / "q.csv").write_text("file\n" + "\n".join(frames) + "\n")
    rc, _, _ = cli("localize", "--map", demo_map, "--images", images, "--queries",
                   tmp_path / "q.csv", "--out", tmp_path / "r.csv")
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert rc == 0 and sorted(r["file"] for r in rows) == sorted(frames)
    assert [r["status"] for r in rows] == ["no_fix"] * len(frames), rows
    assert all(float(r["uncertainty_m"]) > 1000 or "image_error" in r["flags"] for r in rows)


# -- bags --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_bag(tmp_path_factory, demo_data):
    from vlm_vpr_ros.bags.make import make_bag

    root = tmp_path_factory.mktemp("fault_bag")
    coords, _ = _subset(root, demo_data, 6)
    make_bag(demo_data / "images", coords, root / "bag", rate_hz=2.0, compressed=True,
             progress=False)
    return root / "bag"


def _eval(cli, bag, demo_map, out):
    return cli("evaluate-bag", bag, "--map", demo_map, "--out", out, "--no-plots")


@pytest.mark.fault("bag_mcap_truncated")
def test_mcap_truncated(cli, small_bag, demo_map, tmp_path):
    mcap = next(small_bag.glob("*.mcap"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: int(mcap.stat().st_size * 0.6)])
    rc, out, errors = _eval(cli, cut, demo_map, tmp_path / "ev")
    assert "Traceback" not in cli.text
    if rc == 0:
        import json
        s = json.loads((tmp_path / "ev" / "summary.json").read_text())
        assert s["details"]["bag_complete"] is False and 0 < s["details"]["frames"] < 6
    else:
        exit2((rc, out, errors))


@pytest.mark.parametrize("kind", [
    pytest.param("db3", marks=pytest.mark.fault("bag_db3_garbage"), id="bag_db3_garbage"),
    pytest.param("yaml", marks=pytest.mark.fault("bag_metadata_garbage"),
                 id="bag_metadata_garbage"),
])
def test_bag_garbage(cli, small_bag, demo_map, tmp_path, kind):
    bag = tmp_path / "b"
    if kind == "db3":
        bag.mkdir()
        (bag / "b_0.db3").write_bytes(b"not sqlite" + os.urandom(4000))
    else:
        shutil.copytree(small_bag, bag)
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n  : :")
    before = sha_tree(bag)
    res = _eval(cli, bag, demo_map, tmp_path / "ev")
    if kind == "db3":
        exit2(res)
        assert not (tmp_path / "ev").exists()
    else:  # metadata.yaml is optional: the frames are read from the .mcap itself
        import json

        assert res[0] == 0 and "Traceback" not in cli.text
        assert json.loads((tmp_path / "ev" / "summary.json").read_text())["details"][
            "frames"] == 6
    assert sha_tree(bag) == before


@pytest.mark.fault("weights_garbage")
def test_weights_garbage(cli, tmp_path):
    w = tmp_path / "w.pth"
    w.write_bytes(os.urandom(2048))
    exit2(cli("weights", "check", "cosplace", "--weights", w), str(w))


# -- output safety --------------------------------------------------------------------------------
@pytest.fixture
def user_docs(tmp_path):
    d = tmp_path / "docs"
    (d / "sub").mkdir(parents=True)
    (d / "thesis.tex").write_text("years of work")
    (d / "sub" / "data.bin").write_bytes(os.urandom(100))
    return d


@pytest.mark.fault("out_build_not_a_map")
def test_build_overwrite_refuses_non_map(cli, user_docs, demo_data, tmp_path):
    coords, _ = _subset(tmp_path, demo_data, 4)
    before = sha_tree(user_docs)
    msg = exit2(cli("build-map", "--images", demo_data / "images", "--coords", coords, "--out",
                    user_docs, "--overwrite", *FAST), "is not a map", "left untouched")
    msg = msg.replace(str(user_docs), "DIR")
    assert "overwrite" not in msg and "delete" not in msg and "remove" not in msg
    assert sha_tree(user_docs) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["c.csv", "docs"])


@pytest.mark.fault("out_build_fails_keeps_old")
def test_failed_rebuild_keeps_old_map(cli, map_copy, tmp_path, demo_data):
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    before = sha_tree(map_copy)
    empty = tmp_path / "empty"
    empty.mkdir()
    coords, _ = _subset(tmp_path, demo_data, 4)
    exit2(cli("build-map", "--images", empty, "--coords", coords, "--out", map_copy,
              "--overwrite", *FAST))  # every image is missing: the new build fails
    assert sha_tree(map_copy) == before and ReferenceMap.load(map_copy).n_references == 71


@pytest.mark.fault("out_bag_not_a_bag")
def test_bag_make_refuses_user_folder(cli, user_docs, demo_data, tmp_path):
    coords, _ = _subset(tmp_path, demo_data, 3)
    before = sha_tree(user_docs)
    msg = exit2(cli("bag", "make", "--images", demo_data / "images", "--coords", coords,
                    "--out", user_docs, "--overwrite"), "left untouched")
    msg = msg.replace(str(user_docs), "DIR")
    assert "delete" not in msg and "overwrite" not in msg
    assert sha_tree(user_docs) == before


@pytest.mark.fault("out_eval_into_bag")
def test_evaluate_bag_out_into_bag(cli, small_bag, demo_map, tmp_path):
    bag = tmp_path / "bag"
    shutil.copytree(small_bag, bag)
    before = sha_tree(bag)
    for out in (bag, bag / "eval", tmp_path):
        exit2(_eval(cli, bag, demo_map, out), "never written into inputs")
        assert sha_tree(bag) == before


@pytest.mark.fault("out_localize_file")
def test_localize_out_is_user_file(cli, demo_map, demo_data, queries, tmp_path):
    f = tmp_path / "notes.csv"
    f.write_text("name,phone\nann,123\n")
    before = sha_tree(f)
    for extra in ((), ("--overwrite",), ("--resume",)):
        exit2(cli("localize", "--map", demo_map, "--images", demo_data / "images", "--queries",
                  queries, "--out", f, *extra), "is not a results CSV")
        assert sha_tree(f) == before


@pytest.mark.fault("out_localize_exists")
def test_localize_existing_results(cli, demo_map, demo_data, queries, tmp_path):
    args = ("localize", "--map", demo_map, "--images", demo_data / "images", "--queries",
            queries, "--out", tmp_path / "r.csv")
    assert cli(*args)[0] == 0
    before = sha_tree(tmp_path / "r.csv")
    exit2(cli(*args), "already exists", "--resume", "--overwrite")
    assert sha_tree(tmp_path / "r.csv") == before
    assert cli(*args, "--resume")[0] == 0 and sha_tree(tmp_path / "r.csv") == before
    assert cli(*args, "--overwrite")[0] == 0


@pytest.mark.fault("out_out_is_file")
def test_out_is_a_file(cli, demo_data, tmp_path):
    coords, _ = _subset(tmp_path, demo_data, 3)
    f = tmp_path / "file"
    f.write_text("x")
    exit2(cli("build-map", "--images", demo_data / "images", "--coords", coords, "--out", f,
              *FAST), "is not a folder")
    exit2(cli("bag", "make", "--images", demo_data / "images", "--coords", coords, "--out", f),
          "is not a folder")
    assert f.read_text() == "x"


# -- partial results ------------------------------------------------------------------------------
def _rows(p):
    return list(csv.DictReader(Path(p).open()))


@pytest.mark.fault("partial_query_exception")
def test_query_exception_is_a_flagged_row(cli, demo_map, demo_data, queries, tmp_path,
                                          monkeypatch):
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    real = LocalizationPipeline.localize_descriptor
    calls = {"n": 0}

    def flaky(self, desc, prior=None, local=None):
        calls["n"] += 1
        if calls["n"] == 3:  # what an empty candidate list did in the localizer
            raise IndexError("index 0 is out of bounds for axis 0 with size 0")
        return real(self, desc, prior, local)

    monkeypatch.setattr(LocalizationPipeline, "localize_descriptor", flaky)
    rc, out, _ = cli("localize", "--map", demo_map, "--images", demo_data / "images",
                     "--queries", queries, "--out", tmp_path / "r.csv")
    rows = _rows(tmp_path / "r.csv")
    assert rc == 0 and len(rows) == 6
    assert rows[2]["flags"] == "error" and "IndexError" in rows[2]["prior_reason"]
    assert all(r["lat"] and r["flags"] != "error" for i, r in enumerate(rows) if i != 2)


@pytest.mark.fault("partial_interrupt_resume")
def test_interrupt_then_resume(cli, demo_map, demo_data, queries, tmp_path, monkeypatch):
    from vlm_vpr_ros.localization import batch

    args = ("localize", "--map", demo_map, "--images", demo_data / "images", "--queries",
            queries, "--priors", demo_data / "priors_osv5m_baseline.csv")
    assert cli(*args, "--out", tmp_path / "full.csv")[0] == 0
    real = batch.ResultsStream.write

    def interrupting(self, row):
        if len(self.rows) == 3:
            raise KeyboardInterrupt
        real(self, row)

    monkeypatch.setattr(batch.ResultsStream, "write", interrupting)
    out = tmp_path / "r.csv"
    assert cli(*args, "--out", out)[0] == 130
    assert not out.exists() and len(_rows(tmp_path / "r.csv.partial")) == 3
    exit2(cli(*args, "--out", out), "--resume")  # the partial file is not silently dropped
    monkeypatch.setattr(batch.ResultsStream, "write", real)
    rc, stdout, _ = cli(*args, "--out", out, "--resume")
    assert rc == 0 and "3 kept from the earlier run" in stdout
    assert not (tmp_path / "r.csv.partial").exists()
    strip = [{k: v for k, v in r.items() if not k.endswith(("_ms", "latency_s"))}
             for r in _rows(out)]
    assert strip == [{k: v for k, v in r.items() if not k.endswith(("_ms", "latency_s"))}
                     for r in _rows(tmp_path / "full.csv")]


# -- full disk ------------------------------------------------------------------------------------
class _FullDisk:
    """``os`` for one module, whose fsync fails with ENOSPC after ``after`` calls."""

    def __init__(self, after: int) -> None:
        self.after, self.calls = after, 0

    def __getattr__(self, name):
        return getattr(os, name)

    def fsync(self, fd):
        self.calls += 1
        if self.calls > self.after:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return os.fsync(fd)


@pytest.mark.fault("disk_full_build")
def test_disk_full_during_build(cli, map_copy, demo_data, tmp_path, monkeypatch, caplog):
    from vlm_vpr_ros.files import atomic
    from vlm_vpr_ros.mapping import build_images as map_build
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    monkeypatch.setattr(map_build, "CHUNK", 8)
    before = sha_tree(map_copy)
    # two fsyncs per file (the file, then its folder): job.json, fitted state, one chunk
    # (2 files) ... then full
    full = _FullDisk(after=8)
    monkeypatch.setattr(atomic, "os", full)
    coords, _ = _subset(tmp_path, demo_data, 24)
    args = ("build-map", "--images", demo_data / "images", "--coords", coords, "--out",
            map_copy, "--overwrite", *FAST)
    exit2(cli(*args), "No space left on device", "free some space")
    assert sha_tree(map_copy) == before  # the old map is untouched
    leftovers = [p for p in tmp_path.rglob("*") if ".tmp" in p.name]
    assert leftovers == []  # no .tmpNNNN files
    work = tmp_path / ".map.partial" / "work"
    assert (work / "descriptor_state.npz").exists()
    monkeypatch.setattr(atomic, "os", os)  # space freed
    rc, out, _ = cli(*args)
    assert rc == 0 and "resuming the partial build" in cli.text
    assert ReferenceMap.load(map_copy).partition_method == "none"
    assert not (tmp_path / ".map.partial").exists()


@pytest.mark.fault("disk_full_localize")
def test_disk_full_while_streaming(cli, demo_map, demo_data, queries, tmp_path, monkeypatch):
    from vlm_vpr_ros.localization import batch

    real = batch.ResultsStream.write

    def full(self, row):
        if len(self.rows) == 4:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(self, row)

    monkeypatch.setattr(batch.ResultsStream, "write", full)
    args = ("localize", "--map", demo_map, "--images", demo_data / "images", "--queries",
            queries, "--out", tmp_path / "r.csv")
    exit2(cli(*args), "No space left on device", "4 rows kept", "--resume")
    monkeypatch.setattr(batch.ResultsStream, "write", real)
    assert cli(*args, "--resume")[0] == 0 and len(_rows(tmp_path / "r.csv")) == 6


@pytest.mark.fault("kill9_build_resume")
def test_kill9_mid_build_then_resume(tmp_path, demo_data):
    out = tmp_path / "m"
    coords, _ = _subset(tmp_path, demo_data, 30)
    cmd = [sys.executable, "-m", "vlm_vpr_ros.cli", "-v", "build-map", "--images",
           demo_data / "images", "--coords", coords, "--out", out, *FAST]
    cmd = [str(c) for c in cmd]
    state = tmp_path / ".m.partial" / "work" / "descriptor_state.npz"
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not state.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(10) == -signal.SIGKILL and state.exists()
    assert not out.exists()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "resumed fitted descriptor state" in done.stderr
    assert "Traceback" not in done.stderr
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    assert ReferenceMap.load(out).n_references == 30
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv", "m"]


@pytest.mark.fault("bag_flipped_byte_ours")
def test_a_flipped_byte_in_our_bag_is_detected(small_bag, tmp_path):
    """Before: `bag make` wrote chunk CRC 0 ("not computed"): a flipped byte went unseen."""
    from vlm_vpr_ros.bags.reader import open_bag

    mcap = next(small_bag.glob("*.mcap"))
    full = [m.data for m in open_bag(mcap).messages()]
    data = bytearray(mcap.read_bytes())
    data[len(data) // 3] ^= 0x01  # inside the (first) chunk: a JPEG byte
    flipped = tmp_path / "flip.mcap"
    flipped.write_bytes(bytes(data))
    bag = open_bag(flipped)
    got = [m.data for m in bag.messages()]
    assert not bag.complete and len(got) < len(full) and bag.problems
    assert got == full[:len(got)]  # what was read before the damage, never a garbled frame
