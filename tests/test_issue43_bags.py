"""Issue 43: bags we write carry real chunk CRCs (a flipped byte is detected by our reader),
and ``evaluate-bag`` says when its ground truth's own covariance is wide."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import pytest

from vlm_vpr_ros.bags.reader import open_bag
from vlm_vpr_ros.bags.writer import bag_files


def _raw_chunks(path: Path) -> list[tuple[int, int, str, bytes]]:
    """(offset, stored uncompressed_crc, compression, records) of each chunk, parsed
    from the MCAP spec's layout independently of the writer."""
    data = path.read_bytes()
    pos, out = 8, []
    while pos < len(data) - 8:
        op, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        if op == 0x06:
            body = pos + 9
            crc = struct.unpack_from("<I", data, body + 24)[0]
            n = struct.unpack_from("<I", data, body + 28)[0]
            comp = data[body + 32:body + 32 + n].decode()
            size = struct.unpack_from("<Q", data, body + 32 + n)[0]
            records = data[body + 40 + n:body + 40 + n + size]
            out.append((pos, crc, comp, records))
        if op == 0x02:  # footer
            break
        pos += 9 + length
    return out


@pytest.fixture(scope="module")
def made_bag(demo_data, tmp_path_factory) -> Path:
    from vlm_vpr_ros.bags.make import make_bag

    root = tmp_path_factory.mktemp("crcbag")
    lines = (demo_data / "coords.csv").read_text().splitlines()[:4]
    (root / "c.csv").write_text("\n".join(lines) + "\n")
    make_bag(demo_data / "images", root / "c.csv", root / "bag", rate_hz=2.0,
             start_time_ns=10**18, progress=False)
    return root / "bag"


def test_bag_make_writes_real_chunk_crcs(made_bag):
    chunks = _raw_chunks(bag_files(made_bag)[0])
    assert len(chunks) >= 3  # ~1 MB raw frames: a chunk each
    for _, crc, comp, records in chunks:
        assert comp == "" and crc != 0 and crc == zlib.crc32(records)


def test_a_flipped_byte_in_a_bag_we_made_is_detected(made_bag, tmp_path):
    src = bag_files(made_bag)[0]
    full = sum(1 for _ in open_bag(src).messages())
    assert full == 6 and open_bag(src).complete
    off, _, _, records = _raw_chunks(src)[1]
    data = bytearray(src.read_bytes())
    data[off + 9 + 40 + len(records) // 2] ^= 0xFF  # inside the second chunk's image data
    flipped = tmp_path / "flip.mcap"
    flipped.write_bytes(bytes(data))
    bag = open_bag(flipped)
    n = sum(1 for _ in bag.messages())
    assert not bag.complete and n < full, (n, bag.problems)


def test_ground_truth_with_a_wide_covariance_is_left_out(tmp_path, caplog):
    import logging

    from vlm_vpr_ros.bags.frames import MAX_GT_SIGMA_M, read_ground_truth
    from vlm_vpr_ros.bags.messages import NAVSATFIX, navsatfix_msg
    from vlm_vpr_ros.bags.writer import BagWriter, qos_profile

    sigmas = [3.0, 1e6, None, MAX_GT_SIGMA_M, 1e6, 250.0]
    with BagWriter(tmp_path / "gt") as w:
        w.add_topic("/gps/fix", NAVSATFIX, [qos_profile()])
        for k, s in enumerate(sigmas):
            w.write("/gps/fix", navsatfix_msg(37.0 + k * 1e-4, -122.0, 10**18 + k * 10**8,
                                              sigma_m=s), 10**18 + k * 10**8)
    with caplog.at_level(logging.WARNING, logger="vlm_vpr_ros.bags.frames"):
        gt = read_ground_truth(open_bag(tmp_path / "gt"), "/gps/fix")
    # kept: 3 m, an unknown covariance (most GPS topics), exactly the limit
    assert [round((a - 37.0) / 1e-4) for a in gt.lat] == [0, 2, 3]
    assert gt.too_uncertain == 3 and gt.rejected == 0
    lines = [r.getMessage() for r in caplog.records
             if r.name == "vlm_vpr_ros.bags.frames" and r.levelno >= logging.WARNING]
    assert len(lines) == 1 and "3 fix(es)" in lines[0] and "1e+06 m" in lines[0]
