"""``map add`` / ``map remove`` on every map format and index kind: format v1 (flat), v2 flat /
fp16 / pq (the pq codebook of the map is reused by new submaps). A map of real demo references
plus synthetic filler references (to reach pq-sized submaps) keeps the test fast."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("vlm_vpr_ros.maps.indexes")  # format v2 / pq (issue 11)

from vlm_vpr_ros.files.images import load_image  # noqa: E402
from vlm_vpr_ros.mapping.assemble import assemble_map  # noqa: E402
from vlm_vpr_ros.mapping.edit import add_references, remove_references  # noqa: E402
from vlm_vpr_ros.maps.reference_map import ReferenceMap  # noqa: E402
from vlm_vpr_ros.maps.indexes import PQ_MIN_REFS  # noqa: E402
from vlm_vpr_ros.localization.pipeline import LocalizationPipeline  # noqa: E402


@pytest.fixture(scope="module")
def base(demo_half_map, demo_data):
    """(rows, descriptors of the 36 real references, identity, state, query descriptors)."""
    rows, half = demo_half_map
    pipe = LocalizationPipeline.open(half)
    m = pipe.map
    by_id = dict(zip(m.all_ids(), m.all_descriptors()))
    feats = np.stack([by_id[f] for f, _, _ in rows[:36]])
    new_desc = pipe.descriptor.describe([load_image(demo_data / "images" / f)
                                         for f, _, _ in rows[36:44]])
    return rows, feats, dict(m.descriptor_identity), m.descriptor_state, new_desc, pipe


def _make(path, base, kind, v1=False):
    rows, feats, ident, state, _, _ = base
    rng = np.random.default_rng(0)
    n_fill = PQ_MIN_REFS + 200 if kind == "pq" else 300
    fill = rng.normal(size=(n_fill, feats.shape[1])).astype(np.float32)
    fill /= np.linalg.norm(fill, axis=1, keepdims=True)
    desc = np.concatenate([feats, fill])
    coords = np.concatenate([np.array([[a, b] for _, a, b in rows[:36]]),
                             np.column_stack([rng.uniform(40, 41, n_fill),
                                              rng.uniform(2, 3, n_fill)])])
    ids = [f for f, _, _ in rows[:36]] + [f"fill/{i}.jpg" for i in range(n_fill)]
    m = assemble_map(desc, coords, ids, ident, state, "kmeans", 2, index=kind)
    (m.save_v1 if v1 else m.save)(path)
    return path


@pytest.mark.parametrize("kind, v1", [("flat", True), ("flat", False), ("fp16", False),
                                      ("pq", False)])
def test_add_and_remove_every_kind(base, demo_data, tmp_path, kind, v1):
    rows, _, _, _, new_desc, pipe0 = base
    path = _make(tmp_path / "map", base, kind, v1)
    before = ReferenceMap.load(path)
    before_ids = sorted(before.all_ids())  # (v2 opens submaps lazily: read them now)
    kinds_before = {s.id: s.kind for s in before.submaps}
    pq_before = [s for s in before.submaps if s.kind == "pq"]
    if kind == "pq":
        assert pq_before, "the test map must have a pq submap"
    lazy = ReferenceMap.load(path)  # a reader (a running node) that has opened no submap yet
    res = add_references(path, demo_data / "images", rows[36:44], progress=False)
    assert sorted(lazy.all_ids()) == before_ids  # the previous generation is still complete
    m = ReferenceMap.load(path, verify=True)
    man = json.loads((path / "manifest.json").read_text())
    assert man["version"] == (1 if v1 else 2) and m.n_references == before.n_references + 8
    for s in m.submaps:  # rewritten submaps keep their kind; new ones follow the map's
        if s.id in kinds_before:
            assert s.kind == kinds_before[s.id]
    if kind == "pq":
        import faiss

        old_pq = faiss.downcast_index(pq_before[0].index)
        for s in m.submaps:
            if s.kind == "pq" and s.id in res.changed:
                cents = faiss.vector_to_array(faiss.downcast_index(s.index).pq.centroids)
                np.testing.assert_array_equal(
                    cents, faiss.vector_to_array(old_pq.pq.centroids))
    # each new reference is found by its own descriptor, with and without a prior
    pipe = LocalizationPipeline(m, pipe0.descriptor,
                                type(pipe0.localizer)(m, pipe0.localizer.config))
    from vlm_vpr_ros.priors.provider import Prior, PriorResult

    for (f, a, b), d in zip(rows[36:44], new_desc):
        assert pipe.localize_descriptor(d).ref_id == f
        assert pipe.localize_descriptor(d, PriorResult(Prior(a, b, "t"), "t")).ref_id == f
    remove_references(path, [f for f, _, _ in rows[36:44]])
    m2 = ReferenceMap.load(path, verify=True)
    assert sorted(m2.all_ids()) == before_ids
    # nothing left over: every file in the folder is listed in the manifest or retired by
    # the last edit (kept one generation for readers of the previous manifest)
    man = json.loads((path / "manifest.json").read_text())
    on_disk = {p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file()}
    assert man["retired"] and not set(man["retired"]) & set(man["files"])
    assert on_disk - set(man["files"]) - set(man["retired"]) <= {"manifest.json",
                                                                  ".edit.lock"}
    shutil.rmtree(path)
