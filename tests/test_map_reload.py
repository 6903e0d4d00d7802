"""A map grown on disk (``vlm-vpr map add``) is swapped into a running localizer between two
queries: first the pure runtime, then vlm_vpr_node's ``map_reload`` service over a real ROS 2
graph (separate process, Fast DDS, own domain)."""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from pathlib import Path

import pytest

from node_harness import domain_id, image_msg, node_and_client
from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.files.images import load_image
from vlm_vpr_ros.mapping.edit import add_references
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
from vlm_vpr_ros.priors import create_prior_provider
from vlm_vpr_ros.runtime.worker import Frame, QueryRuntime, RuntimeConfig

pytestmark = pytest.mark.timeout(150)
NEW = 50  # a demo image that only the second half of the references contains


@pytest.fixture(scope="module")
def half(demo_half_map):
    return demo_half_map


def _near(lat, lon, truth, m=1.0):
    return haversine_km(lat, lon, *truth) * 1000 <= m


def test_runtime_swaps_the_map_between_queries(half, demo_data, tmp_path):
    rows, src = half
    map_dir = tmp_path / "map"
    shutil.copytree(src, map_dir)
    truth = rows[NEW][1:]
    rgb = load_image(demo_data / "images" / rows[NEW][0])
    outcomes, lock = [], threading.Lock()

    def collect(o):
        with lock:
            outcomes.append(o)

    # verify=True (node parameter verify_map): a reload then re-checks every sha256 as well
    rt = QueryRuntime(LocalizationPipeline.open(map_dir, verify=True),
                      create_prior_provider("none", {}),
                      RuntimeConfig(min_period_s=0.0), decode=lambda m: m, on_outcome=collect)
    stop = threading.Event()

    def feed():
        k = 0
        while not stop.is_set():
            k += 1
            rt.on_frame(Frame(rgb, k, "cam"))
            time.sleep(0.02)

    feeder = threading.Thread(target=feed, daemon=True)
    rt.start()
    feeder.start()
    try:
        time.sleep(1.0)
        add_references(map_dir, demo_data / "images", rows[36:52], progress=False)
        ok, msg = rt.reload_map()
        assert ok and "36 -> 52 references" in msg and "generation 0 -> 1" in msg
        n_swap = len(outcomes)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(outcomes) < n_swap + 3:
            time.sleep(0.05)
        # a broken map on disk: reload refused, the loaded map keeps answering (the damaged
        # copy replaces the file: the running map may have it memory-mapped)
        man = json.loads((map_dir / "manifest.json").read_text())
        idx = map_dir / man["submaps"][0]["files"]["index"]
        (map_dir / "bad.tmp").write_bytes(idx.read_bytes()[:-8] + b"\0" * 8)
        os.replace(map_dir / "bad.tmp", idx)
        ok, msg = rt.reload_map()
        assert not ok and "current map stays in use" in msg and "checksum" in msg
        n_bad = len(outcomes)
        while time.monotonic() < deadline and len(outcomes) < n_bad + 2:
            time.sleep(0.05)
    finally:
        stop.set()
        feeder.join(2)
        rt.stop()
    assert all(o.hypothesis is not None and not o.error for o in outcomes)
    before = [o.hypothesis for o in outcomes[:max(1, n_swap - 1)]]
    after = [o.hypothesis for o in outcomes[n_swap + 1:]]
    assert before and not any(_near(h.lat, h.lon, truth) for h in before)
    assert len(after) >= 3 and all(h.ref_id == rows[NEW][0] for h in after)
    snap = rt.stats.snapshot()
    assert snap["map_reloads"] == 1 and snap["map_reload_failures"] == 1


def test_node_map_reload_service(half, demo_data, tmp_path):
    from std_srvs.srv import Trigger

    rows, src = half
    map_dir = tmp_path / "map"
    shutil.copytree(src, map_dir)
    truth = rows[NEW][1:]
    rgb = load_image(demo_data / "images" / rows[NEW][0])
    params = {"map_dir": str(map_dir), "prior_provider": "none", "min_period_s": 0.2,
              "diagnostics_period_s": 0.5}
    with node_and_client(params, tmp_path / "node.log", domain_id()) as (node, client):
        stamps = []

        def tick():
            stamps.append(time.time_ns())
            client.image_pub.publish(image_msg(rgb, stamps[-1]))

        assert client.wait_for(lambda: len(client.fixes) >= 2, 30.0, tick=tick,
                               period_s=0.1), node.log()
        assert not _near(client.fixes[-1][0].latitude, client.fixes[-1][0].longitude, truth)
        add_references(map_dir, demo_data / "images", rows[36:52], progress=False)
        srv = client.node.create_client(Trigger, "map_reload")
        assert srv.wait_for_service(timeout_sec=20.0)
        fut = srv.call_async(Trigger.Request())
        client.wait_for(fut.done, 60.0, tick=tick, period_s=0.1)
        res = fut.result()
        assert res is not None and res.success, node.log()
        assert "36 -> 52 references" in res.message
        found = client.wait_for(
            lambda: _near(client.fixes[-1][0].latitude, client.fixes[-1][0].longitude, truth),
            30.0, tick=tick, period_s=0.1)
        assert found, node.log()
        for _ in range(10):  # frames keep flowing after the swap
            tick()
            time.sleep(0.1)
        time.sleep(1.5)
        # every query the node ran was published: no fix lost across the swap
        diag = client.wait_for(lambda: (d := client.latest_diag()) and
                               int(d["fixes"]) == len(client.fixes) and
                               d.get("query_in_progress") == "false" and d, 10.0)
        assert diag, (client.latest_diag(), len(client.fixes))
        assert int(diag["query_errors"]) == 0 and int(diag["map_reloads"]) == 1
        assert diag["map_references"] == "52" and diag["map_generation"] == "1"
        sent = set(stamps)
        assert all(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec in sent
                   for m, _ in client.fixes)
        assert node.alive()


def test_reload_checks_as_much_as_the_start_did(half, tmp_path, monkeypatch):
    """Opened without verify_map (the default), a reload hashes no file larger than
    SMALL_FILE_BYTES whole (a 4.1M map is 4.5 GB: large files are checked by sampled pages)
    but still refuses a file whose size no longer matches the manifest."""
    from vlm_vpr_ros.maps import format as map_format

    _, src = half
    map_dir = tmp_path / "map"
    shutil.copytree(src, map_dir)
    pipe = LocalizationPipeline.open(map_dir)
    assert not pipe.verify and LocalizationPipeline.open(map_dir, verify=True).verify
    hashed, big, real = [], [], map_format.file_sha256

    def spy(path):
        hashed.append(Path(path).name)
        big.append(Path(path).stat().st_size > map_format.SMALL_FILE_BYTES)
        return real(path)

    monkeypatch.setattr(map_format, "file_sha256", spy)
    new = pipe.reloaded()
    assert new.map.n_references == pipe.map.n_references and not new.verify
    assert "calibration.json" in hashed and not any(big)
    pipe.reloaded(verify=True)
    assert any(h.endswith(".faiss") for h in hashed)  # the opt-in full pass
    man = json.loads((map_dir / "manifest.json").read_text())
    coords = map_dir / man["submaps"][0]["files"]["coords"]
    coords.write_bytes(coords.read_bytes()[:-16])
    with pytest.raises(MapError, match="bytes, manifest says"):
        pipe.reloaded()
