"""Verification's candidates shared between threads (issue 31): every candidate computed once,
results in order, errors raised, the caller never waiting for a helper that got no core, a
forked child with threads of its own; and the same answers — inlier counts, matches, status,
protection level — on one thread and on several (timing: benchmarks/bench_verify.py)."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification import share
from vlm_vpr_ros.localization.verification.stage import VerificationConfig
from vlm_vpr_ros.threads import one_blas_thread, usable_cores


@pytest.mark.parametrize("threads", [1, 2, 4, 30])
def test_results_in_order_each_index_once(threads):
    calls, lock = [], threading.Lock()

    def f(i):
        with lock:
            calls.append(i)
        return i * i

    assert share.map_shared(f, 23, threads) == [i * i for i in range(23)]
    assert sorted(calls) == list(range(23))
    assert share.map_shared(f, 0, threads) == []


def test_the_first_error_in_index_order_after_all_started_calls():
    ended = []

    def f(i):
        if i in (3, 7):
            raise ValueError(f"bad {i}")
        ended.append(i)
        return i

    with pytest.raises(ValueError, match="bad 3"):
        share.map_shared(f, 12, 2)
    assert sorted(ended) == [i for i in range(12) if i not in (3, 7)]  # none was abandoned


def test_the_caller_does_the_work_when_no_helper_gets_to_run(monkeypatch):
    """A helper that never starts (a busy machine) delays nothing: the caller claims every
    candidate and returns without waiting for it."""
    gate = threading.Event()
    stuck = ThreadPoolExecutor(max_workers=1)
    stuck.submit(gate.wait)  # the only helper thread is busy
    monkeypatch.setattr(share, "_helpers", lambda n: stuck)
    who = []
    try:
        out = share.map_shared(lambda i: who.append(threading.get_ident()) or i, 8, 2)
    finally:
        gate.set()
        stuck.shutdown(wait=True)
    assert out == list(range(8)) and set(who) == {threading.get_ident()}


def test_a_forked_child_gets_helpers_of_its_own():
    import multiprocessing as mp

    assert share.map_shared(lambda i: i + 1, 6, 2) == list(range(1, 7))  # the pool exists
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        got = pool.apply_async(_in_child).get(120)
    assert got == [i + 1 for i in range(6)]


def _in_child() -> list[int]:
    return share.map_shared(lambda i: i + 1, 6, 2)


def test_thread_settings():
    assert share.resolve_threads(3) == 3
    assert share.resolve_threads(0) == min(usable_cores(), share.MAX_THREADS)
    assert 1 <= usable_cores() <= (os.cpu_count() or 1)
    with pytest.raises(ConfigError, match="verify_threads"):
        VerificationConfig(threads=65)
    with pytest.raises(ConfigError, match="verify_threads"):
        VerificationConfig(threads=-1)


@pytest.fixture()
def two_blas_threads():
    """Every BLAS on 2 threads during the test (the suite's workers run with 1 by env)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=2, user_api="blas"):
        yield


def test_one_blas_thread_limits_and_restores(two_blas_threads):
    from threadpoolctl import threadpool_info

    before = {i["filepath"]: i["num_threads"] for i in threadpool_info()
              if i["user_api"] == "blas"}
    with one_blas_thread():
        inside = {i["filepath"]: i["num_threads"] for i in threadpool_info()
                  if i["user_api"] == "blas"}
    after = {i["filepath"]: i["num_threads"] for i in threadpool_info()
             if i["user_api"] == "blas"}
    assert set(before.values()) == {2} and set(inside.values()) == {1} and after == before


def test_same_answers_on_one_thread_and_several(demo_map, demo_data):
    """Every query's candidates, inlier counts, matches and answer fields are the same whatever
    the number of threads (demo map, altered copies of its pictures)."""
    from vlm_vpr_ros.evaluation.demo import make_query
    from vlm_vpr_ros.files.images import load_image
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    rows = read_coords_csv(demo_data / "coords.csv")[:10]
    pipes = {t: LocalizationPipeline.open(demo_map, verification={"threads": t})
             for t in (1, 3)}
    assert pipes[1].verifier.threads == 1 and pipes[3].verifier.threads == 3
    verified = 0
    for i, (name, _, _) in enumerate(rows):
        im = make_query(load_image(demo_data / "images" / name), np.random.default_rng(i))
        h1, h3 = (pipes[t].localize_image(im) for t in (1, 3))
        assert [(c.ref_id, c.inliers) for c in h1.candidates] == \
            [(c.ref_id, c.inliers) for c in h3.candidates]
        assert (h1.status, h1.ref_id, h1.inliers, h1.p_correct, h1.protection_m,
                h1.uncertainty_m) == (h3.status, h3.ref_id, h3.inliers, h3.p_correct,
                                      h3.protection_m, h3.uncertainty_m)
        assert len(h1.matches) == len(h3.matches) and all(
            np.array_equal(a, b) for a, b in zip(h1.matches, h3.matches))
        verified += h1.verification == "verified" and (h1.inliers or 0) > 0
    assert verified >= 5  # the comparison saw real geometric evidence
