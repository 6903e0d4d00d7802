"""Hostile inputs of round 3 (issue 19): decode bombs in every format, strict CSV numbers and
columns, NUL bytes late in a file, out-of-range numbers on the command line and in node
parameters, stamps past int32, a map whose references share one position."""

from __future__ import annotations

import csv
import io
import math
import shutil
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from faults.conftest import exit2, sha_tree

SIDE = 12000  # 1.44e8 px: above the 1e8 budget


def _tiny(fmt: str) -> bytearray:
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (16, 16), (10, 20, 30)).save(buf, fmt)
    return bytearray(buf.getvalue())


def bomb(fmt: str, side: int = SIDE) -> bytes:
    """A tiny real file of ``fmt`` whose header says side x side pixels."""
    d = _tiny(fmt)
    if fmt == "WEBP":  # VP8 frame header: 14-bit width and height after the start code
        i = d.find(b"\x9d\x01\x2a")
        d[i + 3:i + 7] = struct.pack("<HH", side, side)
    elif fmt == "GIF":  # logical screen and the first image descriptor
        d[6:10] = struct.pack("<HH", side, side)
        j = d.find(b",", 13)
        d[j + 5:j + 9] = struct.pack("<HH", side, side)
    elif fmt == "BMP":
        d[18:26] = struct.pack("<ii", side, side)
    elif fmt == "TIFF":  # ImageWidth / ImageLength entries of the first IFD (LONG)
        for k in range(struct.unpack("<H", d[8:10])[0]):
            off = 10 + 12 * k
            if struct.unpack("<H", d[off:off + 2])[0] in (256, 257):
                d[off + 8:off + 12] = struct.pack("<I", side)
    return bytes(d)


FORMATS = ("TIFF", "WEBP", "GIF", "BMP")


@pytest.fixture
def no_decode(monkeypatch):
    from vlm_vpr_ros.files import images

    def refuse(*a, **k):
        raise AssertionError("a bomb reached the decoder")

    monkeypatch.setattr(images.cv2, "imdecode", refuse)


@pytest.mark.fault("image_bomb_formats")
def test_bombs_of_every_format_refused_from_the_header(no_decode):
    """Peak RSS of the same files, decoded before and refused now:
    benchmarks/bench_decode_bombs.py (docs/robustness.md)."""
    from vlm_vpr_ros.errors import ImageDecodeError
    from vlm_vpr_ros.files.images import decode_image_bytes, header_size

    for fmt in FORMATS:
        data = bomb(fmt)
        assert len(data) < 1000 and header_size(data) == (SIDE, SIDE), fmt
        with pytest.raises(ImageDecodeError, match=rf"q\.{fmt}: unusable size {SIDE}x{SIDE} "
                                                   r"\(too large"):
            decode_image_bytes(data, f"q.{fmt}")


@pytest.mark.fault("image_unknown_header")
def test_data_without_a_known_header_is_never_decoded(no_decode):
    from vlm_vpr_ros.errors import ImageDecodeError
    from vlm_vpr_ros.files.images import decode_image_bytes

    for data in (b"\x00" * 64, np.random.default_rng(0).bytes(4096), b"P7\nWIDTH 99999\n"):
        with pytest.raises(ImageDecodeError, match="not a decodable image .* with no JPEG"):
            decode_image_bytes(data, "x.bin")


@pytest.mark.fault("image_bomb_cli")
def test_bombs_in_localize_and_build_map(cli, tmp_path, demo_data, demo_map):
    images = tmp_path / "images"
    names = sorted(p.name for p in (demo_data / "images").iterdir())[:10]
    images.mkdir()
    for n in names:
        shutil.copy(demo_data / "images" / n, images / n)
    (images / "bomb.webp").write_bytes(bomb("WEBP"))
    (images / "bomb.tif").write_bytes(bomb("TIFF"))
    q = tmp_path / "q.csv"
    q.write_text("file\n" + "\n".join([names[0], "bomb.webp", "bomb.tif"]) + "\n")
    rc, _, _ = cli("localize", "--map", demo_map, "--images", images, "--queries", q, "--out",
                   tmp_path / "r.csv")
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert rc == 0 and [r["flags"] == "" or "image_error" not in r["flags"] for r in rows] == [
        True, False, False]
    assert "unusable size 12000x12000 (too large" in cli.text
    coords = tmp_path / "c.csv"
    src = {r.split(",")[0]: r for r in (demo_data / "coords.csv").read_text().splitlines()[1:]}
    coords.write_text("file,lat,lon\n" + "".join(f"{src[n]}\n" for n in names[:8])
                      + "bomb.tif,10,10\nbomb.webp,11,11\n")
    rc, out, _ = cli("build-map", "--images", images, "--coords", coords, "--out",
                     tmp_path / "m", "--descriptor", "vlad_rootsift_fast", "--partition", "none")
    assert rc == 0 and "8 references" in out
    assert f"{images / 'bomb.tif'}: unusable size 12000x12000 (too large" in cli.text


@pytest.mark.fault("image_bomb_node")
def test_bomb_on_image_compressed(no_decode):
    """The node decodes image/compressed through msg_adapters: a 16383^2 WebP of ~50 bytes is
    an undecodable frame (counted by the worker), never decoded."""
    from msg_adapters.image import message_to_rgb
    from vlm_vpr_ros.errors import ImageDecodeError

    msg = SimpleNamespace(format="webp", data=bomb("WEBP", 16383))
    with pytest.raises(ImageDecodeError, match="too large: 268,402,689 px"):
        message_to_rgb(msg)


# -- CSV ------------------------------------------------------------------------------------------
@pytest.mark.fault("csv_number_underscore")
def test_numbers_with_underscores_or_other_digits(cli, tmp_path, demo_data):
    (tmp_path / "r.csv").write_text("file,lat,lon\na.jpg,39.5,8.9\n")
    for bad in ("3_9.5591", "\u0663\u0669.5", "0x27", "nan"):
        (tmp_path / "gt.csv").write_text(f"file,lat,lon\na.jpg,{bad},8.9\n", encoding="utf-8")
        exit2(cli("evaluate", "--results", tmp_path / "r.csv", "--ground-truth",
                  tmp_path / "gt.csv"), "gt.csv:2", "not numbers")
    name = sorted(p.name for p in (demo_data / "images").iterdir())[0]
    (tmp_path / "c.csv").write_text(f"file,lat,lon\n{name},4_5.0,7\n")
    exit2(cli("build-map", "--images", demo_data / "images", "--coords", tmp_path / "c.csv",
              "--out", tmp_path / "m"), "c.csv:2", "not numbers")
    assert not (tmp_path / "m").exists()


@pytest.mark.fault("csv_duplicate_column")
def test_duplicate_columns_refused(cli, tmp_path):
    (tmp_path / "r.csv").write_text("file,lat,lon\na.jpg,39.5,8.9\n")
    (tmp_path / "gt.csv").write_text("file,lat,lon,lat\na.jpg,1,8.9,39.5\n")
    exit2(cli("evaluate", "--results", tmp_path / "r.csv", "--ground-truth",
              tmp_path / "gt.csv"), "gt.csv", "column 'lat' appears twice", "columns 2 and 4")
    (tmp_path / "q.csv").write_text("file,note,file\na.jpg,x,b.jpg\n")
    exit2(cli("localize", "--map", tmp_path, "--queries", tmp_path / "q.csv", "--out",
              tmp_path / "o.csv"), "column 'file' appears twice")


@pytest.mark.fault("csv_nul_after_64k")
def test_nul_byte_after_64_kib(cli, tmp_path, demo_map, demo_data):
    names = sorted(p.name for p in (demo_data / "images").iterdir())
    lines = ["file"] + [names[i % len(names)] for i in range(4000)]
    body = "\n".join(lines) + "\n"
    assert len(body) > 1 << 16
    q = tmp_path / "q.csv"
    q.write_bytes(body.encode() + names[0].encode() + b"\x00x.jpg\n")
    exit2(cli("localize", "--map", demo_map, "--images", demo_data / "images", "--queries", q,
              "--out", tmp_path / "r.csv"), f"q.csv:{len(lines) + 1}", "NUL byte")
    assert "Traceback" not in cli.text and not (tmp_path / "r.csv.partial").exists()


# -- numbers on the command line and in node parameters -------------------------------------
@pytest.mark.fault("cli_prior_timeout")
def test_prior_timeout_values(cli, tmp_path):
    for bad, shown in (("inf", "inf"), ("1e309", "inf"), ("-1", "-1.0"), ("nan", "nan"),
                       ("0", "0.0")):
        exit2(cli("localize", "--map", tmp_path, "--queries", tmp_path / "q.csv", "--out",
                  tmp_path / "r.csv", "--prior-timeout", bad), "--prior-timeout",
              f"got {shown}")


@pytest.mark.fault("cli_map_build_numbers")
def test_build_numbers(cli, tmp_path, demo_data):
    base = ("build-map", "--images", demo_data / "images", "--coords",
            demo_data / "coords.csv", "--out", tmp_path / "m")
    for opt, bad in (("--clusters", "0"), ("--clusters", "-1"), ("--max-submap-size", "0"),
                     ("--rerank-factor", "0"), ("--rerank-factor", "-1"),
                     ("--ram-budget-mb", "nan")):
        exit2(cli(*base, opt, bad), opt)
    exit2(cli("map", "upgrade", tmp_path, "--out", tmp_path / "u", "--rerank-factor", "0"),
          "--rerank-factor")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.fault("cli_descriptor_options")
def test_descriptor_options_checked_before_the_build(cli, tmp_path, demo_data, monkeypatch):
    from vlm_vpr_ros.mapping import build_images

    def no_work(*a, **k):
        raise AssertionError("the build started")

    monkeypatch.setattr(build_images, "_build_staged", no_work)
    base = ("build-map", "--images", demo_data / "images", "--coords",
            demo_data / "coords.csv", "--out", tmp_path / "m", "--descriptor",
            "vlad_rootsift_fast")
    for opt, name in (("max_side=1", "max_side"), ("pca_dim=0", "pca_dim"),
                      ("n_words=1", "n_words"), ("whiten_shrink=-1", "whiten_shrink")):
        exit2(cli(*base, "--descriptor-option", opt), name)
    assert not (tmp_path / "m").exists() and not (tmp_path / ".m.partial").exists()


@pytest.mark.fault("node_param_numbers")
def test_node_parameters_out_of_range(demo_map):
    from vlm_vpr_ros.errors import ConfigError
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline
    from vlm_vpr_ros.runtime.params import from_params

    for name, bad in (("prior_timeout_s", math.inf), ("prior_timeout_s", math.nan),
                      ("prior_timeout_s", -1.0), ("top_p", 0), ("min_period_s", math.inf),
                      ("max_frame_age_s", 0.0)):
        with pytest.raises(ConfigError, match=name):
            from_params({"map_dir": str(demo_map), name: bad})
    cfg = from_params({"map_dir": str(demo_map), "descriptor_options.max_side": 1})
    with pytest.raises(ConfigError, match="max_side"):  # what the node's configure step opens
        LocalizationPipeline.open(cfg.map_dir, descriptor_config=cfg.descriptor_options)


@pytest.mark.fault("bag_start_time_range")
def test_bag_start_time_past_int32(cli, tmp_path, demo_data):
    coords = tmp_path / "c.csv"
    coords.write_text("\n".join((demo_data / "coords.csv").read_text().splitlines()[:4]) + "\n")
    for start in ("4294967296", "9223372036.854775807", "1e12", "2147483647"):
        exit2(cli("bag", "make", "--images", demo_data / "images", "--coords", coords, "--out",
                  tmp_path / "bag", "--start-time", start), "--start-time", "int32")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.csv"]
    assert cli("bag", "make", "--images", demo_data / "images", "--coords", coords, "--out",
               tmp_path / "bag", "--start-time", "2147483640")[0] == 0


@pytest.mark.fault("map_one_position")
def test_references_at_one_position_build(cli, tmp_path, demo_data):
    names = sorted(p.name for p in (demo_data / "images").iterdir())[:12]
    coords = tmp_path / "c.csv"
    coords.write_text("file,lat,lon\n" + "".join(f"{n},45.0,7.0\n" for n in names))
    rc, out, _ = cli("build-map", "--images", demo_data / "images", "--coords", coords,
                     "--out", tmp_path / "m", "--descriptor", "vlad_rootsift_fast")
    assert rc == 0 and "12 references" in out, cli.text[-500:]
    q = tmp_path / "q.csv"
    q.write_text("file\n" + "\n".join(names[:3]) + "\n")
    assert cli("localize", "--map", tmp_path / "m", "--images", demo_data / "images",
               "--queries", q, "--out", tmp_path / "r.csv")[0] == 0
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert [(float(r["lat"]), float(r["lon"])) for r in rows] == [(45.0, 7.0)] * 3
    assert sha_tree(coords)  # the input is still there


@pytest.mark.fault("image_bomb_more_formats")
def test_pnm_and_jpeg2000_bombs(no_decode):
    from PIL import Image

    from vlm_vpr_ros.errors import ImageDecodeError
    from vlm_vpr_ros.files.images import decode_image_bytes

    pgm = f"P5\n{SIDE} {SIDE}\n255\n".encode() + b"\x00" * 64
    buf = io.BytesIO()
    Image.new("RGB", (16, 16)).save(buf, "JPEG2000")
    j2k = bytearray(buf.getvalue())
    i = j2k.find(b"ihdr")  # JP2 image header box: height, width (big-endian uint32)
    j2k[i + 4:i + 12] = struct.pack(">II", SIDE, SIDE)
    k = j2k.find(b"\xff\x51")  # the codestream's SIZ marker: Xsiz, Ysiz
    j2k[k + 6:k + 14] = struct.pack(">II", SIDE, SIDE)
    for data, what in ((pgm, "q.pgm"), (bytes(j2k), "q.jp2")):
        with pytest.raises(ImageDecodeError, match="too large"):
            decode_image_bytes(data, what)


@pytest.mark.fault("image_file_too_big")
def test_image_file_larger_than_any_image_is_not_read(tmp_path, monkeypatch):
    from pathlib import Path

    from vlm_vpr_ros.errors import ImageDecodeError
    from vlm_vpr_ros.files.images import MAX_FILE_BYTES, load_image

    p = tmp_path / "video.jpg"
    with open(p, "wb") as fh:  # sparse: no disk used
        fh.truncate(MAX_FILE_BYTES + 1)

    def no_read(self):
        raise AssertionError("read a file larger than any image")

    monkeypatch.setattr(Path, "read_bytes", no_read)
    with pytest.raises(ImageDecodeError, match="video.jpg: unusable file size"):
        load_image(p)


@pytest.mark.fault("csv_utf16")
def test_utf16_csv(cli, tmp_path, demo_data):
    (tmp_path / "c.csv").write_text("file,lat,lon\na.jpg,1,1\n", encoding="utf-16")
    exit2(cli("build-map", "--images", demo_data / "images", "--coords", tmp_path / "c.csv",
              "--out", tmp_path / "m"), "c.csv:1", "malformed CSV")


@pytest.mark.fault("csv_crlf_bom_accepted")
def test_crlf_and_bom_accepted(tmp_path):
    from vlm_vpr_ros.evaluation.metrics import read_ground_truth

    (tmp_path / "gt.csv").write_bytes(b"\xef\xbb\xbffile,lat,lon\r\na.jpg, 39.5 ,+8.9\r\n"
                                      b"b.jpg,-1e1,.5\r\n")
    assert read_ground_truth(tmp_path / "gt.csv") == {"a.jpg": (39.5, 8.9),
                                                      "b.jpg": (-10.0, 0.5)}


@pytest.mark.fault("csv_empty_number")
def test_empty_coordinate(cli, tmp_path, demo_data):
    """An empty longitude in a coordinates CSV (a row cut short by a spreadsheet)."""
    names = sorted(p.name for p in (demo_data / "images").iterdir())[:3]
    rows = [f"{names[0]},45.1,7.6", f"{names[1]},45.2,", f"{names[2]},45.3,7.7"]
    (tmp_path / "c.csv").write_text("file,lat,lon\n" + "\n".join(rows) + "\n")
    exit2(cli("bag", "make", "--images", demo_data / "images", "--coords", tmp_path / "c.csv",
              "--out", tmp_path / "b"), "c.csv:3", "not numbers")
    assert not (tmp_path / "b").exists()


@pytest.mark.fault("queries_csv_header_only")
def test_queries_csv_with_only_a_header(cli, tmp_path, demo_map, demo_data):
    """A queries CSV with its header but no file name: nothing to localize is an error, not an
    empty results file and exit 0."""
    (tmp_path / "q.csv").write_text("file,lat,lon\n,,\n")
    exit2(cli("localize", "--map", demo_map, "--images", demo_data / "images", "--queries",
              tmp_path / "q.csv", "--out", tmp_path / "r.csv"), "q.csv", "no rows")
    assert not (tmp_path / "r.csv").exists()


@pytest.mark.fault("cli_bag_numbers")
def test_bag_command_numbers(cli, tmp_path):
    for args, opt in ((("bag", "make", "--images", tmp_path, "--coords", tmp_path / "c.csv",
                        "--out", tmp_path / "b", "--rate"), "--rate"),
                      (("replay", tmp_path / "b", "--rate"), "--rate"),
                      (("replay", tmp_path / "b", "--clock"), "--clock"),
                      (("replay", tmp_path / "b", "--wait-subscribers"), "--wait-subscribers"),
                      (("replay", tmp_path / "b", "--domain-id"), "--domain-id")):
        bads = {"--domain-id": ("-1", "300"), "--wait-subscribers": ("-1", "inf", "nan")}
        for bad in bads.get(opt, ("0", "-1", "inf", "nan", "1e9")):
            exit2(cli(*args, bad), opt)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.fault("cli_engine_numbers")
def test_describe_engine_numbers(cli, tmp_path):
    base = ("describe", "--images", tmp_path, "--coords", tmp_path / "c.csv", "--out",
            tmp_path / "s")
    for opt, bad in (("--shard-size", "0"), ("--batch-size", "0"), ("--batch-size", "5000"),
                     ("--workers", "0"), ("--num-gpus-per-worker", "-1"),
                     ("--num-gpus-per-worker", "nan")):
        exit2(cli(*base, opt, bad), opt)


@pytest.mark.fault("cli_teach_numbers")
def test_teach_and_evaluate_bag_numbers(cli, tmp_path):
    teach = ("build-map", "--bag", tmp_path / "b", "--out", tmp_path / "m")
    for opt, bad in (("--fix-tolerance-s", "nan"), ("--fix-tolerance-s", "0"),
                     ("--min-spacing-m", "-1"), ("--max-fix-sigma-m", "0")):
        exit2(cli(*teach, opt, bad), opt)
    ev = ("evaluate-bag", tmp_path / "b", "--map", tmp_path / "m")
    for opt, bad in (("--max-gt-gap", "inf"), ("--max-gt-gap", "-1"), ("--max-frames", "0"),
                     ("--top-p", "0"), ("--n-submaps", "0"), ("--prior-timeout", "nan")):
        exit2(cli(*ev, opt, bad), opt)


@pytest.mark.fault("image_zero_bytes")
def test_zero_byte_query(cli, tmp_path, demo_data, demo_map):
    images = tmp_path / "q"
    images.mkdir()
    name = sorted(p.name for p in (demo_data / "images").iterdir())[0]
    shutil.copy(demo_data / "images" / name, images / name)
    (images / "empty.jpg").write_bytes(b"")
    (tmp_path / "q.csv").write_text(f"file\n{name}\nempty.jpg\n")
    rc, _, _ = cli("localize", "--map", demo_map, "--images", images, "--queries",
                   tmp_path / "q.csv", "--out", tmp_path / "r.csv")
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert rc == 0 and "image_error" in rows[1]["flags"] and rows[1]["lat"] == ""
    assert "empty.jpg: empty data" in cli.text


@pytest.mark.fault("csv_overflow_number")
def test_overflowing_coordinate(cli, tmp_path, demo_data):
    name = sorted(p.name for p in (demo_data / "images").iterdir())[0]
    (tmp_path / "c.csv").write_text(f"file,lat,lon\n{name},1e400,7\n")
    exit2(cli("build-map", "--images", demo_data / "images", "--coords", tmp_path / "c.csv",
              "--out", tmp_path / "m"), "c.csv:2", "out of range")


# -- round 5 (issue 43) --------------------------------------------------------------------------
@pytest.mark.fault("prior_sigma_out_of_range")
def test_prior_sigma_outside_the_error_models_range(cli, demo_map, demo_data, queries,
                                                    tmp_path):
    """Before: 1e-300 an OverflowError on every query, 3e7 m / 30000 km an error-model failure
    on every query, both exit 0."""
    names = queries.read_text().split()[1:3]
    out = tmp_path / "r.csv"

    def run(*prior):
        res = cli("localize", "--map", demo_map, "--images", demo_data / "images",
                  "--queries", queries, "--out", out, *prior)
        assert not out.exists() and not out.with_name("r.csv.partial").exists()
        return res

    for cell in ("1e-300", "3e7", "1e12"):
        p = tmp_path / "p.csv"
        p.write_text(f"file,lat,lon,sigma_m\n{names[0]},37.7,-122.4,100\n"
                     f"{names[1]},37.7,-122.4,{cell}\n")
        exit2(run("--priors", p), f"{p}:3: field sigma_m", "is outside [0.01, 20015114] m")
    for km in ("1e-300", "30000"):
        exit2(run("--prior", "fixed", "--prior-option", "lat=37.7", "--prior-option",
                  "lon=-122.4", "--prior-option", f"sigma_km={km}"),
              f"option sigma_km={km}", "is outside [1e-05, 20015] km")


@pytest.mark.fault("help_double_percent")
def test_no_help_prints_a_doubled_percent(capsys):
    import argparse

    from vlm_vpr_ros.cli import build_parser

    def walk(parser):
        yield parser
        for a in parser._actions:
            if isinstance(a, argparse._SubParsersAction):
                for sub in a.choices.values():
                    yield from walk(sub)

    helps = [p.format_help() for p in walk(build_parser())]
    assert len(helps) > 20 and not [h for h in helps if "%%" in h]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["calibrate", "--help"])
    assert "68 % / 95 %" in " ".join(capsys.readouterr().out.split())
