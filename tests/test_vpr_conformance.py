"""Conformance of the deep VPR models with the official code (``../shared/vpr_conformance``).

For each model the fixture lists the official state_dict layout and the descriptors the official
code produces from deterministic "recipe" weights on a seeded input. A model that reproduces
both loads and runs the real released checkpoint unmodified. Skipped when ../shared is absent.
Also here: the image preprocessing against Pillow as an independent reference.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from vlm_vpr_ros.descriptors.deep.specs import IMAGENET_MEAN, IMAGENET_STD, get_spec  # noqa: E402
from vlm_vpr_ros.descriptors.deep.torch_descriptor import DeepDescriptor  # noqa: E402
from vlm_vpr_ros.descriptors.deep.weights import build_model, recipe_state_dict  # noqa: E402
from vlm_vpr_ros.errors import ImageDecodeError  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402

MODELS = ("cosplace", "eigenplaces", "mixvpr", "mixvpr_4096", "boq")
TOL = 1e-5  # per element, as suggested by the fixture README (observed noise <= 5e-7)


@pytest.fixture(scope="module")
def fixture_dir(shared_dir: Path) -> Path:
    d = shared_dir / "vpr_conformance"
    if not d.is_dir():
        pytest.skip("../shared/vpr_conformance is absent")
    return d


_CACHE: dict[str, tuple[dict, DeepDescriptor, dict]] = {}


@pytest.fixture(scope="module")
def built(fixture_dir):
    """name -> (fixture json, descriptor with recipe weights, recipe state_dict); built once."""
    def get(name: str):
        if name not in _CACHE:
            fx = json.loads((fixture_dir / f"{name}.json").read_text())
            spec = get_spec(name)
            state = recipe_state_dict(build_model(spec))
            desc = DeepDescriptor(spec, {"device": "cpu"}, state_dict=state)
            _CACHE[name] = (fx, desc, state)
        return _CACHE[name]
    yield get
    _CACHE.clear()


def fixture_input(fx: dict) -> torch.Tensor:
    h, w = fx["input_size_hw"]
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, h, w, generator=g)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    return (x - mean) / std


@pytest.mark.parametrize("name", MODELS)
def test_conformance_state_dict_layout(built, name):
    fx, desc, _ = built(name)
    got = [[k, list(v.shape)] for k, v in desc.model.state_dict().items()]
    assert got == [[k, list(s)] for k, s in fx["state_dict_keys_shapes"]]  # names, order, shapes
    assert len(got) == fx["state_dict_num_keys"]
    assert sum(p.numel() for p in desc.model.parameters()) == fx["num_parameters"]
    int64 = [k for k, v in desc.model.state_dict().items() if v.dtype == torch.int64]
    assert sorted(int64) == sorted(e if isinstance(e, str) else e[0]
                                   for e in fx["state_dict_non_float32_entries"])
    assert desc.dim == fx["output_dim"]
    assert list(get_spec(name).input_hw or [512, 512]) == fx["input_size_hw"]


@pytest.mark.parametrize("name", MODELS)
def test_conformance_recipe_weights(built, name):
    """Our weight generator reproduces the fixture's bytes, and they were loaded strictly."""
    fx, desc, state = built(name)
    h = hashlib.sha256()
    for t in state.values():
        h.update(t.numpy().astype("<i8" if t.dtype == torch.int64 else "<f4").tobytes())
    assert h.hexdigest() == fx["weights_sha256"]
    loaded = desc.model.state_dict()
    assert all(torch.equal(loaded[k].cpu(), v) for k, v in state.items())
    assert not desc.model.training


@pytest.mark.parametrize("name", MODELS)
def test_conformance_descriptors(built, name):
    fx, desc, _ = built(name)
    x = fixture_input(fx)
    digest = hashlib.sha256(x.numpy().astype("<f4").tobytes()).hexdigest()
    assert digest == fx["input"]["sha256_normalized_float32_le_bytes"]
    feats = {}
    hook = desc.model.backbone.register_forward_hook(lambda m, i, o: feats.setdefault("b", o))
    try:
        y = desc.forward(x)  # the descriptor's own inference path (eval, inference_mode)
    finally:
        hook.remove()
    fmap = feats["b"]
    bfx = fx["backbone_feature_map"]
    assert list(fmap.shape) == bfx["shape"]
    assert float(fmap.double().sum()) == pytest.approx(bfx["sum"], rel=1e-5)
    np.testing.assert_allclose(fmap.flatten()[:8].numpy(), bfx["first8"], atol=1e-4)
    ref = np.asarray(fx["descriptors"], dtype=np.float32).reshape(2, fx["output_dim"])
    assert y.shape == ref.shape and y.dtype == np.float32
    err = np.abs(y - ref).max(axis=1)
    assert (err <= TOL).all(), f"max abs diff per row {err}"
    # the two rows differ far more than the tolerance: a row-swapped or constant output fails
    row_gap = np.abs(ref[0] - ref[1]).max()
    assert row_gap > 20 * TOL
    np.testing.assert_allclose(np.linalg.norm(y, axis=1), 1.0, atol=1e-5)


# -- preprocessing against Pillow --------------------------------------------------------------
Image = pytest.importorskip("PIL.Image")


@pytest.fixture(scope="module")
def street_images(demo_data):
    files = sorted((demo_data / "images").iterdir())[:2]
    return [load_image(f) for f in files]  # real 682x512 street photos


def _unnormalize(x: torch.Tensor) -> np.ndarray:
    mean = np.asarray(IMAGENET_MEAN, np.float32)[:, None, None]
    std = np.asarray(IMAGENET_STD, np.float32)[:, None, None]
    return x.numpy() * std + mean


def _light(name: str) -> DeepDescriptor:
    """A descriptor whose weights do not matter (preprocessing checks only)."""
    spec = get_spec(name)
    model = build_model(spec)
    return DeepDescriptor(spec, {"device": "cpu"}, state_dict=model.state_dict())


def test_boq_resize_matches_pillow_float_bicubic(street_images):
    """BoQ resizes the float tensor (ToTensor → Resize(384, BICUBIC, antialias=True)); Pillow's
    float-mode bicubic resample is an independent implementation of the same filter."""
    desc = _light("boq")
    for im in street_images:
        got = _unnormalize(desc.prepare([im])[0])
        f = im.astype(np.float32) / 255.0
        ref = np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(f[..., c]), mode="F")
                                   .resize((384, 384), Image.BICUBIC)) for c in range(3)])
        assert got.shape == (3, 384, 384)
        assert np.abs(got - ref).max() < 0.02 / 255  # well below one grey level


def test_mixvpr_resize_matches_pillow_uint8_bicubic(street_images):
    """MixVPR resizes the PIL image (uint8) before ToTensor: at most 1 grey level apart, and
    on fewer than 1% of the values (Pillow's fixed-point arithmetic); the descriptor from
    ``describe()`` is then within 1e-3 of the one from Pillow-resized pixels."""
    spec = get_spec("mixvpr")
    desc = DeepDescriptor(spec, {"device": "cpu"},
                          state_dict=recipe_state_dict(build_model(spec)))
    mean = np.asarray(IMAGENET_MEAN, np.float32)[:, None, None]
    std = np.asarray(IMAGENET_STD, np.float32)[:, None, None]
    for im in street_images:
        got = np.rint(_unnormalize(desc.prepare([im])[0]) * 255.0)
        ref = np.asarray(Image.fromarray(im).resize((320, 320), Image.BICUBIC), np.float32)
        ref = ref.transpose(2, 0, 1)
        diff = np.abs(got - ref)
        assert diff.max() <= 1.0
        assert (diff > 0).mean() < 0.01
        via_pil = desc.forward(torch.from_numpy((ref / 255.0 - mean) / std)[None])
        assert np.abs(desc.describe([im]) - via_pil).max() < 1e-3


def test_native_resolution_and_batching(street_images):
    """CosPlace: no resize by default; mixed sizes are batched per size; results do not depend
    on batching; bad inputs are ImageDecodeError."""
    spec = get_spec("cosplace")
    desc = DeepDescriptor(spec, {"device": "cpu", "batch_size": 2},
                          state_dict=recipe_state_dict(build_model(spec)))
    a, b = street_images
    small = np.ascontiguousarray(a[::4, ::4])
    x = desc.prepare([small])
    assert tuple(x.shape) == (1, 3) + small.shape[:2]
    manual = (small.astype(np.float32).transpose(2, 0, 1) / 255.0
              - np.asarray(IMAGENET_MEAN, np.float32)[:, None, None]) \
        / np.asarray(IMAGENET_STD, np.float32)[:, None, None]
    np.testing.assert_allclose(x[0].numpy(), manual, atol=1e-6)
    batch = desc.describe([small, a[::4, ::4].copy(), np.ascontiguousarray(b[::4, ::4]), small])
    one = np.stack([desc.describe_one(im) for im in (small, np.ascontiguousarray(b[::4, ::4]))])
    np.testing.assert_allclose(batch[[0, 2]], one, atol=1e-5)
    np.testing.assert_array_equal(batch[0], batch[1])
    assert batch.dtype == np.float32 and math.isclose(float(np.linalg.norm(batch[3])), 1.0,
                                                       rel_tol=1e-5)
    assert desc.describe([]).shape == (0, 512)
    with pytest.raises(ImageDecodeError):
        desc.describe([a.astype(np.float32)])
    with pytest.raises(ImageDecodeError):
        desc.describe([a[..., :2]])
    resized = DeepDescriptor(spec, {"device": "cpu", "resize": [96, 128]},
                             state_dict=recipe_state_dict(build_model(spec)))
    assert tuple(resized.prepare([a]).shape) == (1, 3, 96, 128)
    assert resized.identity()["config"] == {"resize": [96, 128]}
    assert resized.identity()["preprocessing"] != desc.identity()["preprocessing"]
