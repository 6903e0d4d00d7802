"""Round 4 (issue 28), stored files: the local-feature store checked against the manifest like
every other map file; writer locks that never follow a symbolic link; output paths checked
before any work."""

from __future__ import annotations

import csv
import json
import os

import numpy as np
import pytest

from faults.conftest import exit2, sha_tree


def _lf(man: dict, k: int, role: str) -> str:
    return man["local_features"]["submaps"][man["submaps"][k]["id"]]["files"][role]


def _open(m):
    from vlm_vpr_ros.maps.features import FeatureStore

    return FeatureStore.open(m, json.loads((m / "manifest.json").read_text()))


@pytest.mark.fault("features_not_the_manifest")
def test_feature_files_checked_against_manifest(cli, map_copy, demo_data, queries, tmp_path,
                                                caplog):
    from vlm_vpr_ros.errors import MapError

    m = map_copy
    man = json.loads((m / "manifest.json").read_text())
    assert _open(m) is not None
    pristine = {p: p.read_bytes() for p in (m / "submaps").glob("*.lf_*.npy")}
    # 1. each role of submap 0 given another submap's bytes, same size (a swap sizes miss)
    for role in ("rows", "keypoints", "descriptors"):
        a, b = m / _lf(man, 0, role), m / _lf(man, 1, role)
        raw, other = a.read_bytes(), b.read_bytes()
        a.write_bytes((other * (len(raw) // len(other) + 1))[:len(raw)])
        assert a.stat().st_size == len(raw)
        with pytest.raises(MapError, match="does not match the manifest") as ei:
            _open(m)
        assert _lf(man, 0, role) in str(ei.value)
        a.write_bytes(raw)
    # 2. garbage bytes in a small lf_kpts (the .npy header kept)
    kp = m / _lf(man, 2, "keypoints")
    raw = kp.read_bytes()
    assert len(raw) <= 256 * 1024
    kp.write_bytes(raw[:128] + np.random.default_rng(0).bytes(len(raw) - 128))
    with pytest.raises(MapError, match="does not match the manifest"):
        _open(m)
    kp.write_bytes(raw)
    # 3. a wrong sha256 for lf_desc in the manifest (the file itself untouched)
    bad = json.loads((m / "manifest.json").read_text())
    rel = _lf(man, 3, "descriptors")
    bad["files"][rel]["sha256"] = "0" * 64
    bad["files"][rel].pop("sample", None)
    if bad["files"][rel]["bytes"] > 256 * 1024:  # large: the sampled-page fingerprint instead
        bad["files"][rel]["sample"] = "0" * 64
    (m / "manifest.json").write_text(json.dumps(bad))
    with pytest.raises(MapError, match="does not match the manifest"):
        _open(m)
    (m / "manifest.json").write_text(json.dumps(man))
    # 4. the CLI on a swapped store: never a verified answer from the wrong features
    a = m / _lf(man, 0, "descriptors")
    raw = a.read_bytes()
    a.write_bytes(raw[:128] + bytes(len(raw) - 128))
    out = tmp_path / "r.csv"
    rc, _, _ = cli("localize", "--map", m, "--images", demo_data / "images", "--queries",
                   queries, "--out", out, "--prior", "none")
    assert rc == 0
    assert _lf(man, 0, "descriptors") in cli.text and "does not match the manifest" in cli.text
    rows = list(csv.DictReader(out.open()))
    assert rows and all("unverified" in r["flags"].split(";") or "unverified" in r["flags"]
                        for r in rows), [r["flags"] for r in rows]
    a.write_bytes(raw)
    assert {p: p.read_bytes() for p in pristine} == pristine
    assert _open(m) is not None


@pytest.mark.fault("features_rewritten_while_open")
def test_feature_file_rewritten_after_open(map_copy):
    from vlm_vpr_ros.errors import MapError

    m = map_copy
    man = json.loads((m / "manifest.json").read_text())
    store = _open(m)
    sid = man["submaps"][0]["id"]
    assert len(store.get(sid, 0)) >= 0
    p = m / _lf(man, 0, "keypoints")
    raw = p.read_bytes()
    with open(p, "r+b") as fh:  # in place, same size, same inode
        fh.seek(128)
        fh.write(bytes(len(raw) - 128))
    os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 10**9))
    with pytest.raises(MapError, match="does not match the manifest"):
        store.get(sid, 0)
    p.write_bytes(raw)
    with pytest.raises(MapError):  # refused until reloaded
        store.get(sid, 0)
    assert _open(m).get(sid, 0) is not None


@pytest.mark.fault("features_bad_caps")
def test_feature_caps_and_missing_section(map_copy):
    from vlm_vpr_ros.errors import MapError

    m = map_copy
    man = json.loads((m / "manifest.json").read_text())
    for key, v in (("max_keypoints", -1), ("query_max_keypoints", "x")):
        bad = json.loads(json.dumps(man))
        bad["local_features"][key] = v
        (m / "manifest.json").write_text(json.dumps(bad))
        with pytest.raises(MapError) as ei:
            _open(m)
        assert f"local_features.{key}" in str(ei.value) and str(m) in str(ei.value)
    bad = json.loads(json.dumps(man))
    bad["local_features"]["submaps"].pop(man["submaps"][0]["id"])
    (m / "manifest.json").write_text(json.dumps(bad))
    with pytest.raises(MapError) as ei:
        _open(m)
    assert "map features" not in str(ei.value) and "vlm-vpr build-map" in str(ei.value)
