"""``vlm-vpr bag make``: geotagged images → a rosbag2 bag with camera frames and GPS truth."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from vlm_vpr_ros.bags.messages import COMPRESSED, IMAGE, NAVSATFIX
from vlm_vpr_ros.bags.messages import compressed_msg, image_msg, navsatfix_msg
from vlm_vpr_ros.bags.writer import BagWriter, now_ns, qos_profile, write_sidecar
from vlm_vpr_ros.errors import BagError, ConfigError, ImageDecodeError

log = logging.getLogger(__name__)

_PASS_THROUGH = {".jpg": "jpeg", ".jpeg": "jpeg", ".png": "png"}
#: builtin_interfaces/Time.sec is an int32: the last stamp a message header can carry
MAX_STAMP_NS = (2 ** 31 - 1) * 1_000_000_000 + 999_999_999


def check_stamps(start_ns: int, n_frames: int, period_ns: int) -> None:
    """ConfigError unless every frame's stamp fits ``header.stamp`` (sec int32 >= 0): a start
    time that would wrap the seconds is refused before anything is written."""
    last = start_ns + max(0, n_frames - 1) * period_ns
    if start_ns < 0 or last > MAX_STAMP_NS:
        raise ConfigError(
            f"--start-time {start_ns / 1e9:.9f} s: the frames' stamps (up to {last / 1e9:.3f} s)"
            f" do not fit a ROS header stamp (sec is an int32: 0 .. {2 ** 31 - 1}, i.e. until "
            "2038-01-19 03:14:07 UTC); choose an earlier start time")


def image_topic_name(prefix: str, compressed: bool) -> str:
    """image_transport naming: ``PREFIX/image_raw`` or ``PREFIX/image_raw/compressed``."""
    base = "/" + prefix.strip("/") + "/image_raw" if prefix.strip("/") else "/image_raw"
    return base + "/compressed" if compressed else base


def make_bag(images_dir: str | os.PathLike[str], coords_csv: str | os.PathLike[str],
             out: str | os.PathLike[str], rate_hz: float = 1.0, compressed: bool = False,
             topic_prefix: str = "/camera", gt_topic: str = "/gps/fix",
             frame_id: str = "camera", start_time_ns: int | None = None,
             compression: str = "none", overwrite: bool = False,
             progress: bool = True, storage: str = "mcap") -> dict:
    """Write one camera frame per CSV row (``file, lat, lon``) at ``rate_hz``, each with a
    ``NavSatFix`` ground truth of the same stamp. With ``compressed`` JPEG/PNG files are stored
    as they are (no re-encoding). Returns paths, topics and counts; ``frames.csv`` beside the
    bag maps stamps back to file names (so recorded priors keyed by file can be used)."""
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv
    from vlm_vpr_ros.files.outputs import StagedOutput, check_not_inside

    if not (rate_hz > 0 and rate_hz < 1e6):
        raise ConfigError(f"--rate must be a positive frequency in Hz, got {rate_hz}")
    images_dir = Path(images_dir)
    rows = read_coords_csv(coords_csv)
    if start_time_ns is not None:
        check_stamps(int(start_time_ns), len(rows), int(round(1e9 / rate_hz)))
    check_not_inside(out, [images_dir, coords_csv], allow_out_inside=True)
    with StagedOutput(out, "bag", overwrite) as stage:
        info = _make(images_dir, rows, coords_csv, stage.path, rate_hz, compressed,
                     topic_prefix, gt_topic, frame_id, start_time_ns, compression, progress,
                     storage)
        stage.commit()
    info["bag"] = str(out)
    log.info("bag %s: %d frames on %s + %s (%d skipped)", out, info["frames"],
             info["image_topic"], gt_topic, len(info["skipped"]))
    return info


def _make(images_dir: Path, rows, coords_csv, out: Path, rate_hz: float, compressed: bool,
          topic_prefix: str, gt_topic: str, frame_id: str, start_time_ns: int | None,
          compression: str, progress: bool, storage: str) -> dict:
    from vlm_vpr_ros.files.images import decode_image_bytes, encode_jpeg

    period_ns = int(round(1e9 / rate_hz))
    t0 = int(start_time_ns if start_time_ns is not None else now_ns())
    img_topic = image_topic_name(topic_prefix, compressed)
    sidecar, skipped = [], []
    qos_img = [qos_profile(depth=10)]
    with BagWriter(out, storage=storage, compression=compression, overwrite=True) as bag:
        bag.add_topic(img_topic, COMPRESSED if compressed else IMAGE, qos_img)
        bag.add_topic(gt_topic, NAVSATFIX, [qos_profile(depth=10)])
        it = rows
        if progress:
            from tqdm import tqdm

            it = tqdm(rows, desc="bag make", unit="frame", disable=None, leave=False)
        for f, lat, lon in it:
            path = images_dir / f
            try:
                data = path.read_bytes()
                rgb = decode_image_bytes(data, what=str(path))
            except (OSError, ImageDecodeError) as exc:
                log.warning("skipping %s: %s", path, exc)
                skipped.append(f)
                continue
            t = t0 + len(sidecar) * period_ns
            if compressed:
                fmt = _PASS_THROUGH.get(path.suffix.lower())
                msg = compressed_msg(data if fmt else encode_jpeg(rgb), fmt or "jpeg", t,
                                     frame_id)
            else:
                msg = image_msg(rgb, t, frame_id)
            bag.write(gt_topic, navsatfix_msg(lat, lon, t), t)
            bag.write(img_topic, msg, t)
            sidecar.append({"index": len(sidecar), "stamp_ns": t, "file": f, "lat": lat,
                            "lon": lon})
        if not sidecar:
            raise BagError(f"no readable image among the {len(rows)} rows of {coords_csv}")
    write_sidecar(Path(out) / "frames.csv", sidecar)
    info = {"bag": str(out), "image_topic": img_topic, "gt_topic": gt_topic,
            "frames": len(sidecar), "skipped": skipped,
            "duration_s": (len(sidecar) - 1) * period_ns / 1e9}
    return info
