"""Map format v2 (issue 11): mmap'd lazy submaps, index kinds, v1 compatibility, the
descriptors import (single file, shards, Parquet, bad input), query-descriptor localization,
balanced submaps, map info/verify and files truncated after the map was opened."""

import csv
import json
import os
import shutil

import numpy as np
import pytest

from vlm_vpr_ros.cli import main
from vlm_vpr_ros.errors import DataError, MapError
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.mapping import build_descriptors as mbuild
from vlm_vpr_ros.mapping.build_descriptors import build_from_descriptors
from vlm_vpr_ros.priors.provider import Prior, PriorResult

IDENT = {"name": "synthetic", "dim": 32, "config": {}, "preprocessing": {}}


def clustered(n, dim, seed=0, centres=40, noise=0.8):
    """Clustered unit descriptors (near neighbours are nearly tied: hard for PQ)."""
    rng = np.random.default_rng(seed)
    c = rng.normal(size=(centres, dim)).astype(np.float32)
    x = c[rng.integers(0, centres, n)] + noise * rng.normal(size=(n, dim)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    pos = np.stack([rng.uniform(-50, 60, n), rng.uniform(-170, 170, n)], 1)
    return x, pos


def exact(db, q, k):
    d = ((db - q) ** 2).sum(1)
    o = np.argsort(d, kind="stable")[:k]
    return o, d[o]


def write_coords(path, ids, pos):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "lat", "lon"])
        for i, (la, lo) in zip(ids, pos):
            w.writerow([i, f"{la:.6f}", f"{lo:.6f}"])


@pytest.fixture(scope="module")
def ref512(tmp_path_factory):
    """3,000 clustered 512-D descriptors (cosplace's dim) at random positions, as files."""
    d = tmp_path_factory.mktemp("ref512")
    x, pos = clustered(3000, 512, seed=3)
    ids = [f"img/{i:05d}.jpg" for i in range(len(x))]
    np.save(d / "desc.npy", x)
    write_coords(d / "coords.csv", ids, pos)
    return d, x, pos, ids


def test_v2_round_trip_is_lazy_mmapped_and_equals_brute_force(tmp_path):
    x, pos = clustered(600, 32)
    ids = [f"r{i}" for i in range(len(x))]
    for kind in ("flat", "fp16"):
        m = assemble_map(x, pos, ids, IDENT, {}, "kmeans", 5, index=kind)
        m.save(tmp_path / kind)
        man = json.loads((tmp_path / kind / "manifest.json").read_text())
        assert man["version"] == 2 and {s["kind"] for s in man["submaps"]} == {kind}
        loaded = ReferenceMap.load(tmp_path / kind)
        assert not any(s.is_open for s in loaded.submaps)  # nothing read at open
        loc = Localizer(loaded)
        db = x if kind == "flat" else x.astype(np.float16).astype(np.float32)
        rng = np.random.default_rng(1)
        for _ in range(5):
            q = rng.normal(size=32).astype(np.float32)
            got = loc.search(q, list(range(len(loaded.submaps))), 20)
            rows, d = exact(db, q, 20)
            assert [c.ref_id for c in got] == [ids[r] for r in rows]
            np.testing.assert_allclose([c.l2_sq for c in got], d, rtol=1e-4, atol=1e-5)
            assert all(tuple(pos[int(c.ref_id[1:])]) == pytest.approx((c.lat, c.lon))
                       for c in got)
        sub = loaded.submaps[0]
        assert isinstance(sub.coords, np.ndarray) and sub.coords.base is not None  # a mapping
        assert sub.is_open and not loaded.submaps[-1].is_open or len(loaded.submaps) == 1 or \
            all(s.is_open for s in loaded.submaps)


def test_pq_recall_vs_exact_and_exact_rerank_distances(tmp_path):
    x, pos = clustered(6000, 64, seed=2)
    ids = [f"r{i}" for i in range(len(x))]
    m = assemble_map(x, pos, ids, dict(IDENT, dim=64), {}, "none", index="pq", rerank_factor=8)
    m.save(tmp_path / "pq")
    m = ReferenceMap.load(tmp_path / "pq")
    sub = m.submaps[0]
    assert sub.kind == "pq" and type(sub.index).__name__ == "IndexPQFastScan"
    assert sub.recall["recall_at_50"] >= 0.95  # measured at build, stored in the manifest
    x16 = x.astype(np.float16).astype(np.float32)
    rng = np.random.default_rng(7)
    r1 = r50 = 0.0
    for _ in range(40):
        a, b = rng.integers(0, len(x), 2)
        q = (x[a] + 0.5 * (x[b] - x[a]) * rng.uniform(0.2, 1)).astype(np.float32)
        got = Localizer(m).search(q, [0], 50)
        rows, _ = exact(x, q, 50)
        got_rows = [int(c.ref_id[1:]) for c in got]
        r1 += got_rows[0] == rows[0]
        r50 += len(set(got_rows) & set(rows.tolist())) / 50
        # re-ranked distances are the exact L2 to the fp16 vectors
        np.testing.assert_allclose([c.l2_sq for c in got],
                                   ((x16[got_rows] - q) ** 2).sum(1), rtol=1e-5, atol=1e-6)
    assert r1 / 40 >= 0.97 and r50 / 40 >= 0.97
    # a wider re-rank can only help; factor 1 = PQ order alone is clearly worse
    m.rerank_factor = 1
    low = np.mean([len({int(c.ref_id[1:]) for c in Localizer(m).search(x[i] + 0.01, [0], 50)}
                       & set(exact(x, x[i] + 0.01, 50)[0].tolist())) / 50 for i in range(10)])
    assert low < r50 / 40


def test_auto_index_respects_ram_budget_and_records_choice(tmp_path):
    x, pos = clustered(4000, 32, seed=4)
    ids = [f"r{i}" for i in range(len(x))]
    m = assemble_map(x, pos, ids, IDENT, {}, "kmeans", 4, index="auto", ram_budget_mb=0.3)
    from vlm_vpr_ros.maps.indexes import ram_bytes

    assert sum(ram_bytes(s.kind, s.count, 32) for s in m.submaps) <= 0.3 * 2 ** 20
    assert {s.kind for s in m.submaps} - {"flat"}  # something had to be downgraded
    m.save(tmp_path / "a")
    man = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert man["index"] == "auto"
    for e in man["submaps"]:
        assert e["kind"] in ("flat", "fp16", "pq")
        assert (e["kind"] == "flat") == ("recall" not in e)
    big = assemble_map(x, pos, ids, IDENT, {}, "kmeans", 4, index="auto", ram_budget_mb=100)
    assert {s.kind for s in big.submaps} == {"flat"}


def test_v1_maps_still_load_and_upgrade_to_v2(tmp_path, capsys):
    x, pos = clustered(500, 32, seed=5)
    ids = [f"r{i}" for i in range(len(x))]
    m = assemble_map(x, pos, ids, IDENT, {}, "kmeans", 4)
    m.save_v1(tmp_path / "v1")
    assert json.loads((tmp_path / "v1" / "manifest.json").read_text())["version"] == 1
    v1 = ReferenceMap.load(tmp_path / "v1", verify=True)
    q = np.random.default_rng(2).normal(size=32).astype(np.float32)
    want = [c.ref_id for c in Localizer(v1).search(q, list(range(len(v1.submaps))), 10)]
    assert want == [ids[r] for r in exact(x, q, 10)[0]]
    assert main(["map", "upgrade", str(tmp_path / "v1"), "--out", str(tmp_path / "v2")]) == 0
    v2 = ReferenceMap.load(tmp_path / "v2")
    assert v2.manifest["version"] == 2 and [s.id for s in v2.submaps] == [s.id for s in
                                                                            v1.submaps]
    assert [c.ref_id for c in Localizer(v2).search(q, list(range(len(v2.submaps))), 10)] == want
    assert main(["map", "upgrade", str(tmp_path / "v1"), "--out", str(tmp_path / "v2")]) == 2


def test_upgrade_to_another_index_keeps_calibrations_and_local_features(demo_map, demo_data,
                                                                        tmp_path, capsys):
    """map upgrade rebuilds the indexes of the same submaps: the radius calibration, the
    verification calibration and the local-feature store come along (before, the new map
    answered unverified and uncalibrated), and a query gets the same verified answer."""
    from vlm_vpr_ros.evaluation.demo import make_query
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    out = tmp_path / "fp16"
    assert main(["map", "upgrade", str(demo_map), "--out", str(out), "--index", "fp16"]) == 0
    assert "other files carried" in capsys.readouterr().out
    old, new = LocalizationPipeline.open(demo_map), LocalizationPipeline.open(out)
    assert {s.kind for s in new.map.submaps} == {"fp16"}
    assert new.localizer.calibration_source == old.localizer.calibration_source
    assert new.verifier.enabled and new.verifier.calibration_source == \
        old.verifier.calibration_source != "none"
    r = next(csv.DictReader(open(demo_data / "coords.csv")))
    q = make_query(load_image(demo_data / "images" / r["file"]), np.random.default_rng(0))
    a, b = old.localize_image(q), new.localize_image(q)
    assert (b.ref_id, b.status, b.inliers) == (a.ref_id, a.status, a.inliers)
    assert b.status == "fix" and b.p_correct == a.p_correct
    ReferenceMap.load(out, verify=True)  # every carried file is listed and checks out


def test_build_from_single_npy_and_localize_query_descriptors(ref512, tmp_path, monkeypatch,
                                                              caplog):
    d, x, pos, ids = ref512
    out = tmp_path / "m"
    assert main(["build-map", "--descriptors", str(d / "desc.npy"), "--coords",
                 str(d / "coords.csv"), "--descriptor", "cosplace", "--out", str(out),
                 "--clusters", "4", "--index", "pq"]) == 0
    m = ReferenceMap.load(out, verify=True)
    assert m.n_references == 3000 and m.descriptor_identity["name"] == "cosplace"
    assert m.descriptor_identity["weights_sha256"] is None  # no weights were needed
    # localize precomputed query descriptors: no descriptor model may be created
    import vlm_vpr_ros.descriptors as D
    import vlm_vpr_ros.maps.reference_map as P

    def no_model(*a, **k):
        pytest.fail("a descriptor model was created")

    monkeypatch.setattr(D, "create_descriptor", no_model)
    monkeypatch.setattr(P, "create_descriptor", no_model)
    rng = np.random.default_rng(9)
    picks = rng.integers(0, 3000, 12)
    q = (x[picks] + 0.01 * rng.normal(size=(12, 512))).astype(np.float32)
    q[3] = np.nan
    np.save(tmp_path / "q.npy", q)
    with open(tmp_path / "q.csv", "w") as fh:
        fh.write("file\n" + "".join(f"q{i}.jpg\n" for i in range(12)))
    with open(tmp_path / "priors.csv", "w") as fh:
        fh.write("file,lat,lon\n" + "".join(f"q{i}.jpg,{pos[p][0]},{pos[p][1]}\n"
                                            for i, p in enumerate(picks)))
    res = tmp_path / "r.csv"
    assert main(["localize", "--map", str(out), "--query-descriptors", str(tmp_path / "q.npy"),
                 "--queries", str(tmp_path / "q.csv"), "--priors", str(tmp_path / "priors.csv"),
                 "--out", str(res)]) == 0
    rows = list(csv.DictReader(open(res)))
    assert rows[3]["flags"] == "bad_descriptor" and not rows[3]["ref_id"]
    for i, r in enumerate(rows):
        if i != 3:
            assert r["ref_id"] == ids[picks[i]] and "global" not in r["flags"]
    # misaligned query rows / wrong dim: exit 2 with one clear line
    np.save(tmp_path / "q5.npy", q[:5])
    assert main(["localize", "--map", str(out), "--query-descriptors",
                 str(tmp_path / "q5.npy"), "--queries", str(tmp_path / "q.csv"),
                 "--out", str(tmp_path / "r5.csv")]) == 2
    assert "5 query descriptors but the queries CSV has 12 rows" in caplog.text


def _shards(folder, x, ids, order, parts=3):
    folder.mkdir()
    for k, chunk in enumerate(np.array_split(order, parts)):
        np.save(folder / f"part-{k:03d}.npy", x[chunk])
        (folder / f"part-{k:03d}.ids.txt").write_text("".join(f"{ids[i]}\n" for i in chunk))


def test_build_from_shards_with_ids_any_order_missing_nan_and_zero_rows(ref512, tmp_path):
    d, x, pos, ids = ref512
    rng = np.random.default_rng(1)
    order = rng.permutation(3000)[:2990]  # 10 CSV rows get no descriptor
    x = x.copy()
    x[order[5]] = np.nan
    x[order[6]] = 0.0
    _shards(tmp_path / "shards", x, ids, order)
    m = build_from_descriptors(tmp_path / "shards", d / "coords.csv", tmp_path / "m",
                               "cosplace", clusters=3, index="fp16", progress=False)
    skipped = m.manifest["source"]["skipped"]
    assert m.n_references == 2988 and len(skipped) == 12
    assert f"{ids[order[5]]}: NaN/inf in descriptor" in skipped
    assert f"{ids[order[6]]}: zero descriptor" in skipped
    # every stored descriptor is the one given for its id, at the CSV's position
    where = {i: k for k, i in enumerate(ids)}
    for s in m.submaps:
        v = s.vectors()
        for j in range(0, s.count, 97):
            r = where[s.ids[j]]
            np.testing.assert_allclose(v[j], x[r], atol=2e-3)
            assert tuple(s.coords[j]) == pytest.approx(tuple(pos[r]), abs=1e-6)


def test_build_from_parquet_shards(ref512, tmp_path):
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    d, x, pos, ids = ref512
    (tmp_path / "pq").mkdir()
    for k, sl in enumerate((slice(0, 1000), slice(1000, 3000))):
        t = pa.table({"id": ids[sl], "descriptor": pa.array(list(x[sl]),
                                                            pa.list_(pa.float32()))})
        pq.write_table(t, tmp_path / "pq" / f"s{k}.parquet")
    m = build_from_descriptors(tmp_path / "pq", d / "coords.csv", tmp_path / "m", "cosplace",
                               clusters=2, index="flat", progress=False)
    assert m.n_references == 3000
    np.testing.assert_array_equal(m.submaps[0].vectors()[0], x[ids.index(m.submaps[0].ids[0])])


def test_descriptor_source_bad_input(ref512, tmp_path):
    d, x, pos, ids = ref512
    csvp = d / "coords.csv"

    def build(src, name="cosplace", **kw):
        return build_from_descriptors(src, csvp, tmp_path / "out", name, progress=False,
                                      overwrite=True, **kw)

    np.save(tmp_path / "short.npy", x[:2999])
    with pytest.raises(DataError, match="2999 descriptor rows but the coordinates CSV has 3000"):
        build(tmp_path / "short.npy")
    np.save(tmp_path / "d256.npy", x[:, :256])
    with pytest.raises(DataError, match="256-D, but cosplace is 512-D"):
        build(tmp_path / "d256.npy")
    raw = (d / "desc.npy").read_bytes()
    (tmp_path / "trunc.npy").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(DataError, match="truncated"):
        build(tmp_path / "trunc.npy")
    with pytest.raises(MapError, match="fitted descriptor"):
        build(d / "desc.npy", name="vlad_rootsift")
    _shards(tmp_path / "dup", x, ids, np.r_[np.arange(3000), [7]])
    with pytest.raises(DataError, match="duplicate descriptor for id 'img/00007.jpg'"):
        build(tmp_path / "dup")
    _shards(tmp_path / "unk", x, ids[:2999] + ["nope.jpg"], np.arange(3000))
    with pytest.raises(DataError, match="'nope.jpg' is not in the coordinates CSV"):
        build(tmp_path / "unk")
    (tmp_path / "unk" / "describe.json").write_text(json.dumps(
        {"format": "vlm_vpr_ros.descriptors", "version": 1, "descriptor": {"name": "mixvpr"}}))
    with pytest.raises(MapError, match="'mixvpr'"):
        build(tmp_path / "unk")
    with pytest.raises(MapError, match="ram-budget"):
        build(d / "desc.npy", index="auto")


def test_fitted_descriptor_state_from_describe_json(demo_map, tmp_path):
    """vlad_rootsift_fast descriptors computed elsewhere + describe.json with its state."""
    src = ReferenceMap.load(demo_map)
    x, ids = src.all_descriptors(), src.all_ids()
    pos = src.all_coords()
    folder = tmp_path / "src"
    folder.mkdir()
    np.save(folder / "all.npy", x)
    (folder / "all.ids.txt").write_text("".join(f"{i}\n" for i in ids))
    np.savez(folder / "descriptor_state.npz", **src.descriptor_state)
    (folder / "describe.json").write_text(json.dumps(
        {"format": "vlm_vpr_ros.descriptors", "version": 1,
         "descriptor": src.descriptor_identity, "descriptor_state": "descriptor_state.npz",
         "skipped": []}))
    write_coords(tmp_path / "c.csv", ids, pos)
    m = build_from_descriptors(folder, tmp_path / "c.csv", tmp_path / "m", "vlad_rootsift_fast",
                               partition="none", index="flat", progress=False)
    assert m.descriptor_identity == src.descriptor_identity
    np.testing.assert_array_equal(m.descriptor_state["codebook"] if "codebook" in
                                  m.descriptor_state else 0,
                                  src.descriptor_state["codebook"] if "codebook" in
                                  src.descriptor_state else 0)
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    LocalizationPipeline.open(tmp_path / "m")  # the query-time descriptor matches the map


def test_interrupted_descriptor_build_resumes(ref512, tmp_path, monkeypatch):
    d, x, pos, ids = ref512
    real = mbuild.write_submap
    calls = {"n": 0}

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(mbuild, "write_submap", flaky)
    args = (d / "desc.npy", d / "coords.csv", tmp_path / "m", "cosplace")
    with pytest.raises(KeyboardInterrupt):
        build_from_descriptors(*args, clusters=4, index="fp16", progress=False)
    work = tmp_path / ".m.partial" / "work"  # staged beside the target (vlm_vpr_ros.files.outputs)
    assert len(list((work / "subs").glob("*.json"))) == 2
    calls["n"] = -100
    m = build_from_descriptors(*args, clusters=4, index="fp16", progress=False)
    assert calls["n"] == -100 + 2  # only the two unfinished submaps were built again
    assert m.n_references == 3000 and not (tmp_path / ".m.partial").exists()
    again = build_from_descriptors(*args, clusters=4, index="fp16", progress=False)
    assert calls["n"] == -98 and again.n_references == 3000  # up to date: nothing rebuilt
    with pytest.raises(MapError, match="--overwrite"):
        build_from_descriptors(*args, clusters=5, index="fp16", progress=False)


def test_balanced_submaps_and_prior_choice(tmp_path):
    rng = np.random.default_rng(0)
    # one dense cluster (Paris area) and three small ones
    pos = np.concatenate([np.stack([rng.normal(48.85, 1.0, 1500), rng.normal(2.35, 1.5, 1500)],
                                   1),
                          np.stack([rng.normal(35.7, 0.3, 300), rng.normal(139.6, 0.3, 300)],
                                   1),
                          np.stack([rng.normal(-1.3, 0.3, 300), rng.normal(36.8, 0.3, 300)],
                                   1)])
    x, _ = clustered(len(pos), 32, seed=8)
    ids = [f"r{i}" for i in range(len(pos))]
    m = assemble_map(x, pos, ids, IDENT, {}, "kmeans", 3, max_submap_size=400)
    assert max(s.count for s in m.submaps) <= 600 and len(m.submaps) >= 6
    pieces = [s for s in m.submaps if s.group]
    assert len({s.group for s in pieces}) == 1 and len(pieces) >= 4
    m.save(tmp_path / "b")
    m = ReferenceMap.load(tmp_path / "b")
    assert len(m.group_members(pieces[0].group)) == len(pieces)
    loc = Localizer(m, LocalizerConfig(top_p=5, fusion="paper"))
    fused = Localizer(m, LocalizerConfig(top_p=5))  # posterior: the prior's whole region
    # a prior in the split cluster searches the piece whose centroid is nearest to it
    for r in rng.integers(0, 1500, 10):
        chosen, _ = loc.select_submaps(Prior(*pos[r], "t"))
        assert chosen[0] in fused.select_submaps(Prior(*pos[r], "t"))[0]
        sub = m.submaps[chosen[0]]
        d_all = [((s.centroid[0] - pos[r][0]) ** 2 + (s.centroid[1] - pos[r][1]) ** 2)
                 for s in m.submaps]
        assert sub.group == pieces[0].group and sub.count <= 600
        assert chosen[0] == int(np.argmin(d_all)) or min(d_all) > 0.5
        hyp = loc.localize(x[r], PriorResult(Prior(*pos[r], "t"), "t"))
        assert all(c.submap == sub.id for c in hyp.candidates)


def test_country_split_searches_a_piece_of_the_right_country(tmp_path):
    rng = np.random.default_rng(3)
    pos = np.concatenate([np.stack([rng.uniform(43, 50, 800), rng.uniform(-1, 7, 800)], 1),
                          np.stack([rng.uniform(35, 36, 100), rng.uniform(139, 140, 100)], 1)])
    x, _ = clustered(len(pos), 32, seed=1)
    m = assemble_map(x, pos, [f"r{i}" for i in range(len(pos))], IDENT, {}, "country",
                     max_submap_size=200)
    fr = m.group_members("FR")
    assert len(fr) >= 4 and m.submap_index("FR") is None
    chosen, flags = Localizer(m).select_submaps(Prior(45.76, 4.84, "t"))  # Lyon
    assert chosen[0] in fr and not flags


def test_map_info_and_verify(ref512, tmp_path, capsys, caplog):
    d, *_ = ref512
    out = tmp_path / "m"
    build_from_descriptors(d / "desc.npy", d / "coords.csv", out, "cosplace", clusters=2,
                           index="pq", progress=False)
    capsys.readouterr()
    assert main(["map", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_references"] == 3000 and info["index_kinds"] == {"pq": 2}
    assert info["expected_ram_bytes"] == 3000 * 128  # PQ256x4: 128 B per reference
    assert info["disk_bytes"] == sum(f.stat().st_size for f in out.rglob("*")
                                     if f.is_file() and f.name != "manifest.json")
    assert all(s["recall"]["recall_at_50"] > 0.9 for s in info["submaps"])
    assert main(["map", "info", str(out)]) == 0 and "pq: 2" in capsys.readouterr().out
    assert main(["map", "verify", str(out)]) == 0 and "OK" in capsys.readouterr().out
    from vlm_vpr_ros.maps.format import PAGE_BYTES, sample_offsets

    f = next((out / "submaps").glob("*.f16.npy"))
    data = bytearray(f.read_bytes())
    data[-3] ^= 0x40  # in a sampled page (the last): refused at open
    f.write_bytes(bytes(data))
    with pytest.raises(MapError, match="does not match the manifest"):
        ReferenceMap.load(out)
    data[-3] ^= 0x40
    sampled = set(sample_offsets(len(data)))
    off = next(p for p in range(PAGE_BYTES, len(data), PAGE_BYTES) if p not in sampled)
    data[off + 7] ^= 0x40  # outside the sampled pages: only the full pass sees it
    f.write_bytes(bytes(data))
    ReferenceMap.load(out)  # opening reads a few pages per file: fast at any scale
    assert main(["map", "verify", str(out)]) == 2
    assert "checksum mismatch" in caplog.text


@pytest.fixture(scope="module")
def pq_map(ref512, tmp_path_factory):
    d, *_ = ref512
    out = tmp_path_factory.mktemp("pq_map") / "m"
    build_from_descriptors(d / "desc.npy", d / "coords.csv", out, "cosplace", partition="none",
                           index="pq", progress=False)
    return out


@pytest.mark.parametrize("role", ["vectors", "coords", "ids", "index"])
def test_file_truncated_after_open_is_an_error_not_sigbus(ref512, pq_map, tmp_path, role):
    d, x, *_ = ref512
    out = tmp_path / "m"
    shutil.copytree(pq_map, out)
    m = ReferenceMap.load(out)
    loc = Localizer(m)
    assert loc.localize(x[5], None).ref_id == "img/00005.jpg"  # opens and maps the submap
    rel = m.submaps[0].files[role]
    with open(out / rel, "r+b") as fh:
        fh.truncate(os.path.getsize(out / rel) // 3)
    with pytest.raises(MapError, match="after the map was opened"):
        loc.localize(x[6], None)
    # a new open refuses the map before mapping anything
    with pytest.raises(MapError, match="truncated"):
        ReferenceMap.load(out)


def test_file_replaced_atomically_after_open_keeps_serving(pq_map, ref512, tmp_path):
    d, x, *_ = ref512
    out = tmp_path / "m"
    shutil.copytree(pq_map, out)
    m = ReferenceMap.load(out)
    loc = Localizer(m)
    loc.localize(x[1], None)
    rel = m.submaps[0].files["vectors"]
    (out / "new.tmp").write_bytes(b"x")
    os.replace(out / "new.tmp", out / rel)  # another inode: the open mapping stays valid
    assert loc.localize(x[7], None).ref_id == "img/00007.jpg"


def test_map_remove_keeps_pq_submaps_searchable(pq_map, ref512, tmp_path):
    """issue 13's map edit on a v2 pq map: rewritten submaps stay pq (shared codebook)."""
    from vlm_vpr_ros.mapping.edit import remove_references

    d, x, *_ = ref512
    out = tmp_path / "m"
    shutil.copytree(pq_map, out)
    res = remove_references(out, ["img/00005.jpg", "img/00006.jpg"])
    assert res.n_references == 2998
    m = ReferenceMap.load(out, verify=True)
    assert [s.kind for s in m.submaps] == ["pq"] and m.manifest["version"] == 2
    got = Localizer(m).localize(x[5], None)
    assert got.ref_id != "img/00005.jpg"
    assert Localizer(m).localize(x[7], None).ref_id == "img/00007.jpg"


def test_built_submaps_hold_exactly_their_rows_after_the_sort_pass(ref512, tmp_path):
    """The sequential by-submap pass: every submap's stored vectors are the input rows of its
    ids (fp16-rounded for pq), its stored radius is the true max centroid distance."""
    from vlm_vpr_ros.geodesy import haversine_km

    d, x, pos, ids = ref512
    row_of = {f: i for i, f in enumerate(ids)}
    for kind in ("flat", "pq"):
        m = build_from_descriptors(d / "desc.npy", d / "coords.csv", tmp_path / kind,
                                   "cosplace", clusters=6, index=kind, progress=False)
        man = json.loads((tmp_path / kind / "manifest.json").read_text())
        for sub, entry in zip(m.submaps, man["submaps"]):
            rows = np.array([row_of[i] for i in sub.ids])
            assert np.all(np.diff(rows) > 0)  # ascending input rows
            if sub.kind == "fp16":  # small submaps of a pq map: FAISS's own fp16 rounding
                np.testing.assert_allclose(sub.vectors(), x[rows], rtol=1e-3, atol=1e-4)
            else:
                want = x[rows] if kind == "flat" else x[rows].astype(np.float16)
                np.testing.assert_array_equal(sub.vectors(), want.astype(np.float32))
            np.testing.assert_allclose(sub.coords, pos[rows], atol=1e-6)
            far = np.max(haversine_km(*sub.centroid, pos[rows, 0], pos[rows, 1]))
            assert entry["radius_km"] == pytest.approx(far, abs=1e-3)
        assert sum(s.count for s in m.submaps) == len(x)


def test_localizer_start_opens_no_submap_and_many_pq_submaps_merge_like_one_index(
        ref512, tmp_path):
    """Creating a Localizer reads no index (radii come from the manifest); a search over
    several pq submaps re-ranks the best PQ candidates of all of them once and returns the
    exact fp16 distances, as brute force over their union does."""
    d, x, pos, ids = ref512
    m = build_from_descriptors(d / "desc.npy", d / "coords.csv", tmp_path / "m", "cosplace",
                               clusters=5, index="pq", progress=False)
    m = ReferenceMap.load(tmp_path / "m")
    loc = Localizer(m)  # posterior fusion: region radii + background sample
    assert not any(s.is_open for s in m.submaps)
    x16 = x.astype(np.float16).astype(np.float32)
    row_of = {f: i for i, f in enumerate(ids)}
    everything = list(range(len(m.submaps)))
    rng = np.random.default_rng(4)
    hits1 = hits20 = 0.0
    for _ in range(20):
        a, b = rng.integers(0, len(x), 2)
        q = (x[a] + 0.5 * (x[b] - x[a])).astype(np.float32)
        got = loc.search(q, everything, 20)
        got_rows = [row_of[c.ref_id] for c in got]
        want, _ = exact(x16, q, 20)
        hits1 += got_rows[0] == want[0]
        hits20 += len(set(got_rows) & set(want.tolist())) / 20
        np.testing.assert_allclose([c.l2_sq for c in got], ((x16[got_rows] - q) ** 2).sum(1),
                                   rtol=1e-5, atol=1e-6)
        assert [c.l2_sq for c in got] == sorted(c.l2_sq for c in got)
        assert all((c.lat, c.lon) == pytest.approx(tuple(pos[r].round(6)))
                   for c, r in zip(got, got_rows))
    assert hits1 / 20 >= 0.95 and hits20 / 20 >= 0.95


def test_prefetch_rows_is_advice_only_and_scattered_rows_are_read_exactly(tmp_path):
    from vlm_vpr_ros.maps.mapped import npy_data_offset, prefetch_rows

    arr = np.arange(4000, dtype=np.float32).reshape(1000, 4)
    np.save(tmp_path / "a.npy", arr)
    view = np.load(tmp_path / "a.npy", mmap_mode="r")
    prefetch_rows(tmp_path / "a.npy", 16, np.array([999, 0, 5, 5]),
                  npy_data_offset(tmp_path / "a.npy", view))
    np.testing.assert_array_equal(view[[0, 5, 999]], arr[[0, 5, 999]])
    prefetch_rows(tmp_path / "gone.npy", 16, np.array([1]), 128)  # missing file: no error
    # the build's scattered-row reader (pread): same rows as numpy, any order and repeats,
    # float16 input converted; out-of-range rows are an error
    half = np.random.default_rng(0).normal(size=(300, 8)).astype(np.float16)
    np.save(tmp_path / "h.npy", half)
    rows = np.array([299, 0, 7, 7, 150])
    for name, want in (("a.npy", arr), ("h.npy", half)):
        got = mbuild._Rows(tmp_path / name)[rows]
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, want[rows].astype(np.float32))
    with pytest.raises(IndexError):
        mbuild._Rows(tmp_path / "a.npy")[np.array([1000])]


def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _mapped(path) -> bool:
    with open("/proc/self/maps") as fh:
        return any(line.rstrip().endswith(os.fspath(path)) for line in fh)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc (Linux)")
def test_mapped_npy_keeps_no_descriptor_and_reads_as_np_load(tmp_path):
    """map_npy reads what np.load reads (dtypes, Fortran order, header 2.0, empty), read-only,
    without holding a file descriptor; the file stays readable through the mapping after it
    is replaced and deleted, and is unmapped when the last view is gone. Object arrays,
    truncated files and non-.npy files are errors (load_array: a MapError naming the file)."""
    import gc

    from vlm_vpr_ros.maps.mapped import load_array, map_npy

    rng = np.random.default_rng(5)
    arrays = {"f8": rng.normal(size=(50, 2)), "f2": rng.normal(size=(7, 512)).astype(np.float16),
              "S": np.array([b"a/1.jpg", b"", "é".encode()], "S12"), "empty": np.zeros((0, 2)),
              "F": np.asfortranarray(np.arange(12.0).reshape(3, 4)), "i8": np.arange(10)}
    for name, want in arrays.items():
        np.save(tmp_path / f"{name}.npy", want)
    with open(tmp_path / "v2.npy", "wb") as fh:
        np.lib.format.write_array(fh, arrays["f8"], version=(2, 0))
    arrays["v2"] = arrays["f8"]
    before = _fds()
    got = {name: map_npy(tmp_path / f"{name}.npy", random_access=name == "f2")
           for name in arrays}
    assert _fds() == before
    for name, want in arrays.items():
        assert got[name].dtype == want.dtype and got[name].shape == want.shape
        np.testing.assert_array_equal(got[name], np.load(tmp_path / f"{name}.npy"))
        assert not got[name].flags.writeable
        with pytest.raises(ValueError):
            got[name].flags.writeable = True
    assert got["F"].flags.f_contiguous
    # replaced, then deleted: the mapping keeps the old file's data
    path = tmp_path / "f2.npy"
    np.save(tmp_path / "new.npy", np.zeros((7, 512), np.float16))
    os.replace(tmp_path / "new.npy", path)
    row = got["f2"][3]  # a view keeps the mapping
    path.unlink()
    del got
    gc.collect()
    np.testing.assert_array_equal(row, arrays["f2"][3])
    m = map_npy(tmp_path / "i8.npy")
    assert _mapped(tmp_path / "i8.npy")
    del m, row
    gc.collect()
    assert not _mapped(tmp_path / "i8.npy")
    # errors
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(tmp_path / "short.npy", np.arange(100.0))
    os.truncate(tmp_path / "short.npy", 300)
    (tmp_path / "text.npy").write_text("not an array")
    for name, msg in (("obj", "object array"), ("short", "truncated"), ("text", "magic")):
        with pytest.raises(ValueError, match=msg):
            map_npy(tmp_path / f"{name}.npy")
        with pytest.raises(MapError, match=f"cannot read {name}.npy"):
            load_array(tmp_path, f"{name}.npy", (100,), "f8")
    assert _fds() == before


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc (Linux)")
def test_a_map_of_many_submaps_opens_under_a_low_descriptor_limit(ref512, tmp_path):
    """Every opened submap's files stay mapped but hold no descriptor: a global search of a
    60-submap pq map (180 mapped files, all opened) works under a soft limit of 48 open
    files, where one descriptor per mapped file hit EMFILE (it was 3 per pq submap)."""
    import resource

    d, x, pos, ids = ref512
    build_from_descriptors(d / "desc.npy", d / "coords.csv", tmp_path / "m", "cosplace",
                           clusters=60, index="pq", progress=False)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    limit = 48
    if _fds() + 16 > limit:
        pytest.skip(f"{_fds()} descriptors open already")
    resource.setrlimit(resource.RLIMIT_NOFILE, (limit, hard))
    try:
        m = ReferenceMap.load(tmp_path / "m")
        assert len(m.submaps) >= 50
        hyp = Localizer(m, LocalizerConfig(top_p=20)).localize(x[17])
        assert all(s.is_open for s in m.submaps if s.count)
        assert _fds() < limit - 8
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert hyp.ref_id == ids[17] and "global" in hyp.flags
