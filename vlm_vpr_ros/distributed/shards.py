"""The descriptor shard folder written by ``vlm-vpr describe`` (the shared contract with
``build-map --descriptors``, see docs/planet_scale.md and docs/ray.md).

Layout::

    SHARDS/shard_000000000.npy        (n_i, dim) float32, rows of CSV rows [start, start+size)
    SHARDS/shard_000000000.ids.txt    the n_i reference ids (CSV ``file`` values), one a line
    ...                               (a shard whose images were all unreadable has no files)
    SHARDS/descriptor_state.npz       fitted state (VLAD codebook, PCA), stateful models only
    SHARDS/describe.json              written last: format, version, descriptor identity,
                                      state file, skipped ids with reasons, counts
    SHARDS/.progress/job.json         what is being described (fingerprint), for resuming
    SHARDS/.progress/shard_*.json     one per finished shard: its rows and skipped images

A shard's ``.npy`` and ``.ids.txt`` are written atomically before its ``.progress`` record, so
a record means a complete shard; resuming recomputes only shards without one. ``describe.json``
exists only once every shard is done.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import DataError, DescriptorError, MapError
from vlm_vpr_ros.files.atomic import (atomic_save_npy, atomic_save_npz, atomic_write_bytes,
                                      atomic_write_json)
from vlm_vpr_ros.maps.sources import open_source, read_aligned

log = logging.getLogger(__name__)

SHARDS_FORMAT = "vlm_vpr_ros.descriptors"
SHARDS_VERSION = 1
DESCRIBE_JSON = "describe.json"
STATE_FILE = "descriptor_state.npz"
PROGRESS = ".progress"
DEFAULT_SHARD_SIZE = 1000


def shard_stem(start: int) -> str:
    """File stem of the shard starting at CSV row ``start`` (sorts in row order)."""
    return f"shard_{start:09d}"


def plan_shards(n: int, shard_size: int) -> list[tuple[int, int]]:
    """Contiguous [start, end) row ranges of at most ``shard_size`` rows."""
    if shard_size < 1:
        raise DataError(f"shard size must be >= 1, got {shard_size}")
    return [(s, min(n, s + shard_size)) for s in range(0, n, shard_size)]


def job_fingerprint(ids: Sequence[str], identity: Mapping[str, Any], shard_size: int) -> str:
    """What a shard folder holds: the ids in order, the descriptor (before fitting) and the
    shard size; a folder with another fingerprint is never silently mixed with new shards."""
    h = hashlib.sha256()
    ident = {k: v for k, v in identity.items() if k != "dim"}
    h.update(json.dumps([ident, int(shard_size)], sort_keys=True, default=str).encode())
    for i in ids:
        h.update(i.encode() + b"\n")
    return h.hexdigest()


def _job(folder: Path) -> dict | None:
    try:
        job = json.loads((folder / PROGRESS / "job.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return job if isinstance(job, dict) else None


def finished_job(folder: Path, fingerprint: str) -> dict | None:
    """``describe.json`` of a finished shard folder of this very job (None otherwise)."""
    job = _job(folder)
    if job is None or job.get("fingerprint") != fingerprint:
        return None
    try:
        meta = json.loads((folder / DESCRIBE_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    ok = isinstance(meta, dict) and meta.get("format") == SHARDS_FORMAT and all(
        k in meta for k in ("described", "skipped", "descriptor"))
    return meta if ok else None


def unfinished_job(folder: Path, fingerprint: str) -> bool:
    """Whether ``folder`` holds this job, unfinished, written in place (by a version before
    staging, or seeded by a benchmark): it is then moved into the staging folder and resumed."""
    job = _job(folder)
    return (job is not None and job.get("fingerprint") == fingerprint
            and not (folder / DESCRIBE_JSON).exists())


class ShardStore:
    """Writes (and, for resuming, lists) the shards of one describe job."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.progress = self.folder / PROGRESS

    # -- job ------------------------------------------------------------------------------------
    def open(self, fingerprint: str, n_rows: int, shard_size: int, overwrite: bool) -> None:
        """Start or resume a job. A folder holding other content (other shards, anything
        else) is an error unless ``overwrite``; then only our own files are removed."""
        job = self.progress / "job.json"
        if job.exists():
            old = json.loads(job.read_text())
            if old.get("fingerprint") == fingerprint:
                return
            if not overwrite:
                raise MapError(f"{self.folder} holds descriptors of other images or settings; "
                               "pass --overwrite to replace them or choose another --out")
            self._clear()
        elif self.folder.exists() and any(self.folder.iterdir()):
            if not overwrite:
                raise MapError(f"{self.folder} exists and is not empty; pass --overwrite or "
                               "choose another --out")
            self._clear()
        self.progress.mkdir(parents=True, exist_ok=True)
        atomic_write_json(job, {"fingerprint": fingerprint, "rows": n_rows,
                                "shard_size": shard_size})

    def _clear(self) -> None:
        for p in self.folder.glob("shard_*"):
            p.unlink()
        for name in (DESCRIBE_JSON, STATE_FILE):
            (self.folder / name).unlink(missing_ok=True)
        shutil.rmtree(self.progress, ignore_errors=True)

    # -- fitted state ---------------------------------------------------------------------------
    def load_state(self) -> dict[str, np.ndarray] | None:
        path = self.folder / STATE_FILE
        if not path.exists():
            return None
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}

    def save_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        atomic_save_npz(self.folder / STATE_FILE, arrays)

    # -- shards ---------------------------------------------------------------------------------
    def done(self) -> dict[int, dict]:
        """Finished shards: start row → progress record (``end``, ``n``, ``skipped``)."""
        out = {}
        for p in self.progress.glob("shard_*.json"):
            rec = json.loads(p.read_text())
            out[int(rec["start"])] = rec
        return out

    def write(self, start: int, end: int, ids: Sequence[str], feats: np.ndarray,
              skipped: Sequence[Mapping[str, str]]) -> None:
        """One finished shard: descriptors and ids first, then its progress record."""
        stem = shard_stem(start)
        feats = np.asarray(feats, dtype=np.float32)
        if len(ids) != len(feats):
            raise DescriptorError(f"shard {stem}: {len(ids)} ids for {len(feats)} descriptors")
        if any("\n" in i or "\r" in i for i in ids):
            raise DataError(f"shard {stem}: an id contains a line break")
        if len(ids):
            atomic_save_npy(self.folder / f"{stem}.npy", feats)
            atomic_write_bytes(self.folder / f"{stem}.ids.txt",
                               "".join(f"{i}\n" for i in ids).encode("utf-8"))
        else:  # every image of the shard was skipped: no (0, dim) arrays for readers to trip on
            (self.folder / f"{stem}.npy").unlink(missing_ok=True)
            (self.folder / f"{stem}.ids.txt").unlink(missing_ok=True)
        atomic_write_json(self.progress / f"{stem}.json",
                          {"start": start, "end": end, "n": len(ids), "skipped": list(skipped)})

    def finish(self, identity: Mapping[str, Any], stateful: bool, n_rows: int) -> dict:
        """Write ``describe.json`` (last) once every shard is done; returns it."""
        recs = sorted(self.done().values(), key=lambda r: r["start"])
        skipped = [s for r in recs for s in r["skipped"]]
        meta = {"format": SHARDS_FORMAT, "version": SHARDS_VERSION,
                "descriptor": dict(identity),
                "descriptor_state": STATE_FILE if stateful else None,
                "rows": n_rows, "described": sum(r["n"] for r in recs),
                "shards": sum(1 for r in recs if r["n"]), "skipped": skipped}
        atomic_write_json(self.folder / DESCRIBE_JSON, meta)
        return meta


def read_shards(folder: str | Path, ids: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Descriptors of a finished shard folder aligned with ``ids`` (the CSV's order).

    Returns ``(feats (n, dim) float32, ok (n,) bool)``; rows without a descriptor are zero and
    not ok. Delegates to the one reader of the descriptor-source contract
    (:mod:`vlm_vpr_ros.maps.sources`, issue 11); its errors are raised as MapError here.
    """
    try:
        return read_aligned(open_source(folder), list(ids))
    except DataError as exc:
        raise MapError(str(exc)) from None
