"""What a benchmark ran on: one line (and a dict for JSON) naming the CPU, the SIMD level each
library dispatches to, the BLAS, the thread settings and the load average; and ``--cpu-paths``,
which re-runs a benchmark with the libraries forced onto slower code paths.

Every ``benchmarks/*.py`` script prints :func:`cpu_line` above its table, so two tables say
whether they can be compared. What is reported is what the libraries themselves say:

* NumPy: ``numpy.show_config(mode="dicts")["SIMD Extensions"]`` (baseline + found);
* FAISS: the level its dynamic dispatch runs (``faiss.SIMDConfig.get_level_name()``, FAISS >= 1.13)
  or, for older wheels, the variant the loader imported (``avx512`` / ``avx2`` / generic), with
  ``faiss.get_compile_options()``;
* OpenCV: ``cv2.getCPUFeaturesLine()`` (``*`` = dispatched, ``?`` = disabled by
  ``OPENCV_CPU_DISABLE``);
* BLAS: ``threadpoolctl.threadpool_info()`` (library, version, kernel architecture, threads),
  else NumPy's build configuration;
* threads: ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` / ``MKL_NUM_THREADS`` /
  ``OMP_WAIT_POLICY`` as set, ``faiss.omp_get_max_threads()``, ``cv2.getNumThreads()``;
* host speed: how long a fixed pure-Python loop (:func:`probe_ms`) takes right now.

Why the host's speed: on a shared virtual machine the same single-threaded work runs at two
speeds minutes or seconds apart, with no steal time and no load of its own to show for it
(another tenant on the physical core's other hardware thread). Measured on the AVX-512 EPYC of
issue 31, in one process, 6,000 queries of the 4.1M map's largest submap each between two
probes: the probe's 5th percentile 0.117 ms, its median 0.168 ms; the queries next to probes
within 10 % of the fastest took 1.57 ms (median), those next to probes 1.3x slower or more
2.48 ms. :func:`paired` times a benchmark's queries between two probes and
:func:`by_host_speed` splits their median by the probe, so a table says how much of a number is
the host's state rather than the code's.

``--cpu-paths native|avx2|generic`` (:func:`apply_cpu_paths`, called by each script before it
parses its arguments): ``avx2`` emulates an AVX2 machine without AVX-512 (the common x86-64
server / laptop class), ``generic`` a CPU with SSE only (FAISS's scalar code, OpenBLAS's
Prescott kernels, OpenCV without AVX/SSE4 dispatch, NumPy at its baseline). The environment of
:data:`CPU_PATHS` is set and the script re-executes itself, because every library reads it when
it loads; the printed line then shows the levels actually in force. Clock speed, cache and
memory bandwidth are not emulated: a slower CPU is slower still.
"""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from typing import Any, Callable

#: environment per code-path choice (the libraries read it at import)
CPU_PATHS: dict[str, dict[str, str]] = {
    "native": {},
    "avx2": {
        "FAISS_SIMD_LEVEL": "AVX2", "FAISS_OPT_LEVEL": "avx2",
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
        "OPENCV_CPU_DISABLE": "AVX512-SKX",
        "OPENBLAS_CORETYPE": "Haswell",
    },
    "generic": {
        "FAISS_SIMD_LEVEL": "NONE", "FAISS_OPT_LEVEL": "generic",
        "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
        "OPENCV_CPU_DISABLE": "AVX512-SKX,AVX2,FMA3,AVX,FP16,POPCNT,SSE4.2,SSE4.1",
        "OPENBLAS_CORETYPE": "Prescott",
    },
}
_MARK = "VLM_VPR_CPU_PATHS"
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_WAIT_POLICY",
              "GOMP_SPINCOUNT")


def add_argument(ap: Any) -> None:
    """Register ``--cpu-paths`` on an ``argparse`` parser (handled by apply_cpu_paths)."""
    ap.add_argument("--cpu-paths", choices=sorted(CPU_PATHS), default="native",
                    help="re-run with the libraries forced onto slower code paths: avx2 (no "
                         "AVX-512) or generic (SSE only); see benchmarks/cpuinfo.py")


def apply_cpu_paths(argv: list[str] | None = None) -> str:
    """Re-execute this script under ``--cpu-paths``'s environment (once); returns the choice."""
    argv = list(sys.argv if argv is None else argv)
    choice = "native"
    for i, a in enumerate(argv[1:], 1):
        if a == "--cpu-paths" and i + 1 < len(argv):
            choice = argv[i + 1]
        elif a.startswith("--cpu-paths="):
            choice = a.split("=", 1)[1]
    if choice not in CPU_PATHS:
        sys.stderr.write(f"--cpu-paths: unknown {choice!r}; choices: "
                         f"{', '.join(sorted(CPU_PATHS))}\n")
        raise SystemExit(2)
    if choice == "native" or os.environ.get(_MARK) == choice:
        return choice
    env = {**os.environ, **CPU_PATHS[choice], _MARK: choice}
    sys.stdout.flush()
    os.execve(sys.executable, [sys.executable] + argv, env)
    return choice  # not reached


def cpu_model() -> str:
    """Model name, family/model numbers, usable cores, the widest vector flags of the CPU."""
    name, fam, mod, flags = platform.processor() or platform.machine(), "", "", set()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                k, _, v = line.partition(":")
                k, v = k.strip(), v.strip()
                if k == "model name" and v:
                    name = v
                elif k == "cpu family":
                    fam = v
                elif k == "model":
                    mod = v
                elif k == "flags":
                    flags = set(v.split())
                    break
    except OSError:
        pass
    vec = [f for f in ("avx512f", "avx2", "fma", "f16c", "sse4_2") if f in flags]
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    fm = f" (family {fam} model {mod})" if fam else ""
    return f"{name}{fm}, {cores} cores" + (f", flags {'/'.join(vec)}" if vec else "")


def _numpy() -> str:
    import numpy as np

    try:
        simd = np.show_config(mode="dicts").get("SIMD Extensions", {})
        base = "+".join(simd.get("baseline", []))
        found = ",".join(simd.get("found", []))
        return f"numpy {np.__version__} {base}" + (f"+{found}" if found else "")
    except Exception:  # noqa: BLE001 - old numpy: no dict mode
        return f"numpy {np.__version__}"


def _faiss() -> tuple[str, int | None]:
    try:
        import faiss
    except ImportError:
        return "faiss absent", None
    level = None
    cfg = getattr(faiss, "SIMDConfig", None)
    if cfg is not None:
        try:
            level = cfg.get_level_name()
        except Exception:  # noqa: BLE001
            level = None
    if level is None:  # pre-dispatch wheels: the variant the loader imported
        mods = sys.modules
        level = ("avx512_spr" if "faiss.swigfaiss_avx512_spr" in mods else "avx512"
                 if "faiss.swigfaiss_avx512" in mods else "avx2"
                 if "faiss.swigfaiss_avx2" in mods else "generic")
    opts = faiss.get_compile_options().strip().replace(" ", ",")
    return f"faiss {faiss.__version__} {level} (compiled {opts})", faiss.omp_get_max_threads()


def _opencv() -> tuple[str, int | None]:
    try:
        import cv2
    except ImportError:
        return "opencv absent", None
    return f"opencv {cv2.__version__} {cv2.getCPUFeaturesLine()}", cv2.getNumThreads()


def _blas() -> str:
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        import numpy as np

        try:
            b = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
            return f"{b.get('name')} {b.get('version')} (numpy config)"
        except Exception:  # noqa: BLE001
            return "unknown"
    out = []
    for i in threadpool_info():
        if i.get("user_api") != "blas":
            continue
        lib = os.path.basename(i.get("filepath", "")).split("-")[0].split(".")[0]
        out.append(f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')} "
                   f"{i.get('threading_layer')} {i.get('num_threads')}thr [{lib}]")
    return "; ".join(out) or "none loaded"


def describe() -> dict[str, Any]:
    """The facts of :func:`cpu_line`, for a benchmark's JSON."""
    faiss_s, faiss_t = _faiss()
    cv_s, cv_t = _opencv()
    env = {k: os.environ[k] for k in THREAD_ENV if k in os.environ}
    return {"cpu": cpu_model(), "cpu_paths": os.environ.get(_MARK, "native"),
            "simd": {"numpy": _numpy(), "faiss": faiss_s, "opencv": cv_s}, "blas": _blas(),
            "threads": {"env": env, "faiss_omp": faiss_t, "cv2": cv_t},
            "load_average": [round(x, 2) for x in os.getloadavg()],
            "python": platform.python_version(), "host_speed": host_speed()}


def node_malloc() -> str:
    """glibc's malloc as the node sets it (``vlm_vpr_ros/ros/malloc.py``), applied to this
    process now; the '# malloc' line that says so (``--node-malloc`` of the benchmarks)."""
    from vlm_vpr_ros.ros import malloc

    applied = malloc.tune_malloc()
    return (f"# malloc: the node's settings ({malloc.ARENAS} arenas, mmap threshold "
            f"{malloc.MMAP_THRESHOLD // 2 ** 20} MiB, trim threshold "
            f"{malloc.TRIM_THRESHOLD // 2 ** 20} MiB; applied: {applied})")


#: steps of the host-speed probe's loop: ~0.1-0.2 ms, short against a state's seconds
PROBE_STEPS = 4000
#: a probe within this factor of its run's 5th percentile counts as the host at full speed
FULL_SPEED = 1.15


def probe_ms() -> float:
    """Milliseconds of a fixed pure-Python loop: the interpreter alone (no memory traffic, no
    library, no thread), so its time moves only with the speed the host gives this core."""
    t = time.perf_counter()
    s = 0
    for i in range(PROBE_STEPS):
        s += i
    return (time.perf_counter() - t) * 1e3


def host_speed(n: int = 200) -> dict[str, float]:
    """The probe's 5th percentile and median (ms) over ``n`` runs now (~30 ms in all)."""
    ts = sorted(probe_ms() for _ in range(n))
    return {"steps": PROBE_STEPS, "runs": n, "p5_ms": round(ts[n // 20], 4),
            "median_ms": round(statistics.median(ts), 4)}


def _median(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


def paired(run: Callable[[int], Any], n: int, warm: int = 20) -> tuple[list[float], list[float]]:
    """``run(i)`` for ``i`` in ``range(warm + n)``, each between two probes: (ms of each run,
    the mean of its two probes), the first ``warm`` runs left out. The probes are outside the
    timed span; they only tell how fast the host ran around each run."""
    ms, probes = [], []
    before = probe_ms()
    for i in range(warm + n):
        t = time.perf_counter()
        run(i)
        took = (time.perf_counter() - t) * 1e3
        after = probe_ms()
        if i >= warm:
            ms.append(took)
            probes.append((before + after) / 2.0)
        before = after
    return ms, probes


def by_host_speed(ms: list[float], probes: list[float]) -> dict[str, float]:
    """Medians of ``ms`` split by the host's speed around each run: ``full`` where the probe was
    within :data:`FULL_SPEED` of its 5th percentile, ``contended`` elsewhere (NaN when a side
    is empty), the share at full speed and the probe's 5th percentile and median. When the
    whole run was contended, its fastest probes are slow ones: compare ``probe_p5`` with other
    runs' on the same machine."""
    if not ms:
        nan = float("nan")
        return {"all": nan, "full": nan, "contended": nan, "share_full": nan, "probe_p5": nan,
                "probe_median": nan}
    p5 = sorted(probes)[len(probes) // 20]
    full = [m for m, p in zip(ms, probes) if p <= FULL_SPEED * p5]
    rest = [m for m, p in zip(ms, probes) if p > FULL_SPEED * p5]
    return {"all": _median(ms), "full": _median(full), "contended": _median(rest),
            "share_full": len(full) / len(ms), "probe_p5": p5,
            "probe_median": statistics.median(probes)}


def host_speed_row(label: str, split: dict[str, float], fastest_p5: float) -> str:
    """One line: a paired run's median, and its medians at full speed and contended; its probe
    against ``fastest_p5`` (the fastest 5th percentile of the runs in the same table: a run
    whose own is well above it was contended throughout)."""
    return (f"{label}: {split['all']:.2f} ms; host at full speed {split['full']:.2f} ms "
            f"({split['share_full']:.0%} of runs), contended {split['contended']:.2f} ms "
            f"(probe p5 {split['probe_p5']:.3f} ms = {split['probe_p5'] / fastest_p5:.2f}x the "
            f"table's fastest, median {split['probe_median']:.3f})")


def cpu_line() -> str:
    """Several lines, '# '-prefixed: CPU, SIMD per library, BLAS, threads, load, code paths,
    the host's speed now."""
    d = describe()
    env = " ".join(f"{k}={v}" for k, v in d["threads"]["env"].items()) or "no thread env set"
    la = " / ".join(f"{x:.2f}" for x in d["load_average"])
    h = d["host_speed"]
    return "\n".join([
        f"# CPU: {d['cpu']}; code paths: {d['cpu_paths']}; load average {la}",
        f"# SIMD: {d['simd']['numpy']} | {d['simd']['faiss']} | {d['simd']['opencv']}",
        f"# BLAS: {d['blas']}",
        f"# threads: {env}; faiss omp_get_max_threads {d['threads']['faiss_omp']}; "
        f"cv2.getNumThreads {d['threads']['cv2']}",
        f"# host speed: a {h['steps']:,}-step Python loop {h['p5_ms']:.3f} ms (p5 of "
        f"{h['runs']}), median {h['median_ms']:.3f} ms",
    ])


if __name__ == "__main__":
    add = __import__("argparse").ArgumentParser(description="print what benchmarks run on")
    add_argument(add)
    apply_cpu_paths()
    add.parse_args()
    print(cpu_line())
