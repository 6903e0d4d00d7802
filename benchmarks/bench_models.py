#!/usr/bin/env python3
"""Speed of the deep VPR descriptors: time per image at the model's input size and for a
640x480 frame (preprocessing included), and extraction throughput in batches.

Weights are the deterministic test recipe (speed does not depend on the values), so this runs
without the official checkpoints. EigenPlaces has CosPlace's architecture and speed.

    .venv/bin/python benchmarks/bench_models.py [--device cpu] [--repeats 3] [--batch 8]
        [--batch-images 16] [--models cosplace mixvpr mixvpr_4096 boq] [--json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from benchmarks import cpuinfo  # noqa: E402

from vlm_vpr_ros.descriptors.deep.specs import get_spec  # noqa: E402
from vlm_vpr_ros.descriptors.deep.torch_descriptor import DeepDescriptor  # noqa: E402
from vlm_vpr_ros.descriptors.deep.weights import build_model, recipe_state_dict  # noqa: E402

NATIVE_SIZE = (512, 512)  # CosPlace/EigenPlaces training/test size (SF-XL)


def frames(h: int, w: int, n: int, seed: int = 0) -> list[np.ndarray]:
    """Smooth random RGB frames (content does not change the compute)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        small = rng.integers(0, 256, (h // 8 + 1, w // 8 + 1, 3)).astype(np.uint8)
        out.append(np.ascontiguousarray(np.kron(small, np.ones((8, 8, 1), np.uint8))[:h, :w]))
    return out


def timed(fn, repeats: int) -> float:
    """Best of ``repeats`` runs (least disturbed by other processes on a shared machine)."""
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        samples.append(time.perf_counter() - t0)
    return min(samples)


def bench(name: str, device: str, repeats: int, batch: int, n_batch: int, fp16: bool) -> dict:
    spec = get_spec(name)
    desc = DeepDescriptor(spec, {"device": device, "batch_size": 1, "fp16": fp16},
                          state_dict=recipe_state_dict(build_model(spec)))
    h, w = spec.input_hw or NATIVE_SIZE
    own = frames(h, w, 1)[0]
    vga = frames(480, 640, 1, seed=1)[0]
    desc.describe([own])  # warm-up (allocator, kernels)
    t_own = timed(lambda: desc.describe([own]), repeats)
    desc.describe([vga])
    t_vga = timed(lambda: desc.describe([vga]), repeats)
    many = frames(480, 640, n_batch, seed=2)
    t_one = timed(lambda: desc.describe(many), max(2, repeats // 2))
    desc.batch_size = batch
    t_batch = timed(lambda: desc.describe(many), max(2, repeats // 2))
    return {"model": name, "dim": spec.dim, "input": f"{h}x{w}" if spec.input_hw else
            f"native ({h}x{w})", "ms_own_size": t_own * 1e3, "ms_640x480": t_vga * 1e3,
            "batch": batch, "images_per_s": n_batch / t_batch,
            "images_per_s_b1": n_batch / t_one,
            "device": str(desc.device) + (" fp16" if desc.fp16 else "")}


def bench_storage(n_refs: int, dim: int = 16384, n_queries: int = 50, top: int = 50) -> dict:
    """Memory and query time of a BoQ-sized submap, FAISS flat (float32) vs fp16 scalar
    quantizer (the map's ``--index fp16``), and how often the fp16 top-1 / top-50 agree with the
    exact ones. Synthetic data: unit vectors; queries are noisy copies of references."""
    import faiss

    rng = np.random.default_rng(0)
    refs = rng.standard_normal((n_refs, dim), dtype=np.float32)
    refs /= np.linalg.norm(refs, axis=1, keepdims=True)
    idx = rng.choice(n_refs, n_queries, replace=False)
    noise = rng.standard_normal((n_queries, dim), dtype=np.float32)
    q = refs[idx] + 0.5 / np.sqrt(dim) * noise  # noise of norm ~0.5
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    out = {"refs": n_refs, "dim": dim}
    results = {}
    for kind in ("flat", "fp16"):
        index = (faiss.IndexFlatL2(dim) if kind == "flat" else
                 faiss.IndexScalarQuantizer(dim, faiss.ScalarQuantizer.QT_fp16,
                                            faiss.METRIC_L2))
        if not index.is_trained:
            index.train(refs[:1000])
        index.add(refs)
        nbytes = faiss.serialize_index(index).nbytes
        index.search(q[:2], top)
        t0 = time.perf_counter()
        for i in range(n_queries):
            _, ids = index.search(q[i:i + 1], top)
            results.setdefault(kind, []).append(ids[0])
        out[kind] = {"bytes_per_ref": nbytes / n_refs,
                     "ms_per_query": (time.perf_counter() - t0) / n_queries * 1e3}
    flat, half = results["flat"], results["fp16"]
    out["top1_agree"] = float(np.mean([a[0] == b[0] for a, b in zip(flat, half)]))
    out["top50_overlap"] = float(np.mean([len(set(a) & set(b)) / top
                                          for a, b in zip(flat, half)]))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=["cosplace", "mixvpr", "mixvpr_4096", "boq"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch", type=int, default=8,
                    help="batch_size of the descriptor in the throughput column")
    ap.add_argument("--batch-images", type=int, default=16, help="640x480 frames per batch run")
    ap.add_argument("--fp16", action="store_true", help="float16 autocast (GPU only)")
    ap.add_argument("--storage-refs", type=int, default=0, metavar="N",
                    help="also measure a 16384-D (BoQ) submap of N synthetic references")
    ap.add_argument("--json", action="store_true", help="print only a JSON object")
    cpuinfo.add_argument(ap)
    cpuinfo.apply_cpu_paths()
    args = ap.parse_args()
    print(cpuinfo.cpu_line(), file=sys.stderr if args.json else sys.stdout, flush=True)
    rows = [bench(m, args.device, args.repeats, args.batch, args.batch_images, args.fp16)
            for m in args.models]
    storage = bench_storage(args.storage_refs) if args.storage_refs else None
    env = {"torch": torch.__version__, "threads": torch.get_num_threads(),
           "cpu": platform.processor() or platform.machine(), "python": platform.python_version(),
           "machine": cpuinfo.describe()}
    if args.json:
        print(json.dumps({"environment": env, "results": rows, "storage": storage}))
        return 0
    print(f"torch {env['torch']}, {env['threads']} threads, {env['cpu']}, device {args.device},"
          f" best of {args.repeats}")
    print(f"{'model':<13}{'dim':>6}  {'input':<16}{'ms/img own size':>16}{'ms/img 640x480':>16}"
          f"{'img/s b=1':>11}{f'img/s b={args.batch}':>12}")
    for r in rows:
        print(f"{r['model']:<13}{r['dim']:>6}  {r['input']:<16}{r['ms_own_size']:>16.0f}"
              f"{r['ms_640x480']:>16.0f}{r['images_per_s_b1']:>11.2f}{r['images_per_s']:>12.2f}")
    if storage:
        print(f"\nBoQ-sized submap: {storage['refs']} synthetic refs, {storage['dim']}-D")
        for kind in ("flat", "fp16"):
            s = storage[kind]
            print(f"  index {kind:<5} {s['bytes_per_ref'] / 1024:7.1f} KiB/ref  "
                  f"{s['ms_per_query']:7.1f} ms/query (top-50)")
        print(f"  fp16 vs flat: top-1 agrees {storage['top1_agree']:.0%}, "
              f"top-50 overlap {storage['top50_overlap']:.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
