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
  ``OMP_WAIT_POLICY`` as set, ``faiss.omp_get_max_threads()``, ``cv2.getNumThreads()``.

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
import sys
from typing import Any

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
            "python": platform.python_version()}


def node_malloc() -> str:
    """glibc's malloc as the node sets it (``vlm_vpr_ros/ros/malloc.py``), applied to this
    process now; the '# malloc' line that says so (``--node-malloc`` of the benchmarks)."""
    from vlm_vpr_ros.ros import malloc

    applied = malloc.tune_malloc()
    return (f"# malloc: the node's settings ({malloc.ARENAS} arenas, mmap threshold "
            f"{malloc.MMAP_THRESHOLD // 2 ** 20} MiB, trim threshold "
            f"{malloc.TRIM_THRESHOLD // 2 ** 20} MiB; applied: {applied})")


def cpu_line() -> str:
    """Several lines, '# '-prefixed: CPU, SIMD per library, BLAS, threads, load, code paths."""
    d = describe()
    env = " ".join(f"{k}={v}" for k, v in d["threads"]["env"].items()) or "no thread env set"
    la = " / ".join(f"{x:.2f}" for x in d["load_average"])
    return "\n".join([
        f"# CPU: {d['cpu']}; code paths: {d['cpu_paths']}; load average {la}",
        f"# SIMD: {d['simd']['numpy']} | {d['simd']['faiss']} | {d['simd']['opencv']}",
        f"# BLAS: {d['blas']}",
        f"# threads: {env}; faiss omp_get_max_threads {d['threads']['faiss_omp']}; "
        f"cv2.getNumThreads {d['threads']['cv2']}",
    ])


if __name__ == "__main__":
    add = __import__("argparse").ArgumentParser(description="print what benchmarks run on")
    add_argument(add)
    apply_cpu_paths()
    add.parse_args()
    print(cpu_line())
