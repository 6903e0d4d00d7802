"""The verification matcher of issue 31 (the mutual check on the ratio test's columns only)
finds the pairs of the mutual-nearest-neighbour + ratio definition, ties included, and the pairs
of the matcher it replaced (no timing here: benchmarks/bench_verify.py)."""

from __future__ import annotations

import numpy as np

from vlm_vpr_ros.localization.verification import sift
from vlm_vpr_ros.localization.verification.components import create_matcher
from vlm_vpr_ros.types import LocalFeatures


def brute_force(a: np.ndarray, b: np.ndarray, ratio: float, dmax: float) -> set:
    """The definition, by loops over float64 distances: i's nearest j (the first on ties), the
    ratio to i's second nearest, and i the first of j's nearest queries."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    d = np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1))
    out = set()
    for i in range(len(a)):
        j = int(np.argmin(d[i]))
        second = np.min(np.delete(d[i], j))
        if d[i, j] <= ratio * second and d[i, j] <= dmax and int(np.argmin(d[:, j])) == i:
            out.add((i, j))
    return out


def scene(n_q: int, n_r: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """uint8 SIFT-like descriptors with planted correspondences, as RootSIFT."""
    r = np.random.default_rng(seed)
    qd = r.integers(0, 120, (n_q, 128)).astype(np.uint8)
    rd = r.integers(0, 120, (n_r, 128)).astype(np.uint8)
    k = min(n_q, n_r) // 3
    rd[:k] = np.clip(qd[n_q - k:].astype(int) + r.integers(-3, 4, (k, 128)), 0, 255)
    return sift.rootsift(qd), sift.rootsift(rd)


def tie_scene(n_q: int, n_r: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors with 4 equal non-zero bins among 8: RootSIFT entries of exactly 0.5, so every
    similarity (0, .25, .5, .75, 1) is exact in float32 whatever the product's order, and ties
    (equal nearest references, equal nearest queries, duplicates) are everywhere."""
    r = np.random.default_rng(seed)

    def draw(n):
        d = np.zeros((n, 128), np.uint8)
        for row in d:
            row[r.choice(8, 4, replace=False)] = 64
        return d
    qd, rd = draw(n_q), draw(n_r)
    return sift.rootsift(qd), sift.rootsift(rd)


def test_matches_equal_the_definition():
    for seed, (n_q, n_r) in enumerate([(300, 250), (130, 401), (64, 64)]):
        q, r = scene(n_q, n_r, seed)
        got = sift.mutual_ratio_matches(q, r, 0.8, 2.0, True)
        want = brute_force(q, r, 0.8, 2.0)
        assert {tuple(p) for p in got.tolist()} == want
        assert len(want) >= min(n_q, n_r) // 3 - 2  # the planted pairs
        assert got.dtype == np.int64 and got.shape[1] == 2


def test_ties_go_to_the_first_row_as_argmax():
    for seed, (n_q, n_r) in enumerate([(200, 150), (90, 300)]):
        q, r = tie_scene(n_q, n_r, seed)
        for ratio in (0.8, 1.0):
            got = sift.mutual_ratio_matches(q, r, ratio, 2.0, True)
            want = brute_force(q, r, ratio, 2.0)
            assert {tuple(p) for p in got.tolist()} == want and len(want) > 3
            assert np.array_equal(got, sift.match_reference(q, r, ratio, 2.0, True))


def test_ratio_distance_cap_and_no_mutual_equal_the_matcher_before():
    q, r = scene(400, 300, 5)
    for ratio, dmax, mutual in [(0.8, 2.0, True), (1.0, 2.0, False), (0.9, 0.3, True),
                                (0.6, 2.0, False)]:
        before = sift.match_reference(q, r, ratio, dmax, mutual)
        now = sift.mutual_ratio_matches(q, r, ratio, dmax, mutual)
        assert np.array_equal(now, before)  # one product: the same floats, the same pairs


def test_registry_matcher_and_too_few_features():
    q, r = scene(500, 420, 9)
    rng = np.random.default_rng(0)
    m = create_matcher("nn")
    assert m.shares_threads  # the stage may match its candidates on several threads
    fq = LocalFeatures(rng.random((500, 2), np.float32),
                       rng.integers(0, 120, (500, 128)).astype(np.uint8), (640, 480))
    fr = LocalFeatures(rng.random((420, 2), np.float32), fq.descriptors[:420][::-1].copy(),
                       (640, 480))
    got = {tuple(p) for p in m.match(m.prepare(fq), fq, fr).tolist()}
    assert got == brute_force(sift.rootsift(fq.descriptors), sift.rootsift(fr.descriptors),
                              0.8, 2.0) and len(got) > 100
    into = np.full(fq.descriptors.shape, np.nan, np.float32)  # the matcher's scratch path
    assert np.array_equal(sift.rootsift(fq.descriptors, into), sift.rootsift(fq.descriptors))
    tiny = LocalFeatures(fq.keypoints[:1], fq.descriptors[:1], (640, 480))
    assert m.match(m.prepare(tiny), tiny, fq).shape == (0, 2)  # fewer than 2: no pairs
