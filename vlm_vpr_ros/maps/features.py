"""Local features of the references, stored in the map for the verification stage.

Per submap, three memory-mapped ``.npy`` files (listed with size + sha256 in the manifest's
``files`` table like every other map file)::

    submaps/<stem>.lf_rows.npy   (n, 4) int64: first keypoint, keypoint count, frame width, height
    submaps/<stem>.lf_kpts.npy   (N, 2) float16 keypoints, pixels of the extraction frame
    submaps/<stem>.lf_desc.npy   (N, d) descriptors in the feature's storage dtype (SIFT: uint8)

``<stem>`` is the submap id (``<id>.g<generation>`` after ``vlm-vpr map add/remove``); row ``j``
belongs to reference ``j`` of the submap. The manifest's ``local_features`` section is
versioned and names the feature (name, config, dtype), the verification preset and the
keypoint caps, and lists each submap's files and counts.

Storage: SIFT at 1000 keypoints is 1000 x (128 + 4) bytes = 132 kB per reference (fp16
coordinates, uint8 descriptors): 44 MB for a 332-image city map, 1.3 GB for a 10,000-frame
teach run, 0.54 TB for the 4.1M-reference planet map — which is why maps built from
precomputed descriptors store none and verify from the reference images when a folder is
given, or answer unverified (docs/verification.md, "Storage").

Reading: :class:`FeatureStore` checks the section against the manifest at open (every submap
present, counts and sizes right, the keypoint caps, the feature the verifier expects) and the
content of every feature file by the map's cheap content check
(:func:`~vlm_vpr_ros.maps.format.check_content`: files up to 256 KiB by their whole sha256,
larger ones by sampled pages), so files swapped between submaps, a garbage small file or a
manifest sha256 that does not match are refused at open, and raises one :class:`MapError`
naming what is wrong; files are memory-mapped per submap on first use, and their sizes are
compared with the manifest before every read (a file truncated under a running node is a
MapError, not a SIGBUS); a file written since its check (new modification time) is checked
again and the submap's features refused when it no longer matches.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from vlm_vpr_ros.errors import MapError
from vlm_vpr_ros.files.atomic import atomic_write_json
from vlm_vpr_ros.maps.format import (MANIFEST, check_content, content_error, content_matches,
                                     file_table)
from vlm_vpr_ros.maps.mapped import load_array
from vlm_vpr_ros.types import LocalFeatures

log = logging.getLogger(__name__)

FEATURES_FORMAT = "vlm_vpr_ros.local_features"
FEATURES_VERSION = 1
ROLES = ("rows", "keypoints", "descriptors")
_SUFFIX = {"rows": "lf_rows", "keypoints": "lf_kpts", "descriptors": "lf_desc"}


def feature_files(stem: str) -> dict[str, str]:
    """Relative paths of one submap's feature files."""
    return {role: f"submaps/{stem}.{_SUFFIX[role]}.npy" for role in ROLES}


def _open_npy(path: Path, dtype: np.dtype, shape: tuple[int, ...]) -> np.ndarray:
    from numpy.lib.format import open_memmap

    path.parent.mkdir(parents=True, exist_ok=True)
    if os.path.lexists(path):  # a temporary name: never written through a link left there
        os.unlink(path)
    return open_memmap(path, mode="w+", dtype=dtype, shape=shape)


def write_submap_features(root: Path, stem: str, feats: Sequence[LocalFeatures],
                          dtype: np.dtype, dim: int) -> dict[str, Any]:
    """Write one submap's feature files (row j = ``feats[j]``) through temporary names;
    returns ``{"files": {role: rel}, "count": n, "n_keypoints": N}``."""
    rels = feature_files(stem)
    counts = np.array([len(f) for f in feats], dtype=np.int64)  # pass 1 of 2 over ``feats``
    total = int(counts.sum())
    rows = np.zeros((len(feats), 4), np.int64)
    rows[:, 0] = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(feats) else []
    rows[:, 1] = counts
    tmp = {r: (root / rel).with_name(f".{Path(rel).name}.tmp{os.getpid()}")
           for r, rel in rels.items()}
    try:
        kp = _open_npy(tmp["keypoints"], np.dtype(np.float16), (total, 2))
        de = _open_npy(tmp["descriptors"], np.dtype(dtype), (total, dim))
        for j, f in enumerate(feats):
            a, n = int(rows[j, 0]), int(rows[j, 1])
            rows[j, 2:] = f.size
            if len(f) != n:
                raise MapError(f"local features of row {j} changed while being written")
            if n:
                kp[a:a + n] = np.asarray(f.keypoints, np.float32)
                de[a:a + n] = np.asarray(f.descriptors).astype(dtype, copy=False)
        for arr in (kp, de):
            arr.flush()
        del kp, de
        rw = _open_npy(tmp["rows"], np.dtype(np.int64), rows.shape)
        rw[:] = rows
        rw.flush()
        del rw
        for role, rel in rels.items():
            with open(tmp[role], "rb+") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp[role], root / rel)
    except BaseException:
        for t in tmp.values():
            t.unlink(missing_ok=True)
        raise
    return {"files": rels, "count": len(feats), "n_keypoints": total}


def read_features(root: Path, stem: str) -> Callable[[int], LocalFeatures]:
    """Row reader over files written by :func:`write_submap_features` outside a map (a build's
    resumable work files): no manifest, shapes checked against each other."""
    rels = feature_files(stem)
    try:
        rows, kp, de = (np.load(root / rels[r], mmap_mode="r", allow_pickle=False)
                        for r in ROLES)
    except (OSError, ValueError) as exc:
        raise MapError(f"{root}: cannot read the local features {stem}: {exc}") from exc
    if rows.ndim != 2 or rows.shape[1] != 4 or len(kp) != len(de) or \
            int(np.asarray(rows[:, 1]).sum()) != len(kp):
        raise MapError(f"{root}: local features {stem} are inconsistent; delete them to "
                       "re-extract")

    def get(j: int) -> LocalFeatures:
        a, n, w, h = (int(v) for v in rows[j])
        return LocalFeatures(np.asarray(kp[a:a + n], np.float32), np.array(de[a:a + n]),
                             (w, h))
    return get


def make_section(feature_identity: Mapping[str, Any], preset: str, max_keypoints: int,
                 query_max_keypoints: int, submaps: Mapping[str, Mapping[str, Any]],
                 files_meta: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The manifest's ``local_features`` section."""
    nbytes = sum(int(files_meta[rel]["bytes"]) for e in submaps.values()
                 for rel in e["files"].values())
    return {"format": FEATURES_FORMAT, "version": FEATURES_VERSION,
            "feature": dict(feature_identity), "preset": preset,
            "max_keypoints": int(max_keypoints),
            "query_max_keypoints": int(query_max_keypoints),
            "bytes": nbytes, "n_keypoints": sum(int(e["n_keypoints"]) for e in submaps.values()),
            "submaps": {sid: dict(e) for sid, e in sorted(submaps.items())}}


def attach_features(map_dir: Path, manifest: dict,
                    by_submap: Mapping[str, Sequence[LocalFeatures]],
                    feature_identity: Mapping[str, Any], preset: str, max_keypoints: int,
                    query_max_keypoints: int) -> dict:
    """Write the feature files of a saved map (``by_submap[id]``: features in the submap's row
    order; a lazy sequence is read a few times, never held whole), list them in ``files``, add
    the section and rewrite the manifest (last). Returns the new manifest."""
    dtype = np.dtype(feature_identity["dtype"])
    dim = int(feature_identity["descriptor_dim"])
    entries, rels = {}, []
    for s in manifest["submaps"]:
        entries[s["id"]] = write_submap_features(map_dir, s["id"], by_submap[s["id"]], dtype,
                                                 dim)
        rels += list(entries[s["id"]]["files"].values())
    new = dict(manifest)
    new["files"] = {**manifest["files"], **file_table(map_dir, rels)}
    new["local_features"] = make_section(feature_identity, preset, max_keypoints,
                                         query_max_keypoints, entries, new["files"])
    atomic_write_json(map_dir / MANIFEST, new)
    return new


def bytes_per_reference(manifest: Mapping[str, Any]) -> float | None:
    """Mean stored feature bytes per reference (None: the map stores no local features)."""
    sec = manifest.get("local_features")
    n = int(manifest.get("n_references", 0))
    if not sec or not n:
        return None
    return float(sec.get("bytes", 0)) / n


# -- reading ----------------------------------------------------------------------------------
class _SubmapFeatures:
    def __init__(self, root: Path, entry: Mapping[str, Any], sizes: Mapping[str, int],
                 dtype: np.dtype, dim: int) -> None:
        self.root, self.entry, self.dtype, self.dim = root, entry, dtype, dim
        self.files: dict[str, str] = dict(entry["files"])
        self.sizes = {rel: int(sizes[rel]) for rel in self.files.values()}
        self.count, self.total = int(entry["count"]), int(entry["n_keypoints"])
        self._arrays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._inodes: dict[str, tuple[int, int]] = {}
        #: (dev, ino, mtime_ns, ctime_ns) of each file when its content was last checked
        self._seen: dict[str, tuple[int, int, int, int]] = {}
        self._metas: dict[str, Mapping[str, Any]] = {}
        self._refused = ""
        self._lock = threading.Lock()

    def note_checked(self, metas: Mapping[str, Mapping[str, Any]]) -> None:
        """Record the files' identity and times (their content is checked next)."""
        self._metas = {rel: metas[rel] for rel in self.files.values()}
        for rel in self.files.values():
            try:
                st = os.stat(self.root / rel)
            except OSError:
                continue
            self._seen[rel] = (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns)

    def check(self) -> None:
        """MapError when a file is missing or not the size the manifest says (before any read
        of a mapped page: a truncated mapped file would crash the process with SIGBUS), or was
        written since its content was checked and no longer matches the manifest."""
        if self._refused:
            raise MapError(self._refused)
        for rel, size in self.sizes.items():
            try:
                st = os.stat(self.root / rel)
            except OSError as exc:
                if self._arrays is not None:
                    continue  # unlinked by a newer generation: the mapping keeps the data
                raise MapError(f"{self.root}: missing local-feature file {rel} "
                               f"({exc.strerror})") from None
            same = self._inodes.get(rel) in (None, (st.st_dev, st.st_ino))
            if same and st.st_size != size:
                raise MapError(f"{self.root}: {rel} has {st.st_size} bytes, manifest says {size}"
                               " (truncated or modified); rebuild or reload the map")
            now = (st.st_dev, st.st_ino, st.st_mtime_ns, st.st_ctime_ns)
            if same and rel in self._metas and self._seen.get(rel, now) != now:
                try:
                    ok = content_matches(self.root / rel, self._metas[rel])
                except OSError:
                    ok = False
                if ok is False:
                    self._refused = str(content_error(self.root, rel, " since it was checked"))
                    log.error("%s", self._refused)
                    raise MapError(self._refused)
                self._seen[rel] = now

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._arrays is None:
            with self._lock:
                if self._arrays is None:
                    self.check()
                    f = self.files
                    rows = load_array(self.root, f["rows"], (self.count, 4), "i8")
                    kp = load_array(self.root, f["keypoints"], (self.total, 2), "f2")
                    de = load_array(self.root, f["descriptors"], (self.total, self.dim),
                                     self.dtype.str.lstrip("<>|="))
                    if self.count and (int(rows[:, 1].sum()) != self.total
                                       or rows[:, 0].min() < 0 or rows[:, 1].min() < 0
                                       or int((rows[:, 0] + rows[:, 1]).max()) > self.total):
                        raise MapError(f"{self.root}: {f['rows']} does not index "
                                       f"{f['keypoints']} ({self.total} keypoints)")
                    for rel in f.values():
                        st = os.stat(self.root / rel)
                        self._inodes[rel] = (st.st_dev, st.st_ino)
                    self._arrays = (rows, kp, de)
        self.check()
        return self._arrays

    def get(self, row: int) -> LocalFeatures:
        rows, kp, de = self.arrays()
        a, n, w, h = (int(v) for v in rows[row])
        return LocalFeatures(np.asarray(kp[a:a + n], np.float32), np.array(de[a:a + n]),
                             (w, h))


class FeatureStore:
    """Read access to a map's stored local features (module docstring)."""

    def __init__(self, root: Path, section: Mapping[str, Any],
                 subs: dict[str, _SubmapFeatures]) -> None:
        self.root, self.section, self._subs = root, dict(section), subs

    @property
    def feature(self) -> dict[str, Any]:
        return dict(self.section["feature"])

    @property
    def preset(self) -> str:
        return str(self.section.get("preset", ""))

    @property
    def max_keypoints(self) -> int:
        return int(self.section["max_keypoints"])

    @property
    def query_max_keypoints(self) -> int:
        return int(self.section["query_max_keypoints"])

    def get(self, submap: str, row: int) -> LocalFeatures:
        """Features of reference ``row`` of submap ``submap``."""
        sub = self._subs.get(submap)
        if sub is None:
            raise MapError(f"{self.root}: no local features for submap {submap!r}")
        if not 0 <= row < sub.count:
            raise MapError(f"{self.root}: submap {submap} has {sub.count} feature rows, "
                           f"asked for row {row}")
        return sub.get(row)

    def check(self) -> None:
        for sub in self._subs.values():
            sub.check()

    @classmethod
    def open(cls, root: Path, manifest: Mapping[str, Any]) -> "FeatureStore | None":
        """The map's feature store, checked against its manifest (sizes, counts, every submap);
        None when the map stores no local features. MapError naming the problem otherwise."""
        sec = manifest.get("local_features")
        if not sec:
            return None
        where = f"{root}: local_features"
        if not isinstance(sec, dict) or sec.get("format") != FEATURES_FORMAT:
            raise MapError(f"{where}: not a {FEATURES_FORMAT} section")
        if sec.get("version") != FEATURES_VERSION:
            raise MapError(f"{where}: version {sec.get('version')!r} is not supported (this "
                           f"software reads version {FEATURES_VERSION}); rebuild the map")
        try:
            feat = sec["feature"]
            dtype, dim = np.dtype(feat["dtype"]), int(feat["descriptor_dim"])
            entries = dict(sec["submaps"])
        except (KeyError, TypeError, ValueError) as exc:
            raise MapError(f"{where}: malformed ({exc})") from None
        for key in ("max_keypoints", "query_max_keypoints"):
            v = sec.get(key)
            if isinstance(v, bool) or not isinstance(v, int) or not 8 <= v <= 100_000:
                raise MapError(f"{root}: manifest field 'local_features.{key}' is {v!r}, "
                               "expected an integer in 8..100000")
        files = manifest.get("files", {})
        subs: dict[str, _SubmapFeatures] = {}
        for s in manifest["submaps"]:
            e = entries.get(s["id"])
            if not isinstance(e, dict) or set(e.get("files", {})) != set(ROLES):
                raise MapError(f"{where}: submap {s['id']} has no feature files; rebuild the "
                               "map with 'vlm-vpr build-map ... --overwrite' (it stores the "
                               "local features), or verify from the reference images "
                               "(--reference-images DIR)")
            if int(e.get("count", -1)) != int(s["count"]):
                raise MapError(f"{where}: submap {s['id']} has features for "
                               f"{e.get('count')} references, the submap holds {s['count']}")
            for rel in e["files"].values():
                meta = files.get(rel)
                if not isinstance(meta, dict) or not isinstance(meta.get("bytes"), int):
                    raise MapError(f"{root}: {rel} is not listed in the manifest")
                if ".." in Path(rel).parts or Path(rel).is_absolute():
                    raise MapError(f"{root}: file {rel!r} is outside the map folder")
            subs[s["id"]] = _SubmapFeatures(root, e, {r: files[r]["bytes"]
                                                      for r in e["files"].values()}, dtype, dim)
        rels = [rel for sub in subs.values() for rel in sub.files.values()]
        for sub in subs.values():  # before the check: a change made during it is seen later
            sub.note_checked(files)
        for sub in subs.values():
            sub.check()  # sizes first: a clear "truncated" before the content check
        check_content(root, manifest, rels)  # the same check as every other map file
        for sub in subs.values():
            sub.arrays()  # shapes and dtypes now: one clear error at open
        return cls(root, sec, subs)
