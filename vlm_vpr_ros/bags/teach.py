"""Teach run: a recorded drive (camera + GNSS rosbag2 bag) → geotagged references for a map.

Each camera frame is paired with the position at its stamp, linearly interpolated between the
two nearest usable fixes around it (each at most ``fix_tolerance_s`` away; a frame within 1 ms
of a fix takes that fix). Fixes with ``STATUS_NO_FIX``, non-finite or out-of-range positions,
or a horizontal standard deviation above ``max_fix_sigma_m`` (from ``position_covariance``;
fixes of unknown covariance are kept) are not used. A frame is kept when it is at least
``min_spacing_m`` from the last kept frame, so a robot standing still does not fill the map
with copies. Kept frames are written as JPEG files (CompressedImage JPEG payloads as they are,
other frames re-encoded) named ``<bag>/<sec>.<nanosec>.jpg``: the reference id names the bag and
the stamp. Every skipped frame and rejected fix is counted by reason.
"""

from __future__ import annotations

import bisect
import json
import logging
import math
import os
import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from vlm_vpr_ros.bags.frames import horizontal_sigma_m
from vlm_vpr_ros.bags.messages import COMPRESSED, IMAGE_TYPES, NAVSATFIX, stamp_ns
from vlm_vpr_ros.bags.reader import BagReader, RawMessage, deserialize, open_bag
from vlm_vpr_ros.errors import BagError, ConfigError, ImageDecodeError
from vlm_vpr_ros.files.atomic import atomic_write_bytes

log = logging.getLogger(__name__)

#: a frame this close (ns) to a fix takes the fix as it is
_SAME_STAMP_NS = 1_000_000
_EARTH_M = 6_371_008.8


@dataclass(frozen=True)
class TeachConfig:
    image_topic: str | None = None  # None: the bag's only Image/CompressedImage topic
    fix_topic: str | None = None  # None: the bag's only NavSatFix topic
    fix_tolerance_s: float = 0.5
    min_spacing_m: float = 2.0
    max_fix_sigma_m: float = 10.0
    jpeg_quality: int = 95  # for frames that are not JPEG already

    def __post_init__(self) -> None:
        if not (0 < self.fix_tolerance_s < 3600):
            raise ConfigError(f"--fix-tolerance-s must be in (0, 3600) s, got "
                              f"{self.fix_tolerance_s}")
        if not (0 <= self.min_spacing_m < 1e6):
            raise ConfigError(f"--min-spacing-m must be >= 0 m, got {self.min_spacing_m}")
        if not (self.max_fix_sigma_m > 0):
            raise ConfigError(f"--max-fix-sigma-m must be > 0 m, got {self.max_fix_sigma_m}")
        if not (1 <= self.jpeg_quality <= 100):
            raise ConfigError(f"jpeg_quality must be in 1..100, got {self.jpeg_quality}")


@dataclass
class TeachReference:
    id: str  # "<bag>/<sec>.<nanosec>.jpg", relative to the images folder
    lat: float
    lon: float
    stamp_ns: int


@dataclass
class TeachResult:
    bag: str
    image_topic: str
    fix_topic: str
    references: list[TeachReference] = field(default_factory=list)
    frames: Counter = field(default_factory=Counter)  # frames by outcome (kept or skip reason)
    fixes: Counter = field(default_factory=Counter)  # fixes by outcome (used or reject reason)
    problems: list[str] = field(default_factory=list)  # bag damage met while reading

    def summary(self) -> dict:
        return {"bag": self.bag, "image_topic": self.image_topic, "fix_topic": self.fix_topic,
                "references": len(self.references), "frames": dict(self.frames),
                "fixes": dict(self.fixes), "problems": list(self.problems)}

    def describe(self) -> str:
        """One line: kept/skipped counts by reason."""
        fr = ", ".join(f"{k} {v}" for k, v in sorted(self.frames.items()) if k != "kept")
        fx = ", ".join(f"{k} {v}" for k, v in sorted(self.fixes.items()) if k != "used")
        return (f"{self.bag}: {self.frames.get('kept', 0)} references kept of "
                f"{sum(self.frames.values())} frames on {self.image_topic}"
                f"{' (skipped: ' + fr + ')' if fr else ''}; {self.fixes.get('used', 0)} fixes "
                f"used on {self.fix_topic}{' (rejected: ' + fx + ')' if fx else ''}")


@dataclass
class _Fixes:
    stamps: list[int]
    lat: list[float]
    lon: list[float]


def _stamp(msg, raw: RawMessage) -> int:
    t = stamp_ns(msg.header)
    return t if t > 0 else raw.log_time_ns


def _read_fixes(bag: BagReader, topic: str, cfg: TeachConfig, counts: Counter) -> _Fixes:
    from sensor_msgs.msg import NavSatStatus

    items = []
    for raw in bag.messages([topic]):
        try:
            msg = deserialize(raw)
        except BagError as exc:
            log.warning("%s", exc)
            counts["undecodable"] += 1
            continue
        lat, lon = float(msg.latitude), float(msg.longitude)
        sigma = horizontal_sigma_m(msg)
        if msg.status.status <= NavSatStatus.STATUS_NO_FIX:
            counts["no_fix_status"] += 1
        elif not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90
                  and -180 <= lon <= 180):
            counts["invalid_position"] += 1
        elif sigma is not None and sigma > cfg.max_fix_sigma_m:
            counts["sigma_above_max"] += 1
        else:
            counts["used"] += 1
            items.append((_stamp(msg, raw), lat, lon))
    items.sort()
    return _Fixes([t for t, _, _ in items], [a for _, a, _ in items], [b for _, _, b in items])


def interpolate_fix(fixes: _Fixes, t: int, tol_ns: int) -> tuple[float, float] | None:
    """Position at stamp ``t`` between the nearest fixes before and after it (both within
    ``tol_ns``), or the fix at ``t`` itself; None when there is none."""
    s = fixes.stamps
    i = bisect.bisect_left(s, t)
    for j in (i, i - 1):
        if 0 <= j < len(s) and abs(s[j] - t) <= _SAME_STAMP_NS:
            return fixes.lat[j], fixes.lon[j]
    if i == 0 or i == len(s):
        return None
    t0, t1 = s[i - 1], s[i]
    if t - t0 > tol_ns or t1 - t > tol_ns:
        return None
    w = (t - t0) / (t1 - t0)
    lat = fixes.lat[i - 1] + w * (fixes.lat[i] - fixes.lat[i - 1])
    dlon = (fixes.lon[i] - fixes.lon[i - 1] + 180.0) % 360.0 - 180.0  # across the antimeridian
    lon = (fixes.lon[i - 1] + w * dlon + 180.0) % 360.0 - 180.0
    return lat, lon


def distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle distance in metres (haversine)."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    a = (math.sin((p2 - p1) / 2) ** 2
         + math.cos(p1) * math.cos(p2) * math.sin(math.radians(lon2 - lon1) / 2) ** 2)
    return 2 * _EARTH_M * math.asin(min(1.0, math.sqrt(a)))


def _jpeg_bytes(msg, type_: str, what: str, quality: int) -> bytes:
    """The frame as JPEG bytes: a JPEG CompressedImage payload as it is (after checking it
    decodes), anything else decoded and re-encoded."""
    from vlm_vpr_ros.bags.frames import decode_compressed, decode_raw
    from vlm_vpr_ros.files.images import decode_image_bytes, encode_jpeg

    if type_ == COMPRESSED:
        data = bytes(msg.data)
        if data[:3] == b"\xff\xd8\xff":
            decode_image_bytes(data, what=what)
            return data
        return encode_jpeg(decode_compressed(msg), quality)
    return encode_jpeg(decode_raw(msg), quality)


def _time_range(stamps: list[int]) -> str:
    if not stamps:
        return "none"
    return f"{stamps[0] / 1e9:.3f}..{stamps[-1] / 1e9:.3f} s"


def bag_label(path: str | os.PathLike[str]) -> str:
    """The bag's name as used in reference ids (folder name, or file stem)."""
    p = Path(path)
    name = p.name if p.is_dir() else p.stem
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip(".")
    return safe or "bag"


def extract_references(bag_path: str | os.PathLike[str], out_images: str | os.PathLike[str],
                       config: TeachConfig | None = None, progress: bool = True) -> TeachResult:
    """Pair the bag's frames with interpolated fixes and write the kept frames as JPEG under
    ``out_images/<bag>/``. BagError when the topics are ambiguous or missing (listing the
    bag's topics), when no usable fix exists, or when no frame falls within the fixes'
    time range."""
    cfg = config or TeachConfig()
    bag = open_bag(bag_path)
    img = bag.find_topic(IMAGE_TYPES, cfg.image_topic, "camera images (--image-topic)")
    fix = bag.find_topic((NAVSATFIX,), cfg.fix_topic, "GNSS fixes (--fix-topic)")
    label = bag_label(bag_path)
    res = TeachResult(str(bag_path), img.name, fix.name)
    fixes = _read_fixes(bag, fix.name, cfg, res.fixes)
    if not fixes.stamps:
        raise BagError(f"{bag_path}: no usable fix on {fix.name} ({dict(res.fixes)}); cannot "
                       "place any frame")
    out_dir = Path(out_images) / label
    out_dir.mkdir(parents=True, exist_ok=True)
    tol_ns = int(round(cfg.fix_tolerance_s * 1e9))
    first_frame = last_frame = None
    last_kept: tuple[float, float] | None = None
    frames = bag.messages([img.name])
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, total=img.count, desc="teach", unit="frame", disable=None,
                      leave=False)
    for raw in frames:
        try:
            msg = deserialize(raw)
        except BagError as exc:
            log.warning("%s", exc)
            res.frames["undecodable"] += 1
            continue
        t = _stamp(msg, raw)
        first_frame = t if first_frame is None else min(first_frame, t)
        last_frame = t if last_frame is None else max(last_frame, t)
        pos = interpolate_fix(fixes, t, tol_ns)
        if pos is None:
            res.frames["no_fix_within_tolerance"] += 1
            continue
        if last_kept is not None and distance_m(*last_kept, *pos) < cfg.min_spacing_m:
            res.frames["closer_than_min_spacing"] += 1
            continue
        ref_id = f"{label}/{t // 1_000_000_000}.{t % 1_000_000_000:09d}.jpg"
        try:
            data = _jpeg_bytes(msg, raw.type, f"{img.name} frame at {t} ns", cfg.jpeg_quality)
        except ImageDecodeError as exc:
            log.warning("skipping an undecodable frame: %s", exc)
            res.frames["undecodable"] += 1
            continue
        if (Path(out_images) / ref_id).exists():
            res.frames["duplicate_stamp"] += 1
            continue
        atomic_write_bytes(Path(out_images) / ref_id, data)
        res.references.append(TeachReference(ref_id, pos[0], pos[1], t))
        res.frames["kept"] += 1
        last_kept = pos
    res.problems = list(bag.problems)
    if first_frame is None:
        raise BagError(f"{bag_path}: no readable frame on {img.name}")
    if not res.references:
        if first_frame > fixes.stamps[-1] + tol_ns or last_frame < fixes.stamps[0] - tol_ns:
            raise BagError(f"{bag_path}: the frames on {img.name} "
                           f"({_time_range([first_frame, last_frame])}) and the usable fixes on "
                           f"{fix.name} ({_time_range(fixes.stamps)}) never overlap in time "
                           "(header stamps); no frame can be placed")
        raise BagError(f"{bag_path}: no frame could be placed: {res.describe()}")
    log.info("%s", res.describe())
    return res


def write_coords(path: Path, refs: list[TeachReference]) -> None:
    """``file, lat, lon, stamp_ns`` of the references (the CSV build-map reads)."""
    from vlm_vpr_ros.files.csvio import write_csv_atomic

    write_csv_atomic(path, ["file", "lat", "lon", "stamp_ns"],
                     [{"file": r.id, "lat": repr(r.lat), "lon": repr(r.lon),
                       "stamp_ns": r.stamp_ns} for r in refs])


def build_map_from_bag(bag_path: str | os.PathLike[str], out_dir: str | os.PathLike[str],
                       config: TeachConfig | None = None, overwrite: bool = False,
                       progress: bool = True, **build_options):
    """``vlm-vpr build-map --bag``: extract the references, build the map next to ``out_dir``
    with :func:`vlm_vpr_ros.mapping.build_images.build_map` (``build_options``: descriptor,
    partition, ...), store the images in it and move it into place. Returns (ReferenceMap,
    TeachResult)."""
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.maps.map_images import attach_images
    from vlm_vpr_ros.maps.reference_map import ReferenceMap
    from vlm_vpr_ros.files.atomic import atomic_write_json

    from vlm_vpr_ros.files.outputs import StagedOutput

    out = Path(out_dir)
    # built next to ``out`` and swapped in like every map build (the map's one writer lock; the
    # old map stays until the new one is complete and is put back after a crash in the swap)
    with StagedOutput(out, "map", overwrite) as staged:
        # extracted images + CSV, deleted with the staging (a dot name: never the map's own)
        scratch = staged.root / ".teach"
        shutil.rmtree(scratch, ignore_errors=True)
        res = extract_references(bag_path, scratch / "images", config, progress)
        write_coords(scratch / "references.csv", res.references)
        built = staged.path
        build_map(scratch / "images", scratch / "references.csv", built, progress=progress,
                  **build_options)
        manifest_path = built / "manifest.json"
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        cfg = config or TeachConfig()
        manifest["source"]["teach"] = {**res.summary(), "config": {
            "fix_tolerance_s": cfg.fix_tolerance_s, "min_spacing_m": cfg.min_spacing_m,
            "max_fix_sigma_m": cfg.max_fix_sigma_m}}
        atomic_write_json(manifest_path, manifest)
        attach_images(built, scratch / "images")
        shutil.rmtree(scratch, ignore_errors=True)
        staged.commit(validate=lambda p: ReferenceMap.load(p, verify=False))
    return ReferenceMap.load(out, verify=False), res
