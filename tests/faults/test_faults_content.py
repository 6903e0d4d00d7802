"""Map content that changed with the same sizes: files swapped between submaps, rewritten in
place before or while a process uses the map. Refused (exit 2 naming the file, or a failed,
counted query), never a confident answer from the wrong data."""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest

from faults.conftest import copy_refs, exit2

N = 200  # references per submap: 400 KB flat index files (checked by sampled pages)
PLACES = [(48.8566, 2.3522), (-33.8688, 151.2093)]  # Paris, Sydney: ~16,950 km apart


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    """A v2 map of two K-means submaps of equal size (equal file sizes), its query
    descriptors and the query CSV."""
    from vlm_vpr_ros.mapping.build_descriptors import build_from_descriptors

    root = tmp_path_factory.mktemp("twin")
    rng = np.random.default_rng(7)
    coords = np.concatenate([np.asarray(c) + rng.normal(0, 0.01, (N, 2)) for c in PLACES])
    desc = rng.normal(size=(2 * N, 512)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    np.save(root / "desc.npy", desc)
    ids = [f"{'ps'[i // N]}{i % N:04d}.jpg" for i in range(2 * N)]
    (root / "coords.csv").write_text("file,lat,lon\n" + "".join(
        f"{f},{a:.8f},{b:.8f}\n" for f, (a, b) in zip(ids, coords)))
    build_from_descriptors(root / "desc.npy", root / "coords.csv", root / "map", "cosplace",
                           clusters=2, index="flat", progress=False)
    q = [3, N + 5]  # one query in each city: the reference itself
    np.save(root / "q.npy", desc[q])
    (root / "q.csv").write_text("file,lat,lon\n" + "".join(
        f"q{i}.jpg,{coords[i][0]:.8f},{coords[i][1]:.8f}\n" for i in q))
    return root, desc, coords


def _copy(twin, tmp_path):
    dst = tmp_path / "map"
    shutil.copytree(twin[0] / "map", dst)
    return dst, json.loads((dst / "manifest.json").read_text())


def _localize(cli, m, root, tmp_path):
    return cli("localize", "--map", m, "--query-descriptors", root / "q.npy", "--queries",
               root / "q.csv", "--out", tmp_path / "r.csv")


@pytest.mark.fault("map_submaps_swapped")
def test_files_swapped_between_submaps(cli, twin, tmp_path):
    root = twin[0]
    m, man = _copy(twin, tmp_path)
    assert [s["count"] for s in man["submaps"]] == [N, N]
    assert _localize(cli, m, root, tmp_path)[0] == 0
    rows = (tmp_path / "r.csv").read_text().splitlines()
    assert len(rows) == 3
    (tmp_path / "r.csv").unlink()
    a, b = (s["files"] for s in man["submaps"])
    for role in ("index", "coords", "ids"):
        pa, pb = m / a[role], m / b[role]
        assert pa.stat().st_size == pb.stat().st_size  # sizes alone cannot tell
        pa.rename(m / "tmp")
        pb.rename(pa)
        (m / "tmp").rename(pb)
        exit2(_localize(cli, m, root, tmp_path), a[role], "does not match the manifest")
        assert not (tmp_path / "r.csv").exists()
        pa.rename(m / "tmp")  # swap back for the next role
        pb.rename(pa)
        (m / "tmp").rename(pb)
    assert _localize(cli, m, root, tmp_path)[0] == 0


@pytest.mark.fault("map_rewritten_in_place")
def test_rewritten_in_place_while_open(twin, tmp_path):
    """A coordinates file rewritten in place (same size, other places) under a running process:
    the next query that needs that submap fails, naming the file, and keeps failing (refused
    until reloaded); a reload refuses the map; a file only touched is fine."""
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    _, desc, coords = twin
    m, man = _copy(twin, tmp_path)
    loc = Localizer(ReferenceMap.load(m), LocalizerConfig())
    hyp = loc.localize(desc[3])
    assert abs(hyp.lat - coords[3][0]) < 1e-6
    paris = next(s for s in man["submaps"] if s["centroid"][0] > 0)
    path = m / paris["files"]["coords"]
    time.sleep(0.05)
    path.touch()  # a new modification time, the same bytes: still used
    assert abs(loc.localize(desc[3]).lat - coords[3][0]) < 1e-6
    time.sleep(0.05)
    arr = np.load(path)
    with open(path, "r+b") as fh:  # in place: same inode, same size, Sydney's coordinates
        fh.seek(path.stat().st_size - arr.nbytes)
        fh.write(np.ascontiguousarray(arr + np.array([-82.7, 148.9])).tobytes())
    for _ in range(2):
        with pytest.raises(MapError, match="does not match the manifest since the map was "
                                           "opened.*refused until the map is reloaded"):
            loc.localize(desc[3])
    with pytest.raises(MapError, match=paris["files"]["coords"]):
        ReferenceMap.load(m)


@pytest.mark.fault("map_garbage_in_place_node")
def test_node_counts_garbage_map_files_as_query_errors(demo_map, demo_data, tmp_path):
    """The node's query worker on a map whose index files are overwritten in place with garbage
    of the same size: each query fails (counted in query_errors, no fix, never NaN), and
    map_reload refuses the map (the current map stays)."""
    import threading

    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.priors import create_prior_provider
    from vlm_vpr_ros.runtime.worker import Frame, QueryRuntime, RuntimeConfig

    m = tmp_path / "map"
    shutil.copytree(demo_map, m)
    man = json.loads((m / "manifest.json").read_text())
    outcomes, got = [], threading.Event()

    def on_outcome(o):
        outcomes.append(o)
        got.set()

    rt = QueryRuntime(LocalizationPipeline.open(m), create_prior_provider("none"),
                      RuntimeConfig(mode="on_trigger"), decode=lambda msg: msg,
                      on_outcome=on_outcome)
    rgb = load_image(sorted((demo_data / "images").iterdir())[0])
    rt.start()
    try:
        def query():
            got.clear()
            rt.on_frame(Frame(rgb, time.time_ns(), "camera"))
            rt.request_relocalize()
            assert got.wait(60)
            return outcomes[-1]

        first = query()
        assert first.hypothesis is not None and np.isfinite(first.hypothesis.lat)
        time.sleep(0.05)
        rng = np.random.default_rng(0)
        for s in man["submaps"]:
            p = m / s["files"]["index"]
            with open(p, "r+b") as fh:
                fh.write(rng.bytes(p.stat().st_size))
        for _ in range(2):
            bad = query()
            assert bad.hypothesis is None and "does not match the manifest" in bad.error
        assert rt.stats.snapshot()["query_errors"] == 2
        ok, msg = rt.reload_map()
        assert not ok and "does not match the manifest" in msg
        assert rt.stats.snapshot()["map_reload_failures"] == 1
    finally:
        rt.stop()


@pytest.mark.fault("map_old_no_fingerprints")
def test_maps_written_before_fingerprints_still_open(twin, tmp_path, caplog):
    """A map written before fingerprints: it opens; small files are still checked whole (their
    sha256), large ones by size, and the log says so."""
    import logging

    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    m, man = _copy(twin, tmp_path)
    for meta in man["files"].values():
        meta.pop("sample", None)
    (m / "manifest.json").write_text(json.dumps(man))
    with caplog.at_level(logging.INFO):
        assert ReferenceMap.load(m).n_references == 2 * N
    assert "written before content fingerprints" in caplog.text
    a, b = (s["files"] for s in man["submaps"])
    (m / a["coords"]).write_bytes((m / b["coords"]).read_bytes())  # small: still caught
    with pytest.raises(MapError, match="does not match the manifest"):
        ReferenceMap.load(m)


@pytest.mark.fault("map_small_files_edited")
def test_state_and_calibration_edited_in_place(map_copy):
    """descriptor_state.npz and calibration.json rewritten with the same size: refused at
    open, naming the file."""
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    for rel in ("descriptor_state.npz", "calibration.json"):
        p = map_copy / rel
        good = p.read_bytes()
        bad = bytearray(good)
        bad[len(bad) // 2] ^= 0x01
        p.write_bytes(bytes(bad))
        with pytest.raises(MapError, match=f"{rel} does not match the manifest"):
            ReferenceMap.load(map_copy)
        p.write_bytes(good)
    ReferenceMap.load(map_copy)


@pytest.mark.fault("map_sample_field_type")
def test_fingerprint_field_of_another_type(cli, twin, tmp_path):
    root = twin[0]
    m, man = _copy(twin, tmp_path)
    rel = next(r for r, meta in man["files"].items() if "sample" in meta)
    man["files"][rel]["sample"] = 123
    (m / "manifest.json").write_text(json.dumps(man))
    exit2(_localize(cli, m, root, tmp_path), f"files[{rel!r}].sample", "must be a string")


@pytest.mark.fault("map_refused_until_reload")
def test_refused_submap_comes_back_after_repair_and_reload(twin, tmp_path):
    """Refused since a rewrite, the submap stays refused in that process even when the bytes
    are put back; reloading the repaired map serves it again."""
    from vlm_vpr_ros.errors import MapError
    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    _, desc, coords = twin
    m, man = _copy(twin, tmp_path)
    loc = Localizer(ReferenceMap.load(m), LocalizerConfig())
    idx = m / man["submaps"][0]["files"]["index"]
    good = idx.read_bytes()
    time.sleep(0.05)
    with open(idx, "r+b") as fh:  # garbage over the last page, in place
        fh.seek(len(good) - 4096)
        fh.write(np.random.default_rng(1).bytes(4096))
    with pytest.raises(MapError, match="refused until the map is reloaded"):
        loc.localize(desc[3])
    with open(idx, "r+b") as fh:
        fh.write(good)
    with pytest.raises(MapError, match="refused until the map is reloaded"):
        loc.localize(desc[3])
    loc = Localizer(ReferenceMap.load(m), LocalizerConfig())
    assert abs(loc.localize(desc[3]).lat - coords[3][0]) < 1e-6


@pytest.mark.fault("map_live_edit_not_refused")
def test_map_add_under_an_open_map_is_not_a_content_change(map_copy, demo_data, tmp_path):
    """`map add` writes new generation files and keeps the old ones: a process that opened the
    map before (some submaps open, some not) keeps answering, nothing is refused; a reload
    sees the new references."""
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.mapping.edit import add_references

    pipe = LocalizationPipeline.open(map_copy)
    pipe.map.submaps[0].opened()  # one open, the others not yet
    rows = copy_refs(demo_data, tmp_path / "new", 8)
    time.sleep(0.05)
    add_references(map_copy, tmp_path / "new", rows, progress=False)
    rgb = load_image(tmp_path / "new" / rows[0][0])
    hyp = pipe.localize_image(rgb)
    assert np.isfinite(hyp.lat) and hyp.ref_id
    assert pipe.reloaded().map.n_references == 79


@pytest.mark.fault("map_document_rewrite_killed")
def test_calibration_rewrite_killed_before_the_manifest(map_copy, monkeypatch):
    """Ctrl-C between a rewritten calibration and the manifest (``calibrate``, the
    recalibration after ``map add``): the map still opens with the previous calibration; a
    rewrite never touches a listed file, and the replaced one stays one generation."""
    from vlm_vpr_ros.localization.fusion.calibration import load_calibration, save_calibration
    from vlm_vpr_ros.maps import documents
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    m = ReferenceMap.load(map_copy)
    first = m.manifest["calibration"]
    assert first == "calibration.json"  # a fresh build: the plain name (old maps load alike)
    old = load_calibration(m)
    new = dict(old, beta=float(old["beta"]) * 2)
    real = documents.atomic_write_json

    def killed(path, obj, *a, **k):
        if str(path).endswith("manifest.json"):
            raise KeyboardInterrupt
        return real(path, obj, *a, **k)

    monkeypatch.setattr(documents, "atomic_write_json", killed)
    with pytest.raises(KeyboardInterrupt):
        save_calibration(m, new)
    monkeypatch.setattr(documents, "atomic_write_json", real)
    again = ReferenceMap.load(map_copy)  # before the fix: "does not match the manifest"
    assert load_calibration(again) == old
    save_calibration(again, new)
    now = ReferenceMap.load(map_copy, verify=True)
    second = now.manifest["calibration"]
    assert second != first and load_calibration(now) == new
    assert now.manifest["retired"] == [first] and (map_copy / first).is_file()
    save_calibration(now, old)  # the next rewrite deletes the one retired before
    last = ReferenceMap.load(map_copy, verify=True)
    assert last.manifest["retired"] == [second] and not (map_copy / first).exists()
    assert load_calibration(last) == old and first not in last.manifest["files"]


@pytest.mark.fault("localize_resume_descriptors")
def test_resume_with_query_descriptors(cli, twin, tmp_path):
    """`localize --resume --query-descriptors` (one pass, nothing streamed to resume): exit 2
    naming --resume; an --overwrite run leaves no stale RESULTS.csv.partial behind."""
    root = twin[0]
    partial = tmp_path / "r.csv.partial"
    partial.write_text("file,lat,lon\n")  # an interrupted --images run
    args = ("localize", "--map", root / "map", "--query-descriptors", root / "q.npy",
            "--queries", root / "q.csv", "--out", tmp_path / "r.csv")
    exit2(cli(*args, "--resume"), "--resume", "--query-descriptors")
    assert not (tmp_path / "r.csv").exists() and partial.exists()
    assert cli(*args, "--overwrite")[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv"]
