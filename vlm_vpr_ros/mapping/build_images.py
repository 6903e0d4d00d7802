"""Building a map from geotagged images: resumable descriptor extraction, partition, FAISS."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.descriptors import GlobalDescriptor, create_descriptor
from vlm_vpr_ros.errors import ImageDecodeError, MapError
from vlm_vpr_ros.localization.fusion.calibration import calibrate_references, save_calibration
from vlm_vpr_ros.localization.fusion.error_model import load_error_models
from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
from vlm_vpr_ros.mapping.image_sources import ImageSource
from vlm_vpr_ros.mapping.local_features import (LOO_QUERIES, ReferenceExtractor, calibrate_map,
                                                store_features)
from vlm_vpr_ros.maps.features import feature_files, read_features, write_submap_features
from vlm_vpr_ros.maps.map_images import record_source_images
from vlm_vpr_ros.files.images import check_rgb, load_image
from vlm_vpr_ros.maps.format import MANIFEST
from vlm_vpr_ros.mapping.assemble import assemble_map
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.files.atomic import atomic_save_npy, atomic_save_npz, atomic_write_json
from vlm_vpr_ros.maps.indexes import (DEFAULT_RERANK_FACTOR, check_kind)
from vlm_vpr_ros.files.outputs import StagedOutput, check_not_inside, written_by_us
from vlm_vpr_ros.types import LocalFeatures

log = logging.getLogger(__name__)
CHUNK = 128


def _progress(iterable, total: int, desc: str, enabled: bool):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="img", disable=None, leave=False)


def _fingerprint(rows, descriptor: GlobalDescriptor, partition: str, clusters: int,
                 index: Any, local: Mapping | None = None) -> str:
    h = hashlib.sha256()
    ident = {k: v for k, v in descriptor.identity().items() if k != "dim"}
    h.update(json.dumps([ident, partition, clusters, index] + ([local] if local else []),
                        sort_keys=True, default=str).encode())
    for f, la, lo in rows:
        h.update(f"{f}\t{la!r}\t{lo!r}\n".encode())
    return h.hexdigest()


def _local_path(uri: str) -> Path | None:
    """The folder of a ``file://`` URI (remote sources have no local stat: None)."""
    import urllib.parse

    u = urllib.parse.urlparse(uri)
    return Path(urllib.parse.unquote(u.path)) if u.scheme in ("", "file") else None


def images_fingerprint(images_dir: Path, rows) -> str:
    """Size and modification time (ns) of every reference image ("missing" when absent): a
    map built from other bytes is not up to date."""
    h = hashlib.sha256()
    for f, _, _ in rows:
        try:
            st = os.stat(images_dir / f)
            h.update(f"{f}\t{st.st_size}\t{st.st_mtime_ns}\n".encode())
        except OSError:
            h.update(f"{f}\tmissing\n".encode())
    return h.hexdigest()


def _images(root: Path, rows, idx) -> Iterator[tuple[int, np.ndarray | None]]:
    for i in idx:
        try:
            yield i, check_rgb(load_image(root / rows[i][0]), str(root / rows[i][0]))
        except ImageDecodeError as exc:
            log.warning("skipping reference: %s", exc)
            yield i, None


def build_map(images_dir: str | Path, coords_csv: str | Path, out_dir: str | Path,
              descriptor: str = "vlad_rootsift", descriptor_config: Mapping | None = None,
              partition: str = "kmeans", clusters: int = 100, overwrite: bool = False,
              progress: bool = True, seed: int = 0, index: str = "flat",
              ram_budget_mb: float | None = None, max_submap_size: int | None = None,
              rerank_factor: int = DEFAULT_RERANK_FACTOR, engine: Any = None,
              local_features: str = "sift", feature_options: Mapping | None = None,
              matcher_options: Mapping | None = None,
              calibration_conditions: str | Sequence[str] | None = None) -> ReferenceMap:
    """Build (or resume building) a map folder; the format is in docs/maps.md ("Map format").
    ``calibration_conditions``: the query conditions of the verification calibration
    (default: full size, 640x480, 480x360, JPEG q40; docs/verification.md).
    ``local_features``: verification preset whose local features are stored in the map
    ("sift", "disk_lightglue"; "none": no features, answers unverified; docs/verification.md).
    ``engine``: describe (and fit), partition and index elsewhere, e.g. on Ray
    (``vlm_vpr_ros.distributed.build``); by default everything runs in this process.

    The map is built in ``.OUT.partial/`` next to ``out_dir`` and swapped in when complete and
    valid (:mod:`vlm_vpr_ros.files.outputs`): an old map stays until then, and a failed or
    interrupted build (full disk, Ctrl-C, kill) resumes from its finished chunks."""
    out_dir = Path(out_dir)
    if engine is None:  # an engine may read a URI (s3://, gs://, file://): keep it a string
        images_dir = Path(images_dir)
    rows = read_coords_csv(coords_csv)
    desc = create_descriptor(descriptor, descriptor_config)
    check_kind(index)  # validate the name before any work

    refx = ReferenceExtractor(desc, local_features, feature_options, matcher_options)
    refx.calibration_conditions = calibration_conditions
    if index == "auto" and ram_budget_mb is None:
        raise MapError("--index auto needs --ram-budget-mb")
    extra_opts = (ram_budget_mb, max_submap_size, rerank_factor)
    check_not_inside(out_dir, [images_dir if isinstance(images_dir, Path) else None,
                               coords_csv], allow_out_inside=True)
    fp = _fingerprint(rows, desc, partition, clusters,
                      index if extra_opts == (None, None, DEFAULT_RERANK_FACTOR)
                      else [index, *extra_opts],
                      refx.identity() if refx.enabled else None)
    local = images_dir if isinstance(images_dir, Path) else _local_path(str(images_dir))
    fp_images = images_fingerprint(local, rows) if local is not None else ""
    if (out_dir / MANIFEST).is_file() and written_by_us(out_dir, "map") and not overwrite:
        try:
            source = json.loads((out_dir / MANIFEST).read_text(encoding="utf-8")).get("source")
        except (OSError, ValueError, AttributeError):
            source = None
        source = source if isinstance(source, dict) else {}
        if source.get("fingerprint") == fp:
            if source.get("images_fingerprint") in (None, fp_images):
                log.info("map %s is up to date", out_dir)
                return ReferenceMap.load(out_dir)
            raise MapError(f"{out_dir} is out of date: reference images in {images_dir} were "
                           "deleted, replaced or modified since it was built; pass --overwrite "
                           "to rebuild it")
        raise MapError(f"{out_dir} already holds a different map (other images or settings); "
                       "pass --overwrite to replace it (the old map stays until the new one is "
                       "complete)")
    with StagedOutput(out_dir, "map", overwrite, resumable=True) as stage:
        ref_map = _build_staged(images_dir, rows, desc, stage, fp, fp_images, partition,
                                clusters, seed, index, progress, out_dir, engine,
                                extra_opts, refx)
    ref_map.path = out_dir
    return ref_map


def _build_staged(images_dir: Any, rows, desc: GlobalDescriptor, stage: StagedOutput, fp: str,
                  fp_images: str, partition: str, clusters: int, seed: int, index: str,
                  progress: bool, out_dir: Path, engine: Any = None,
                  extra_opts: tuple = (None, None, DEFAULT_RERANK_FACTOR),
                  refx: Any = None) -> ReferenceMap:
    ram_budget_mb, max_submap_size, rerank_factor = extra_opts
    work = stage.work
    work.mkdir(parents=True, exist_ok=True)
    job = work / "job.json"
    if job.exists():
        try:
            old = json.loads(job.read_text()).get("fingerprint")
        except (OSError, ValueError, AttributeError):
            old = None
        if old != [fp, fp_images]:
            log.info("discarding a partial build with other settings or images")
            shutil.rmtree(work)
            work.mkdir(parents=True)
        else:
            log.info("resuming the partial build in %s", stage.root)
    atomic_write_json(job, {"fingerprint": [fp, fp_images], "n": len(rows)})
    t0 = time.monotonic()
    if engine is not None:
        feats, ok = engine.describe(desc, images_dir, rows, work, progress)
        if refx is not None and refx.enabled:
            _extract_local(refx, images_dir, rows, work, progress, ok)
    else:
        if desc.needs_fit:
            _fit(desc, images_dir, rows, work, progress)
        feats, ok = _extract(desc, images_dir, rows, work, progress, refx)
    identity = desc.identity()
    skipped = [rows[i][0] for i in range(len(rows)) if not ok[i]]
    keep = np.flatnonzero(ok)
    if len(keep) == 0:
        raise MapError("no reference image could be read")
    coords = np.array([[rows[i][1], rows[i][2]] for i in keep], dtype=np.float64)
    ids = [rows[i][0] for i in keep]
    ref_map = assemble_map(feats[keep], coords, ids, identity, desc.state_arrays(), partition,
                           clusters, seed, extra={"fingerprint": fp, "images_fingerprint":
                                                  fp_images, "rows": len(rows),
                                                  "skipped": skipped}, index=index,
                           ram_budget_mb=ram_budget_mb, max_submap_size=max_submap_size,
                           rerank_factor=rerank_factor, engine=engine)
    if stage.path.exists():
        shutil.rmtree(stage.path)  # a half-saved folder of an earlier attempt
    ref_map.save(stage.path)
    local = images_dir if isinstance(images_dir, Path) else _local_path(str(images_dir))
    if local is not None and local.is_dir():  # where its pictures are (docs/maps.md)
        ref_map.manifest = record_source_images(stage.path, local, ids)
    write_map_calibration(ref_map, feats[keep], coords)
    if refx is not None and refx.enabled:
        write_local_features(ref_map, refx, ChunkFeatures(work, rows, refx), progress,
                             images_dir=local)
    stage.commit(validate=lambda p: ReferenceMap.load(p))
    dt = time.monotonic() - t0
    if skipped:
        log.warning("skipped %d unreadable reference image(s): %s%s", len(skipped),
                    ", ".join(skipped[:10]), " ..." if len(skipped) > 10 else "")
    log.info("built map %s: %d references (%d skipped), %d submaps, %.1f s (%.1f img/s)",
             out_dir, len(keep), len(skipped), len(ref_map.submaps), dt, len(rows) / dt)
    return ref_map


def write_map_calibration(ref_map: ReferenceMap, desc: np.ndarray, coords: np.ndarray) -> None:
    """The fusion's leave-one-out calibration, stored as the map's one optional
    ``calibration.json`` (docs/fusion.md); rows of ``desc``/``coords`` in any order."""
    t0 = time.monotonic()
    doc = calibrate_references(desc, coords, load_error_models().get())
    save_calibration(ref_map, doc)
    log.info("fusion calibration: %d leave-one-out queries, visual scale %s, %.1f s",
             doc["loo"].get("queries", 0), doc["visual_scale"], time.monotonic() - t0)


def write_local_features(ref_map: ReferenceMap, refx: Any, features_of: Any,
                         progress: bool = False, loo_queries: int | None = None,
                         images_dir: Path | None = None) -> None:
    """Store the references' local features in the saved map and calibrate ``p_correct`` by
    leave-one-out on them (docs/verification.md; ``loo_queries``: at most this many queries,
    default :data:`~vlm_vpr_ros.mapping.local_features.LOO_QUERIES`), under the query
    conditions ``refx.calibration_conditions`` (degraded copies of the images in
    ``images_dir``)."""
    t0 = time.monotonic()
    store_features(ref_map, features_of, refx)
    log.info("local features stored (%s, %.0f kB per reference), %.1f s",
             refx.preset.name, ref_map.manifest["local_features"]["bytes"]
             / max(1, ref_map.n_references) / 1e3, time.monotonic() - t0)
    calibrate_map(ref_map, loo_queries or LOO_QUERIES, progress=progress,
                  matcher_options=refx.matcher_options,
                  feature_options=refx.feature_options,
                  conditions=refx.calibration_conditions, images_dir=images_dir,
                  descriptor=refx.descriptor)


class ChunkFeatures:
    """Local features of the build's rows, read back from the resumable chunk files."""

    def __init__(self, work: Path, rows, refx: Any) -> None:
        self.work, self.refx, self.pos = work, refx, {f: i for i, (f, _, _) in enumerate(rows)}
        self._open: dict[int, Any] = {}

    def __call__(self, ref_id: str):
        i = self.pos[ref_id]
        s = i - i % CHUNK
        if s not in self._open:
            self._open = {s: read_features(self.work, f"chunk_{s:08d}")}
        return self._open[s](i - s)


def fit_sample_indices(n: int, desc: GlobalDescriptor) -> np.ndarray:
    """Rows a stateful descriptor is fitted on: ``fit_max_images`` evenly spread rows (the
    same for every engine, so local and distributed builds learn the same state)."""
    limit = int(desc.config.get("fit_max_images", 2000))
    return np.unique(np.linspace(0, n - 1, min(limit, n)).astype(int))


def _fit(desc: GlobalDescriptor, root: Path, rows, work: Path, progress: bool) -> None:
    state_file = work / "descriptor_state.npz"
    if state_file.exists():
        with np.load(state_file, allow_pickle=False) as npz:
            desc.load_state({k: npz[k] for k in npz.files})
        log.info("resumed fitted descriptor state")
        return
    idx = fit_sample_indices(len(rows), desc)
    images = (im for _, im in _progress(_images(root, rows, idx), len(idx), "fit", progress)
              if im is not None)
    desc.fit(images, progress=progress)
    atomic_save_npz(state_file, desc.state_arrays())


def _extract(desc: GlobalDescriptor, root: Path, rows, work: Path, progress: bool,
             refx: Any = None):
    """Describe every row in resumable chunks (and store the chunk's local features when
    ``refx`` extracts them)."""
    local = refx is not None and refx.enabled
    n = len(rows)
    feats = np.zeros((n, desc.dim), np.float32)
    ok = np.zeros(n, bool)
    starts = range(0, n, CHUNK)
    bar = _progress(None, n, "describe", progress) if progress else None
    for s in starts:
        part, okf = work / f"chunk_{s:08d}.npy", work / f"chunk_{s:08d}.ok.npy"
        lf_done = not local or all((work / r).exists()
                                   for r in feature_files(f"chunk_{s:08d}").values())
        e = min(n, s + CHUNK)
        if part.exists() and okf.exists() and lf_done:
            feats[s:e], ok[s:e] = np.load(part), np.load(okf)
        else:
            good, images = [], []
            for i, im in _images(root, rows, range(s, e)):
                if im is not None:
                    good.append(i)
                    images.append(im)
            if images:
                feats[good], lf = refx.describe(images) if refx is not None else \
                    (desc.describe(images), None)
                ok[good] = True
            if local:
                by_row = dict(zip(good, lf)) if images else {}
                empty = _empty_features(refx)
                write_submap_features(work, f"chunk_{s:08d}",
                                      [by_row.get(i, empty) for i in range(s, e)],
                                      refx.extractor.descriptor_dtype,
                                      refx.extractor.descriptor_dim)
            atomic_save_npy(part, feats[s:e])
            atomic_save_npy(okf, ok[s:e])
        if bar is not None:
            bar.update(e - s)
    if bar is not None:
        bar.close()
    return feats, ok


def _extract_local(refx: Any, images_dir: Any, rows, work: Path, progress: bool,
                   ok: np.ndarray) -> None:
    """Local features of the described rows, in this process, in the same resumable chunk
    files as :func:`_extract` (builds whose descriptors came from an engine)."""
    source = ImageSource(str(images_dir))
    x, empty = refx.extractor, _empty_features(refx)
    bar = _progress(None, len(rows), "local features", progress) if progress else None
    for s in range(0, len(rows), CHUNK):
        e, stem = min(len(rows), s + CHUNK), f"chunk_{s:08d}"
        if not all((work / r).exists() for r in feature_files(stem).values()):
            feats = []
            for i in range(s, e):
                try:
                    feats.append(x.extract(source.load(rows[i][0]), refx.preset.max_keypoints)
                                 if ok[i] else empty)
                except ImageDecodeError as exc:  # read by the engine, not here: a change
                    raise MapError(f"reference {rows[i][0]} became unreadable during the "
                                   f"build: {exc}") from None
            write_submap_features(work, stem, feats, x.descriptor_dtype, x.descriptor_dim)
        if bar is not None:
            bar.update(e - s)
    if bar is not None:
        bar.close()


def _empty_features(refx: Any):
    dim, dtype = refx.extractor.descriptor_dim, refx.extractor.descriptor_dtype
    return LocalFeatures(np.zeros((0, 2), np.float32), np.zeros((0, dim), dtype), (0, 0))

