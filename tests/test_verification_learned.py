"""Learned local features (DISK + LightGlue via kornia) from a file the user names
(``weights=PATH``): the loading code reads official-layout checkpoints with
``torch.load(weights_only=True)`` — tested on weights made here (random, not trained), never
downloaded; missing or foreign files are clear errors. The shipped weights (the default) are
tested in test_learned_presets.py."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
KF = pytest.importorskip("kornia.feature")

from vlm_vpr_ros.errors import DescriptorError  # noqa: E402
from vlm_vpr_ros.localization.verification.components import create_feature, create_matcher  # noqa
from vlm_vpr_ros.localization.verification.learned import LIGHTGLUE_DISK  # noqa: E402


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """A DISK checkpoint in the official container ({"extractor": state_dict}) and a LightGlue
    one with the official key names (self_attn.<i>.*), both from randomly initialised models."""
    d = tmp_path_factory.mktemp("w")
    torch.manual_seed(0)
    disk = KF.DISK()
    torch.save({"extractor": disk.state_dict()}, d / "depth-save.pth")
    lg = KF.LightGlue(None, **LIGHTGLUE_DISK, flash=False)
    renamed = {}  # the released files have no derived confidence_thresholds buffer
    for k, v in lg.state_dict().items():  # transformers.<i>.self_attn.X -> self_attn.<i>.X
        if k == "confidence_thresholds":
            continue
        parts = k.split(".")
        if parts[0] == "transformers":
            k = ".".join([parts[2], parts[1], *parts[3:]])
        renamed[k] = v
    torch.save(renamed, d / "disk_lightglue.pth")
    return d, disk.state_dict(), lg.state_dict()


def test_disk_and_lightglue_load_local_checkpoints_exactly(weights):
    d, disk_sd, lg_sd = weights
    f = create_feature("disk", {"weights": str(d / "depth-save.pth"), "max_side": 128})
    for k, v in f.model.state_dict().items():
        assert torch.equal(v, disk_sd[k]), k
    m = create_matcher("lightglue", {"weights": str(d / "disk_lightglue.pth")})
    for k, v in m.model.state_dict().items():
        assert torch.equal(v, lg_sd[k]), k
    assert not f.model.training and not m.model.training
    # identity: the weights' sha256, never their path
    ident = f.identity()
    assert "weights" not in ident["config"] and len(ident["weights_sha256"]) == 64
    rng = np.random.default_rng(0)
    img = (rng.random((96, 128, 3)) * 255).astype(np.uint8)
    a = f.extract(img, 64)
    assert 0 < len(a) <= 64 and a.descriptors.dtype == np.float16 and a.size == (128, 96)
    pairs = m.match(m.prepare(a), a, a)  # runs end to end (random weights: any pairs)
    assert pairs.ndim == 2 and pairs.shape[1] == 2 and (pairs < len(a)).all()


def test_missing_garbage_and_foreign_checkpoints_are_clear_errors(weights, tmp_path):
    d, _, _ = weights
    with pytest.raises(DescriptorError, match="nope.pth does not exist"):
        create_feature("disk", {"weights": str(tmp_path / "nope.pth")})
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"\x00garbage" * 100)
    with pytest.raises(DescriptorError, match="not a loadable torch checkpoint"):
        create_feature("disk", {"weights": str(bad)})
    # LightGlue weights given to DISK: every key checked, no partial load
    with pytest.raises(DescriptorError, match="does not fit this model"):
        create_feature("disk", {"weights": str(d / "disk_lightglue.pth")})


def test_a_disk_lightglue_map_end_to_end(weights, demo_data, tmp_path, caplog):
    """build-map with --local-features disk_lightglue stores float16 DISK features (with the
    checkpoint's sha256, never its path), and queries verify with LightGlue."""
    from test_verification_maps import first_rows
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.maps.features import FeatureStore
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    d, _, _ = weights
    rows, coords = first_rows(demo_data, 6, tmp_path / "c.csv")
    m = tmp_path / "map"
    build_map(demo_data / "images", coords, m, descriptor="vlad_rootsift_fast",
              descriptor_config={"max_side": 160, "n_words": 8, "pca_dim": 5}, clusters=2,
              progress=False, local_features="disk_lightglue",
              feature_options={"weights": str(d / "depth-save.pth"), "max_side": 128},
              matcher_options={"weights": str(d / "disk_lightglue.pth")},
              calibration_conditions="full")
    ref = ReferenceMap.load(m)
    sec = ref.manifest["local_features"]
    assert sec["preset"] == "disk_lightglue" and sec["feature"]["dtype"] == "float16"
    assert len(sec["feature"]["weights_sha256"]) == 64 and str(d) not in str(sec)
    store = FeatureStore.open(m, ref.manifest)
    assert store.get(ref.submaps[0].id, 0).descriptors.dtype == np.float16
    pipe = LocalizationPipeline.open(m, verification={
        "feature_options": {"weights": str(d / "depth-save.pth")},
        "matcher_options": {"weights": str(d / "disk_lightglue.pth")}})
    h = pipe.localize_image(load_image(demo_data / "images" / rows[2]["file"]))
    assert h.verification == "verified" and h.inliers >= 0 and h.status in ("fix", "no_fix")
    # without the options at query time the shipped DISK is loaded (never another file), whose
    # sha256 differs from the map's features': said at open, never silently
    caplog.set_level("WARNING")
    pipe = LocalizationPipeline.open(m)
    if pipe.verifier.enabled:
        assert pipe.verifier.extractor.weights_sha256 != sec["feature"]["weights_sha256"]
        assert "another checkpoint" in caplog.text
    else:
        assert "checkpoint" in pipe.verifier.unavailable
