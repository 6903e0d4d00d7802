"""Descriptor shards, ``vlm-vpr describe`` and ``build-map --engine ray`` (issue 12).

Reference: the local single-process build of the same images. Data: a subset of the SF night
database with its real night queries (../shared), or generated images when it is absent.
Ray runs small here (2 CPUs, 100 MB object store): a Ray in this process (``ray.init``), and a
real two-node cluster (``ray start --head`` + ``ray start --address``) driven by the CLI in
subprocesses, always torn down.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from ray_helpers import (DESCRIPTOR, DESCRIPTOR_OPTIONS, OBJECT_STORE, LocalCluster, free_port,
                         make_reference_set, ray_env)
from vlm_vpr_ros.distributed.describe import DescribeOptions, describe_to_shards
from vlm_vpr_ros.distributed.engines import describe_items
from vlm_vpr_ros.distributed.shards import ShardStore, read_shards
from vlm_vpr_ros.mapping.image_sources import ImageSource
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.mapping.build_images import build_map
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors.provider import Prior, PriorResult

CLUSTERS = 4
N_REFS = 16


# -- data and the local reference build ---------------------------------------------------------
@pytest.fixture(scope="module")
def refs(tmp_path_factory):
    from conftest import SHARED

    shared = SHARED if (SHARED / "data" / "sf_night").is_dir() else None
    return make_reference_set(tmp_path_factory.mktemp("refs"), shared, N_REFS)


@pytest.fixture(scope="module")
def reference_map(refs, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("local") / "map"
    build_map(refs["images"], refs["coords"], out, descriptor=DESCRIPTOR,
              descriptor_config=DESCRIPTOR_OPTIONS, partition="kmeans", clusters=CLUSTERS,
              progress=False)
    return out


def by_id(m: ReferenceMap) -> dict[str, np.ndarray]:
    return dict(zip(m.all_ids(), m.all_descriptors()))


def assert_same_map(ray_dir: Path, ref_dir: Path, queries: list[Path]) -> None:
    """Same manifest (but file hashes), descriptors allclose 1e-5, same answer to every query
    with and without a prior."""
    a, b = ReferenceMap.load(ray_dir), ReferenceMap.load(ref_dir)
    ma, mb = dict(a.manifest), dict(b.manifest)
    ma.pop("files"), mb.pop("files")
    assert ma == mb
    da, db = by_id(a), by_id(b)
    assert da.keys() == db.keys()
    for k in db:
        np.testing.assert_allclose(da[k], db[k], atol=1e-5, rtol=0)
    pa, pb = LocalizationPipeline.open(ray_dir), LocalizationPipeline.open(ref_dir)
    for q in queries:
        d = pb.describe(load_image(q))
        np.testing.assert_allclose(pa.describe(load_image(q)), d, atol=1e-5, rtol=0)
        c = b.submaps[0].coords[0]
        for prior in (None, PriorResult(Prior(float(c[0]), float(c[1]), "test"), "test")):
            ha, hb = pa.localize_descriptor(d, prior), pb.localize_descriptor(d, prior)
            assert [x.ref_id for x in ha.candidates] == [x.ref_id for x in hb.candidates]
            assert (ha.lat, ha.lon, ha.submap) == (hb.lat, hb.lon, hb.submap)


# -- shards (no Ray) ----------------------------------------------------------------------------
def test_shard_store_roundtrip_and_reader_errors(tmp_path):
    ids = [f"img_{i}.jpg" for i in range(7)]
    feats = np.random.default_rng(0).random((7, 4), dtype=np.float32)
    store = ShardStore(tmp_path / "s")
    store.open("fp", 7, 3, overwrite=False)
    store.write(0, 3, ids[0:3], feats[0:3], [])
    store.write(3, 6, [ids[3], ids[5]], feats[[3, 5]], [{"id": ids[4], "reason": "broken"}])
    assert set(store.done()) == {0, 3}
    store.write(6, 7, [], np.zeros((0, 4), np.float32), [{"id": ids[6], "reason": "gone"}])
    meta = store.finish({"name": "x", "dim": 4}, False, 7)
    assert meta["described"] == 5 and meta["shards"] == 2
    assert [s["id"] for s in meta["skipped"]] == [ids[4], ids[6]]
    assert not (tmp_path / "s" / "shard_000000006.npy").exists()  # no empty arrays
    # matched by id, in the CSV's order whatever the shard order
    got, ok = read_shards(tmp_path / "s", list(reversed(ids)))
    assert ok.tolist() == [False, True, False, True, True, True, True]
    np.testing.assert_array_equal(got[[1, 3, 4, 5, 6]], feats[[5, 3, 2, 1, 0]])
    with pytest.raises(MapError, match="not in the coordinates CSV"):
        read_shards(tmp_path / "s", ids[1:])
    # another job in the same folder is refused without --overwrite
    with pytest.raises(MapError, match="other images or settings"):
        ShardStore(tmp_path / "s").open("other", 7, 3, overwrite=False)
    ShardStore(tmp_path / "s").open("other", 7, 3, overwrite=True)
    assert not list((tmp_path / "s").glob("shard_*")) and store.done() == {}


class _Flaky:
    """A descriptor that raises (a plain RuntimeError) on any image whose first pixel is 7."""

    dim = 3

    def describe(self, images):
        if any(int(im[0, 0, 0]) == 7 for im in images):
            raise RuntimeError("model exploded")
        return np.array([[im.mean(), 1.0, 0.0] for im in images], np.float32)


def test_describe_items_skips_only_the_image_the_descriptor_raises_on(tmp_path):
    ims = {f"{i}.png": np.full((16, 16, 3), 7 if i == 2 else 10 * i, np.uint8) for i in range(4)}
    for name, im in ims.items():
        cv2.imwrite(str(tmp_path / name), im)
    (tmp_path / "bad.png").write_bytes(b"nope")
    items = list(enumerate([*ims, "bad.png", "missing.png"]))
    idx, ok, feats, reasons = describe_items(_Flaky(), ImageSource(tmp_path), items)
    assert idx.tolist() == [0, 1, 2, 3, 4, 5]
    assert ok.tolist() == [True, True, False, True, False, False]
    assert "RuntimeError: model exploded" in reasons[2] and "2.png" in reasons[2]
    assert "not a decodable image" in reasons[4] and "cannot read image" in reasons[5]
    np.testing.assert_allclose(feats[[0, 1, 3], 0], [0, 10, 30])


def test_image_source_reads_a_filesystem_uri(tmp_path):
    im = np.zeros((20, 30, 3), np.uint8)
    im[:, :, 0] = 200
    (tmp_path / "a b").mkdir()
    cv2.imwrite(str(tmp_path / "a b" / "x.png"), im)
    src = ImageSource(tmp_path.as_uri())  # file:///... (percent-encoded like any URI)
    src.check()
    np.testing.assert_array_equal(src.load("a b/x.png"), ImageSource(tmp_path).load("a b/x.png"))
    assert "does not exist" in _err(lambda: ImageSource((tmp_path / "no").as_uri()).check())


def _err(fn) -> str:
    try:
        fn()
    except Exception as exc:  # noqa: BLE001
        return str(exc)
    return ""


# -- a Ray in this process ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def local_ray(tmp_path_factory):
    ray = pytest.importorskip("ray")
    for k, v in ray_env().items():
        os.environ.setdefault(k, v)
    ray.init(num_cpus=2, object_store_memory=OBJECT_STORE, include_dashboard=False,
             log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


def test_ray_build_equals_local_build(local_ray, refs, reference_map, tmp_path):
    """Local Ray (2 CPUs, 2 actors) build of the reference set, images read through a
    file:// URI (pyarrow filesystem): same manifest, descriptors and query answers."""
    from vlm_vpr_ros.distributed.build import build_map_ray

    out = tmp_path / "map"
    opts = DescribeOptions(engine="ray", workers=2, batch_size=4, shard_size=8, progress=False)
    build_map_ray(refs["images"].as_uri(), refs["coords"], out, descriptor=DESCRIPTOR,
                  descriptor_config=DESCRIPTOR_OPTIONS, partition="kmeans", clusters=CLUSTERS,
                  options=opts)
    assert not (out / ".build").exists()
    m = json.loads((out / "manifest.json").read_text())
    assert m["source"]["skipped"] == ["database/broken.jpg"]
    assert_same_map(out, reference_map, refs["queries"])


def test_ray_describe_skips_an_image_a_worker_raises_on(local_ray, tmp_path):
    """A 4x4 image decodes but makes the descriptor raise inside the worker: only that image
    is skipped (and listed with the reason); local and Ray shards agree."""
    rng = np.random.default_rng(1)
    from ray_helpers import _texture

    img = tmp_path / "img"
    img.mkdir()
    ids = []
    for i in range(6):
        cv2.imwrite(str(img / f"t{i}.jpg"), _texture(rng, 240, 320))
        ids.append(f"t{i}.jpg")
    cv2.imwrite(str(img / "tiny.png"), np.full((4, 4, 3), 90, np.uint8))
    ids.insert(1, "tiny.png")  # not in the fit sample (rows 0, 3, 6 with fit_max_images=3)
    cfg = {**DESCRIPTOR_OPTIONS, "fit_max_images": 3}
    res = {}
    for engine, fit_on in (("local", "driver"), ("ray", "driver"), ("ray", "cluster")):
        opts = DescribeOptions(engine=engine, workers=1, batch_size=4, shard_size=4,
                               fit_on=fit_on, progress=False)
        out = tmp_path / f"{engine}_{fit_on}"
        res[out.name] = r = describe_to_shards(img, ids, out, DESCRIPTOR, cfg, opts)
        assert [s["id"] for s in r.skipped] == ["tiny.png"]
        assert "unusable size 4x4" in r.skipped[0]["reason"]
        assert r.described == 6
        meta = json.loads((out / "describe.json").read_text())
        assert meta["skipped"] == r.skipped and meta["descriptor"] == r.identity
    a, ok_a = read_shards(tmp_path / "local_driver", ids)
    b, ok_b = read_shards(tmp_path / "ray_driver", ids)
    assert ok_a.tolist() == ok_b.tolist() == [True, False, True, True, True, True, True]
    np.testing.assert_allclose(a, b, atol=1e-5, rtol=0)
    # fitted in a Ray task (one thread): same sample, same shapes; k-means may differ in the
    # last bits with another thread count, which is why the driver fits by default
    c, ok_c = read_shards(tmp_path / "ray_cluster", ids)
    assert ok_c.tolist() == ok_a.tolist() and c.shape == a.shape
    assert np.allclose(np.linalg.norm(c[ok_c], axis=1), 1.0, atol=1e-5)


# -- a real two-node cluster, driven by the CLI -------------------------------------------------
def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "vlm_vpr_ros.cli", *args]


def build_cmd(refs, out: Path, address: str) -> list[str]:
    opts = [a for k, v in DESCRIPTOR_OPTIONS.items() for a in ("--descriptor-option", f"{k}={v}")]
    return cli("build-map", "--images", str(refs["images"]), "--coords", str(refs["coords"]),
               "--out", str(out), "--descriptor", DESCRIPTOR, *opts, "--clusters", str(CLUSTERS),
               "--engine", "ray", "--ray-address", address, "--workers", "2",
               "--batch-size", "2", "--shard-size", "4")


@pytest.fixture(scope="module")
def cluster(local_ray):
    local_ray.shutdown()  # the in-process Ray is done: free its CPUs for the cluster
    c = LocalCluster(cpus_per_node=1)
    try:
        c.start()
        yield c
    finally:
        c.stop()


def _wait(cond, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"{what}: the build ended first (rc {proc.returncode}): "
                                 + proc.stderr.read()[-2000:])
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


def test_cluster_build_survives_a_killed_worker(cluster, refs, reference_map, tmp_path):
    out = tmp_path / "map"
    shards = tmp_path / ".map.partial" / "work" / "shards"  # built next to the map
    proc = subprocess.Popen(build_cmd(refs, out, cluster.address), env=ray_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # mid-run: the actor pool is describing and at least one shard is written
        _wait(lambda: cluster.worker_pids() and list(shards.glob(".progress/shard_*.json")),
              90, "a describing worker", proc)
        assert not (shards / "describe.json").exists()
        victim = cluster.worker_pids()[0]
        os.kill(victim, signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr[-3000:]
    assert victim not in cluster.worker_pids()
    assert f"{N_REFS} references" in stdout
    assert_same_map(out, reference_map, refs["queries"][:3])


def test_cluster_driver_killed_and_rerun_resumes(cluster, refs, reference_map, tmp_path):
    out = tmp_path / "map"
    shards = tmp_path / ".map.partial" / "work" / "shards"  # built next to the map
    proc = subprocess.Popen(build_cmd(refs, out, cluster.address), env=ray_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait(lambda: len(list(shards.glob(".progress/shard_*.json"))) >= 2, 90,
              "two finished shards", proc)
        proc.send_signal(signal.SIGKILL)  # the driver dies without any clean-up
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    done = [json.loads(p.read_text()) for p in shards.glob(".progress/shard_*.json")]
    assert len(done) >= 2 and not (out / "manifest.json").exists()
    rerun = subprocess.run(build_cmd(refs, out, cluster.address), env=ray_env(),
                           capture_output=True, text=True, timeout=180)
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    assert "resumed the fitted" in rerun.stderr  # the fit was not redone either
    # "described 16/17 images -> ... (1 skipped, 3 shards resumed): 21 images in ..."
    line = next(x for x in rerun.stderr.splitlines() if "shards resumed" in x)
    resumed = int(line.split(" shards resumed")[0].rsplit(", ", 1)[1])
    computed = int(line.split("): ")[1].split(" images")[0])
    assert resumed == len(done)
    assert computed == len(refs["rows"]) - sum(r["end"] - r["start"] for r in done)
    assert_same_map(out, reference_map, refs["queries"][:3])


def test_unreachable_ray_address_is_one_line_exit_2(refs, tmp_path):
    port = free_port()  # nothing listens there
    for address in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}"):
        t0 = time.monotonic()
        r = subprocess.run(cli("describe", "--images", str(refs["images"]), "--coords",
                               str(refs["coords"]), "--out", str(tmp_path / "s"),
                               "--descriptor", DESCRIPTOR, "--engine", "ray",
                               "--ray-address", address),
                           env=ray_env(), capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, r.stderr
        lines = [x for x in r.stderr.splitlines() if x.strip()]
        assert len(lines) == 1 and f"cannot reach the Ray cluster at {address}" in lines[0]
        assert "Traceback" not in r.stderr and time.monotonic() - t0 < 30
