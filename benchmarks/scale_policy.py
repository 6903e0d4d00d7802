"""Issue 31's thread-policy and re-rank comparison of ``benchmarks/bench_scale.py`` (run in its
query process): the largest submap's search alone, the paper's query on it and the posterior
over the whole map, for each of :data:`VARIANTS`, and the table that prints them."""

from __future__ import annotations

import contextlib
import random
import statistics
import time

import numpy as np

#: (name, one FAISS thread per query?, OpenCV re-rank?) compared query by query (issue 31)
VARIANTS = (("1 thread, OpenCV re-rank (default)", True, True),
            ("OpenMP default threads, OpenCV re-rank", False, True),
            ("1 thread, FAISS fp16 decoder re-rank (before #31)", True, False))


def thread_policy(m, loc, big: int, bp, q: np.ndarray, n: int = 200) -> dict:
    """Wall and CPU ms (median) of the largest submap's search alone and of the paper's whole
    query on it, and of the posterior on the whole map, for each of :data:`VARIANTS`,
    interleaved query by query (one run: the load hits every variant alike), each query's
    runs in a random order (seeded): a run right after another of the same query finds its
    rows in the caches, so a fixed order flatters whatever runs second."""
    # the package is imported in the query process only: bench_scale times its import as
    # part of the map's opening (open_s), which importing it with this module would hide
    from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
    from vlm_vpr_ros.maps import indexes, search

    one, cv = search.one_faiss_thread, indexes._cv2

    @contextlib.contextmanager
    def variant(single: bool, opencv: bool):
        search.one_faiss_thread = one if single else contextlib.nullcontext
        indexes._cv2 = cv if opencv else (lambda: None)
        try:
            yield
        finally:
            search.one_faiss_thread, indexes._cv2 = one, cv
    post = Localizer(m, LocalizerConfig(top_p=50))
    shapes = {"search": lambda x: m.search_submaps([big], x[None, :], 50),
              "paper": lambda x: loc.localize(x, bp),
              "posterior": lambda x: post.localize(x, None)}
    out = {f"{s}|{v[0]}": ([], []) for s in shapes for v in VARIANTS}
    runs = [(shape, v) for shape in shapes for v in VARIANTS]
    rng = random.Random(0)
    for i in range(n + 5):
        x = np.ascontiguousarray(q[i % len(q)])
        rng.shuffle(runs)
        for shape, (name, single, opencv) in runs:
            with variant(single, opencv):
                w, c = time.perf_counter(), time.thread_time()
                shapes[shape](x)
                c, w = time.thread_time() - c, time.perf_counter() - w
            if i >= 5:  # warm-up
                out[f"{shape}|{name}"][0].append(w * 1e3)
                out[f"{shape}|{name}"][1].append(c * 1e3)
    return {k: [statistics.median(w), statistics.median(c)] for k, (w, c) in out.items()}


def print_table(kind: str, r: dict) -> None:
    """The table of one kind's :func:`thread_policy` (``r``: its bench_scale results)."""
    print(f"\n{kind}: thread policy and re-rank, same process, queries interleaved in a "
          f"random order "
          f"(largest submap {r['largest'][0]}, {r['largest'][1]:,} refs, {r['largest'][2]};"
          f" posterior: no prior, the whole map)")
    print(f"  {'shape':<11}{'variant':<52}{'wall ms':>9}{'cpu ms':>9}{'/ default':>11}")
    for shape in ("search", "paper", "posterior"):
        base = r["shapes"][f"{shape}|{VARIANTS[0][0]}"][0]
        for name, _, _ in VARIANTS:
            w, c = r["shapes"][f"{shape}|{name}"]
            print(f"  {shape:<11}{name:<52}{w:>9.2f}{c:>9.2f}{w / base:>10.2f}x")
