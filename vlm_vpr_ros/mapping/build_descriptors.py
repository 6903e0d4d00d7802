"""Out-of-core map build from precomputed descriptors (``vlm-vpr build-map --descriptors``).

Memory stays bounded by the largest submap, not the map: descriptors are memory-mapped (or, for
shards with ids / Parquet, staged once into a memory-mapped ``.build/desc.npy`` in CSV row
order), checked chunk by chunk (NaN/inf or all-zero rows are skipped and listed in the manifest
like unreadable images), partitioned by position, and each submap is gathered, indexed and
written on its own. Resumable: every finished submap leaves a marker in ``OUT/.build``; a
re-run with the same inputs and settings continues with the next submap.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from vlm_vpr_ros import __version__
from vlm_vpr_ros.errors import DataError, MapError
from vlm_vpr_ros.files.atomic import atomic_save_npz, atomic_write_json
from vlm_vpr_ros.geodesy import farthest_km
from vlm_vpr_ros.mapping.assemble import plan_kinds
from vlm_vpr_ros.maps import indexes
from vlm_vpr_ros.mapping.balance import split_large
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
from vlm_vpr_ros.maps.format import MANIFEST, MAP_FORMAT, METRIC, content_matches
from vlm_vpr_ros.maps.partition import make_partition
from vlm_vpr_ros.maps.reference_map import ReferenceMap, Submap
from vlm_vpr_ros.maps.sources import CHUNK, DescriptorSource, descriptor_identity, open_source
from vlm_vpr_ros.maps.mapped import prefetch_rows
from vlm_vpr_ros.maps.store import VERSION, encode_ids, file_table, pq_name, write_submap
from vlm_vpr_ros.files.outputs import StagedOutput, written_by_us

log = logging.getLogger(__name__)


def _progress(total: int, desc: str, enabled: bool, unit: str = "row"):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=None if enabled else True,
                leave=False)


def _fingerprint(rows, source: DescriptorSource, settings: dict) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([source.fingerprint(), settings], sort_keys=True, default=str).encode())
    for f, la, lo in rows:
        h.update(f"{f}\t{la!r}\t{lo!r}\n".encode())
    return h.hexdigest()


def _up_to_date(out_dir: Path, fp: str, overwrite: bool) -> bool:
    """True when ``out_dir`` already holds this map; a different map (or a folder this tool did
    not write) is refused unless ``overwrite`` (then replaced only when the new one is complete,
    see :mod:`vlm_vpr_ros.files.outputs`)."""
    if not ((out_dir / MANIFEST).is_file() and written_by_us(out_dir, "map")) or overwrite:
        return False
    try:
        old = json.loads((out_dir / MANIFEST).read_text(encoding="utf-8")).get("source", {})
    except (OSError, ValueError, AttributeError):
        old = {}
    if isinstance(old, dict) and old.get("fingerprint") == fp:
        return True
    raise MapError(f"{out_dir} already holds a different map; pass --overwrite to replace it "
                   "(the old map stays until the new one is complete)")


def _prepare_work(work: Path, fp: str) -> None:
    """Leave the resumable scratch folder ``work`` ready for the build ``fp``."""
    job = work / "job.json"
    if job.exists():
        try:
            same = json.loads(job.read_text()).get("fingerprint") == fp
        except (OSError, ValueError):
            same = False
        if not same:
            log.info("discarding a partial build with other inputs or settings")
            shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)

    atomic_write_json(job, {"fingerprint": fp})


class _Rows:
    """Row reads from an (n, dim) .npy that map the file only for the duration of one read, so
    the pages an earlier read touched do not stay in the build's RSS (4.1M x 512 float32 is
    8.4 GB: mapped once for the whole build, it would all count)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        a = np.load(path, mmap_mode="r")
        self.shape = a.shape
        del a

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, idx) -> np.ndarray:
        if isinstance(idx, np.ndarray) and idx.dtype.kind in "iu":
            return self._gather(idx)
        a = np.load(self.path, mmap_mode="r")
        try:
            return np.array(a[idx], dtype=np.float32)
        finally:
            del a

    def _gather(self, rows: np.ndarray) -> np.ndarray:
        """Scattered rows by ``pread``, all reads queued first (``posix_fadvise``). Through
        the mapping, every row's page fault would map ~64 KB of neighbours (fault-around) into
        this process's RSS: 32k sampled rows of the 4.1M-row file measured 2.9 GB."""
        a = np.load(self.path, mmap_mode="r")
        offset, row_bytes, dtype, n, dim = a.offset, a.strides[0], a.dtype, *a.shape
        del a
        rows = np.asarray(rows, dtype=np.int64)
        if len(rows) and (rows.min() < 0 or rows.max() >= n):
            raise IndexError(f"{self.path}: row out of range [0, {n})")
        out = np.empty((len(rows), dim), dtype=dtype)
        prefetch_rows(self.path, row_bytes, rows, offset)
        with open(self.path, "rb", buffering=0) as fh:
            for i, r in enumerate(rows.tolist()):
                out[i] = np.frombuffer(os.pread(fh.fileno(), row_bytes, offset + r * row_bytes),
                                       dtype)
        return out.astype(np.float32, copy=False)


def _stage(source: DescriptorSource, file_rows: list[str], work: Path,
           progress: bool) -> tuple[_Rows, list[tuple[str, str]]]:
    """The descriptors in CSV row order (read through :class:`_Rows`) and CSV rows without a
    descriptor."""
    n = len(file_rows)
    if not source.has_ids and source.n_rows != n:
        raise DataError(f"{source.path}: {source.n_rows} descriptor rows but the coordinates "
                        f"CSV has {n} rows (without ids, rows must align one to one)")
    if source.single_array() is not None:
        return _Rows(source.shards[0].path), []
    staged, marker = work / "desc.npy", work / "staged.json"
    have_file = work / "have.npy"
    if marker.exists() and staged.exists() and have_file.exists():
        log.info("resuming: descriptors already staged")
        have = np.load(have_file)
        return _Rows(staged), _missing(file_rows, have)
    arr = np.lib.format.open_memmap(staged, mode="w+", dtype=np.float32,
                                    shape=(n, source.dim))
    del arr  # re-mapped per shard below (bounded RSS)
    have = np.zeros(n, dtype=bool)
    where = {f: i for i, f in enumerate(file_rows)} if source.has_ids else None
    if where is not None and len(where) != n:
        raise DataError("the coordinates CSV lists a file more than once; ids must be unique")
    bar = _progress(source.n_rows, "stage", progress)
    pos = 0
    for shard in source.shards:
        arr = np.load(staged, mmap_mode="r+")
        for off, chunk in shard.chunks():
            if where is None:
                arr[pos:pos + len(chunk)] = chunk
                have[pos:pos + len(chunk)] = True
                pos += len(chunk)
            else:
                ids = shard.ids[off:off + len(chunk)]
                try:
                    rows = np.fromiter((where[i] for i in ids), dtype=np.int64, count=len(ids))
                except KeyError as exc:
                    raise DataError(f"{shard.path}: id {exc.args[0]!r} is not in the "
                                    "coordinates CSV") from None
                dup = have[rows].copy()
                first = np.zeros(len(rows), dtype=bool)
                first[np.unique(rows, return_index=True)[1]] = True
                dup |= ~first
                if dup.any():
                    raise DataError(f"{shard.path}: duplicate descriptor for id "
                                    f"{ids[int(np.flatnonzero(dup)[0])]!r}")
                arr[rows] = chunk
                have[rows] = True
            bar.update(len(chunk))
        arr.flush()
        del arr
    bar.close()
    np.save(have_file, have)
    marker.write_text("{}")
    return _Rows(staged), _missing(file_rows, have)


def _missing(file_rows: list[str], have: np.ndarray) -> list[tuple[str, str]]:
    return [(file_rows[i], "no descriptor") for i in np.flatnonzero(~have)]


def _scan(desc: _Rows, ok: np.ndarray, file_rows: list[str], progress: bool):
    """Mark NaN/inf and all-zero rows as unusable (skipped, with the reason)."""
    bad: list[tuple[str, str]] = []
    bar = _progress(len(desc), "check", progress)
    for s in range(0, len(desc), CHUNK):
        chunk = np.asarray(desc[s:s + CHUNK], dtype=np.float32)
        finite = np.isfinite(chunk).all(1)
        zero = finite & ~chunk.any(1)
        for i in np.flatnonzero(ok[s:s + len(chunk)] & ~(finite & ~zero)):
            bad.append((file_rows[s + i], "zero descriptor" if zero[i] else "NaN/inf in "
                        "descriptor"))
            ok[s + i] = False
        bar.update(len(chunk))
    bar.close()
    return bad


def _by_submap(desc: _Rows, src_rows: np.ndarray, work: Path, progress: bool) -> _Rows:
    """The descriptors of ``src_rows`` (CSV rows in submap order) copied into one scratch
    file in that order, in a single sequential pass, so that every submap is then one
    contiguous read. Gathering a submap's rows straight from the input reads them one by one
    from all over the file: on this machine a cold row costs 0.8 ms (4.1M rows: ~55 min),
    while sequential reads run at ~500 MB/s."""
    path, marker = work / "by_submap.npy", work / "by_submap.json"
    n, dim = len(src_rows), desc.shape[1]
    if marker.exists() and path.exists():
        log.info("resuming: descriptors already in submap order")
        return _Rows(path)
    arr = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(n, dim))
    del arr
    row_bytes = dim * 4
    start = path.stat().st_size - n * row_bytes
    dest = np.full(len(desc), -1, dtype=np.int64)  # position of each CSV row in the file
    dest[src_rows] = np.arange(n)
    bar = _progress(len(desc), "sort", progress)
    fd = os.open(path, os.O_WRONLY)
    try:
        for s in range(0, len(desc), CHUNK):
            e = min(len(desc), s + CHUNK)
            d = dest[s:e]
            sel = np.flatnonzero(d >= 0)
            if len(sel):
                sel = sel[np.argsort(d[sel], kind="stable")]
                block = np.ascontiguousarray(desc[s:e][sel], dtype=np.float32)
                pos = d[sel]
                # runs of consecutive destinations (one per submap present in the chunk)
                cuts = np.flatnonzero(np.diff(pos) != 1) + 1
                for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(pos)]):
                    os.pwrite(fd, block[a:b].tobytes(), start + int(pos[a]) * row_bytes)
            bar.update(e - s)
        os.fsync(fd)
    finally:
        os.close(fd)
    bar.close()
    marker.write_text("{}")
    return _Rows(path)


def build_from_descriptors(source_path: str | Path, coords_csv: str | Path,
                           out_dir: str | Path, descriptor: str,
                           descriptor_config: Mapping[str, Any] | None = None,
                           partition: str = "kmeans", clusters: int = 100, seed: int = 0,
                           index: str = "pq", ram_budget_mb: float | None = None,
                           max_submap_size: int | None = None,
                           rerank_factor: int = indexes.DEFAULT_RERANK_FACTOR,
                           overwrite: bool = False, progress: bool = True) -> Any:
    """Build (or resume) a v2 map from precomputed descriptors; returns the opened map.
    Built in ``.OUT.partial/`` beside ``out_dir`` and swapped in when complete
    (:mod:`vlm_vpr_ros.files.outputs`): an old map stays until then."""
    t0 = time.monotonic()
    out_dir = Path(out_dir)
    indexes.check_kind(index)
    if index == "auto" and ram_budget_mb is None:
        raise MapError("--index auto needs --ram-budget-mb")
    source = open_source(source_path)
    identity, state = descriptor_identity(descriptor, source, dict(descriptor_config or {}))
    rows = read_coords_csv(coords_csv)
    settings = {"descriptor": identity, "partition": partition, "clusters": clusters,
                "seed": seed, "index": index, "ram_budget_mb": ram_budget_mb,
                "max_submap_size": max_submap_size, "rerank_factor": rerank_factor}
    fp = _fingerprint(rows, source, settings)
    if _up_to_date(out_dir, fp, overwrite):
        log.info("map %s is up to date", out_dir)
        return ReferenceMap.load(out_dir)
    with StagedOutput(out_dir, "map", overwrite, resumable=True) as staged:
        _prepare_work(staged.work, fp)
        _build_into(staged, source, identity, state, rows, fp, partition, clusters, seed,
                    index, ram_budget_mb, max_submap_size, rerank_factor, progress, t0)
    return ReferenceMap.load(out_dir)


def _build_into(staged: Any, source: DescriptorSource, identity: dict, state: dict, rows,
                fp: str, partition: str, clusters: int, seed: int, index: str,
                ram_budget_mb: float | None, max_submap_size: int | None, rerank_factor: int,
                progress: bool, t0: float) -> None:
    """The build proper: scratch in ``staged.work``, the finished map in ``staged.path``."""
    out_dir = staged.path
    work = staged.work
    file_rows = [r[0] for r in rows]
    coords = np.array([(r[1], r[2]) for r in rows], dtype=np.float64)
    del rows
    desc, skipped = _stage(source, file_rows, work, progress)
    ok = np.ones(len(file_rows), dtype=bool)
    missing_rows = {f for f, _ in skipped}
    if missing_rows:
        ok[[i for i, f in enumerate(file_rows) if f in missing_rows]] = False
    skipped += _scan(desc, ok, file_rows, progress)
    keep = np.flatnonzero(ok)
    if len(keep) == 0:
        raise MapError("no usable reference descriptor (all rows missing, NaN or zero)")
    if skipped:
        log.warning("%d references skipped (first: %s: %s)", len(skipped), *skipped[0])
    part = make_partition(partition, coords[keep, 0], coords[keep, 1], clusters, seed)
    part, groups = split_large(part, coords[keep, 0], coords[keep, 1], max_submap_size, seed)
    order = np.argsort(part.labels, kind="stable")
    bounds = np.searchsorted(part.labels[order], np.arange(len(part.names) + 1))
    counts = np.diff(bounds).tolist()
    kinds = plan_kinds(index, counts, source.dim, ram_budget_mb)
    trained = _pq_codebook(desc, keep, kinds, work, seed)
    sorted_desc = _by_submap(desc, keep[order], work, progress)
    stage = work / "map"
    subs_dir = work / "subs"
    subs_dir.mkdir(exist_ok=True)
    bar = _progress(len(keep), "index", progress)
    entries = []
    for k, name in enumerate(part.names):
        marker = subs_dir / f"{name}.json"
        if marker.exists():
            entries.append(json.loads(marker.read_text()))
            bar.update(counts[k])
            continue
        rows_k = keep[order[bounds[k]:bounds[k + 1]]]  # ascending CSV rows
        vecs = sorted_desc[bounds[k]:bounds[k + 1]]  # the same rows: one contiguous read
        kind = kinds[k]
        fi = indexes.make_index(kind, vecs, trained)
        rerank = vecs.astype(np.float16) if kind == "pq" else None
        recall = (indexes.measure_recall(fi, kind, rerank, vecs, rerank_factor, seed=seed)
                  if kind != "flat" else None)
        files = write_submap(stage, name, kind, fi, coords[rows_k],
                             encode_ids([file_rows[i] for i in rows_k]), rerank)
        entry = {"id": name, "group": groups[k], "count": int(len(rows_k)),
                 "centroid": [round(float(c), 7) for c in part.centroids[k]], "kind": kind,
                 "radius_km": round(farthest_km(*part.centroids[k], coords[rows_k]), 4),
                 "files": files, "file_table": file_table(stage, list(files.values()))}
        if recall:
            entry["recall"] = recall
        atomic_write_json(marker, entry)
        entries.append(entry)
        del vecs, fi, rerank
        bar.update(counts[k])
    bar.close()
    # move the finished files into place, manifest last
    table: dict[str, dict] = {}
    for e in entries:
        table.update(e.pop("file_table"))
    if state:
        atomic_save_npz(stage / "descriptor_state.npz", state)
        table.update(file_table(stage, ["descriptor_state.npz"]))
    (out_dir / "submaps").mkdir(parents=True, exist_ok=True)
    for rel, meta in table.items():
        _move_finished(stage / rel, out_dir / rel, meta)
    manifest = {
        "format": MAP_FORMAT, "version": VERSION, "software": f"vlm_vpr_ros {__version__}",
        "metric": METRIC, "descriptor": identity, "index": index,
        "index_params": {"rerank_factor": int(rerank_factor), "pq": pq_name(source.dim),
                         "ram_budget_mb": ram_budget_mb},
        "partition": {"method": part.method, "params": part.params},
        "source": {"fingerprint": fp, "descriptors": str(source.path), "rows": len(file_rows),
                   "skipped": [f"{f}: {why}" for f, why in skipped]
                   + [str(s) for s in source.skipped]},
        "n_references": int(len(keep)), "n_submaps": len(entries),
        "descriptor_state": "descriptor_state.npz" if state else None,
        "submaps": entries, "files": table,
    }
    atomic_write_json(out_dir / MANIFEST, manifest)
    del desc
    staged.commit(validate=lambda p: ReferenceMap.load(p, verify=False))
    log.info("built map %s from descriptors: %d references (%d skipped), %d submaps, %.1f s",
             staged.target, len(keep), len(skipped), len(entries), time.monotonic() - t0)


def _move_finished(src: Path, dst: Path, meta: dict) -> None:
    """Move a finished file into the staged map; idempotent: a run that failed after the move
    (disk full at the manifest, a failed validation) left it there, and its rerun finds it."""
    if not src.exists() and dst.is_file() and dst.stat().st_size == meta["bytes"] \
            and content_matches(dst, meta):
        return
    os.replace(src, dst)


def _pq_codebook(desc: _Rows, keep: np.ndarray, kinds: list[str], work: Path,
                 seed: int) -> Any:
    """The map's shared PQ codebook (trained once on a sample; kept in .build for resume)."""
    if "pq" not in kinds:
        return None
    import faiss

    path = work / "pq_codebook.faiss"
    if path.exists():
        return faiss.read_index(str(path))
    rng = np.random.default_rng(seed)
    sample = np.sort(rng.choice(keep, min(len(keep), indexes.PQ_TRAIN_SAMPLE), replace=False))
    trained = indexes.train_pq(np.asarray(desc[sample], dtype=np.float32))
    faiss.write_index(trained, str(path))
    return trained


def convert_map(old: Any, kind: str, rerank_factor: int, seed: int = 0) -> Any:
    """The same submaps (ids, positions, descriptors) with indexes of ``kind``, in memory
    (``vlm-vpr map upgrade``: v1 maps are held in memory anyway)."""
    indexes.check_kind(kind, indexes.SUBMAP_KINDS)
    vecs = [np.ascontiguousarray(s.vectors(), dtype=np.float32) for s in old.submaps]
    kinds = [indexes.effective_kind(kind, len(v)) for v in vecs]
    trained = None
    if "pq" in kinds:
        allv = np.concatenate(vecs)
        rng = np.random.default_rng(seed)
        pick = rng.choice(len(allv), min(len(allv), indexes.PQ_TRAIN_SAMPLE), replace=False)
        trained = indexes.train_pq(allv[np.sort(pick)])
    subs = []
    for s, v, k in zip(old.submaps, vecs, kinds):
        fi = indexes.make_index(k, v, trained)
        rerank = v.astype(np.float16) if k == "pq" else None
        recall = indexes.measure_recall(fi, k, rerank, v, rerank_factor, seed=seed) \
            if k != "flat" else None
        subs.append(Submap(s.id, s.centroid, np.asarray(s.coords, dtype=np.float64),
                           list(s.ids), fi, kind=k, rerank=rerank,
                           group=getattr(s, "group", "") or "", recall=recall))
    manifest = {k: v for k, v in old.manifest.items() if k not in ("files", "submaps")}
    manifest["index"] = kind
    manifest["index_params"] = {**manifest.get("index_params", {}),
                                "rerank_factor": int(rerank_factor)}
    m = ReferenceMap(manifest, subs, dict(old.descriptor_state))
    m.rerank_factor = int(rerank_factor)
    return m
