"""TEST HELPER: synthetic teach-run bags (camera + GNSS) written with the project's rosbag2 MCAP
writer and real ROS 2 serialization. Not part of the package.

The robot visits the given places in order: it stops ``dwell_s`` at each place (the camera frame
is taken in the middle of the stop) and drives ``travel_s`` to the next one. Fixes come at
``fix_hz`` all the time, with injected faults whose counts are returned so tests can check the
teach summary exactly:

* every ``no_fix_every``-th fix: ``STATUS_NO_FIX`` at (0, 0);
* every ``nan_every``-th fix: status FIX with a NaN latitude;
* every ``bad_sigma_every``-th fix: 50 m sigma and a position 500 m off;
* GNSS gaps: after the places in ``gaps``, no fix for ``gap_s`` seconds while driving, with
  ``gap_frames`` camera frames inside the gap (they must be skipped);
* a stand-still: at place ``standstill`` the robot stays ``standstill_frames`` more frames
  (5 Hz) at the same spot (only the first may be kept).
"""

from __future__ import annotations

import math
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from vlm_vpr_ros.bags.messages import (COMPRESSED, IMAGE, NAVSATFIX, compressed_msg, image_msg,
                                       navsatfix_msg)
from vlm_vpr_ros.bags.writer import BagWriter, qos_profile

T0 = 1_700_000_000 * 10**9


@dataclass
class Place:
    image: bytes | np.ndarray  # JPEG bytes (CompressedImage) or RGB array (Image)
    lat: float
    lon: float


@dataclass
class TeachBag:
    path: Path
    truth: dict[int, tuple[float, float]] = field(default_factory=dict)  # place frame stamp
    injected: dict[str, int] = field(default_factory=dict)
    frames: int = 0


def write_teach_bag(out: Path, places: Sequence[Place], fix_hz: float = 10.0,
                    dwell_s: float = 1.0, travel_s: float = 1.0, no_fix_every: int = 5,
                    nan_every: int = 13, bad_sigma_every: int = 11, gaps: Sequence[int] = (),
                    gap_s: float = 3.0, gap_frames: int = 3, standstill: int | None = None,
                    standstill_frames: int = 20, image_topic: str = "/camera/image_raw",
                    fix_topic: str = "/gps/fix", t0: int = T0, fix_offset_s: float = 0.0,
                    extra_image_topic: str | None = None) -> TeachBag:
    """Write the bag; ``fix_offset_s`` shifts every fix stamp (to make them miss the frames)."""
    res = TeachBag(Path(out))
    inj = dict.fromkeys(("no_fix_status", "invalid_position", "sigma_above_max", "used",
                         "gap_frames", "standstill_frames"), 0)
    # the time line: (start, end, lat0, lon0, lat1, lon1) segments, frames as (t, place)
    segs, frames, gap_windows = [], [], []
    t = float(t0) / 1e9
    for i, p in enumerate(places):
        dwell = dwell_s + (standstill_frames * 0.2 if i == standstill else 0.0)
        segs.append((t, t + dwell, p.lat, p.lon, p.lat, p.lon))
        frames.append((t + dwell_s / 2, i, True))
        if i == standstill:
            frames += [(t + dwell_s / 2 + 0.2 * (k + 1), i, False)
                       for k in range(standstill_frames)]
            inj["standstill_frames"] = standstill_frames
        t += dwell
        if i + 1 < len(places):
            q = places[i + 1]
            travel = travel_s + (gap_s + 1.0 if i in gaps else 0.0)
            segs.append((t, t + travel, p.lat, p.lon, q.lat, q.lon))
            if i in gaps:
                g0 = t + 0.5
                gap_windows.append((g0, g0 + gap_s))
                frames += [(g0 + gap_s * (k + 1) / (gap_frames + 1), i, False)
                           for k in range(gap_frames)]
                inj["gap_frames"] += gap_frames
            t += travel
    t_end = t
    compressed = isinstance(places[0].image, (bytes, bytearray))
    with BagWriter(out) as bag:
        bag.add_topic(image_topic, COMPRESSED if compressed else IMAGE, [qos_profile(depth=10)])
        if extra_image_topic:
            bag.add_topic(extra_image_topic, COMPRESSED if compressed else IMAGE,
                          [qos_profile(depth=10)])
        bag.add_topic(fix_topic, NAVSATFIX, [qos_profile(depth=10)])
        msgs = []
        n = 0
        tf = float(t0) / 1e9 - 0.5
        while tf <= t_end + 0.5:
            if not any(a <= tf < b for a, b in gap_windows):
                lat, lon = _position(segs, tf)
                n += 1
                stamp = int(round((tf + fix_offset_s) * 1e9))
                if n % no_fix_every == 0:
                    msg = navsatfix_msg(0.0, 0.0, stamp, fix=False)
                    inj["no_fix_status"] += 1
                elif n % nan_every == 0:
                    msg = navsatfix_msg(math.nan, lon, stamp, sigma_m=1.0)
                    inj["invalid_position"] += 1
                elif n % bad_sigma_every == 0:
                    msg = navsatfix_msg(lat + 0.0045, lon, stamp, sigma_m=50.0)
                    inj["sigma_above_max"] += 1
                else:
                    msg = navsatfix_msg(lat, lon, stamp, sigma_m=0.5)
                    inj["used"] += 1
                msgs.append((stamp, fix_topic, msg))
            tf += 1.0 / fix_hz
        for tc, i, main in frames:
            stamp = int(round(tc * 1e9))
            if main:
                res.truth[stamp] = (places[i].lat, places[i].lon)
            img = places[i].image
            msg = (compressed_msg(bytes(img), "jpeg", stamp) if compressed
                   else image_msg(np.asarray(img), stamp))
            msgs.append((stamp, image_topic, msg))
            if extra_image_topic:
                msgs.append((stamp, extra_image_topic, msg))
        msgs.sort(key=lambda m: (m[0], m[1]))
        for stamp, topic, msg in msgs:
            bag.write(topic, msg, stamp)
    res.frames = len(frames)
    res.injected = inj
    return res


def _position(segs, t: float) -> tuple[float, float]:
    for a, b, la0, lo0, la1, lo1 in segs:
        if a <= t < b:
            w = (t - a) / (b - a) if b > a else 0.0
            return la0 + w * (la1 - la0), lo0 + w * (lo1 - lo0)
    first, last = segs[0], segs[-1]
    return (first[2], first[3]) if t < first[0] else (last[4], last[5])


def mcap_to_db3(src: Path, dst: Path) -> Path:
    """Copy a bag's topics and CDR messages into a rosbag2 sqlite3 file (``dst`` .db3)."""
    from vlm_vpr_ros.bags.reader import open_bag

    bag = open_bag(src)
    db = sqlite3.connect(dst)
    db.executescript(
        "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, "
        "serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL);"
        "CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
        "timestamp INTEGER NOT NULL, data BLOB NOT NULL);")
    ids = {}
    for k, t in enumerate(sorted(bag.topics.values(), key=lambda t: t.name), 1):
        ids[t.name] = k
        db.execute("INSERT INTO topics VALUES (?, ?, ?, 'cdr', '')", (k, t.name, t.type))
    for m in bag.messages():
        db.execute("INSERT INTO messages(topic_id, timestamp, data) VALUES (?, ?, ?)",
                   (ids[m.topic], m.log_time_ns, m.data))
    db.commit()
    db.close()
    return dst


def drive_order(rows: Sequence[tuple[str, float, float]], min_gap_m: float = 2.0) -> list:
    """``rows`` reordered so that no two consecutive places are closer than ``min_gap_m``
    where possible (a drive does not photograph one spot twice in a row unless it stands
    still; photo collections do)."""
    from vlm_vpr_ros.bags.teach import distance_m

    left, out = list(rows), []
    while left:
        k = 0
        if out:
            k = next((i for i, r in enumerate(left)
                      if distance_m(out[-1][1], out[-1][2], r[1], r[2]) >= min_gap_m), 0)
        out.append(left.pop(k))
    return out
