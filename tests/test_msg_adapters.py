"""msg_adapters.image: every encoding against references built here with plain numpy."""

from __future__ import annotations

import array
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from msg_adapters.image import (SUPPORTED_ENCODINGS, compressed_to_rgb, encoded_bytes,
                                image_to_rgb, message_to_rgb, stamp_ns)
from vlm_vpr_ros.errors import ImageDecodeError
from vlm_vpr_ros.files.images import load_image

RNG = np.random.default_rng(7)
REF = RNG.integers(0, 256, size=(24, 30, 3), dtype=np.uint8)  # H=24, W=30


def make_msg(encoding: str, px: np.ndarray, pad: int = 0, bigendian: bool = False,
             data_type=bytes, h: int | None = None, w: int | None = None):
    """An Image-like namespace: rows of ``px`` (H, W*bpp bytes) followed by ``pad`` bytes."""
    rows = np.ascontiguousarray(px).view(np.uint8).reshape(px.shape[0], -1)
    padded = np.concatenate([rows, np.full((rows.shape[0], pad), 0xAB, np.uint8)], axis=1)
    raw = padded.tobytes()
    data = {bytes: raw, bytearray: bytearray(raw), list: list(raw),
            np.ndarray: np.frombuffer(raw, np.uint8).copy(),
            array.array: array.array("B", raw), memoryview: memoryview(raw)}[data_type]
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=12, nanosec=345), frame_id="cam"),
        height=h if h is not None else px.shape[0], width=w if w is not None else REF.shape[1],
        encoding=encoding, is_bigendian=int(bigendian), step=padded.shape[1], data=data)


@pytest.mark.parametrize("enc,order,alpha", [
    ("rgb8", [0, 1, 2], False), ("bgr8", [2, 1, 0], False), ("rgba8", [0, 1, 2], True),
    ("bgra8", [2, 1, 0], True), ("8UC3", [2, 1, 0], False), ("8UC4", [2, 1, 0], True),
])
@pytest.mark.parametrize("pad", [0, 5])
def test_8bit_colour_exact(enc, order, alpha, pad):
    px = REF[:, :, order]
    if alpha:
        px = np.concatenate([px, np.full(px.shape[:2] + (1,), 77, np.uint8)], axis=2)
    out = image_to_rgb(make_msg(enc, px, pad=pad))
    assert out.dtype == np.uint8 and out.shape == REF.shape and out.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(out, REF)


@pytest.mark.parametrize("enc", ["mono8", "8UC1"])
def test_mono8(enc):
    gray = REF[:, :, 1]
    out = image_to_rgb(make_msg(enc, gray[:, :, None], pad=3))
    for c in range(3):
        np.testing.assert_array_equal(out[:, :, c], gray)


@pytest.mark.parametrize("big", [False, True])
@pytest.mark.parametrize("enc,order,ch", [
    ("rgb16", [0, 1, 2], 3), ("bgr16", [2, 1, 0], 3), ("rgba16", [0, 1, 2], 4),
    ("bgra16", [2, 1, 0], 4), ("mono16", [1], 1), ("16UC1", [1], 1),
])
def test_16bit_both_byte_orders(enc, order, ch, big):
    px16 = REF[:, :, order].astype(np.uint16) * 256 + 3  # high byte == the 8-bit value
    if ch == 4:
        px16 = np.concatenate([px16, np.full(px16.shape[:2] + (1,), 9, np.uint16)], axis=2)
    px16 = px16.astype(">u2" if big else "<u2")
    out = image_to_rgb(make_msg(enc, px16, pad=4, bigendian=big))
    want = REF if ch != 1 else np.repeat(REF[:, :, 1:2], 3, axis=2)
    np.testing.assert_array_equal(out, want)


def _bt601_yuv(rgb: np.ndarray) -> np.ndarray:
    """Studio-range BT.601 Y, U, V of RGB pixels (the formula, written out)."""
    r, g, b = [rgb[..., i].astype(np.float64) for i in range(3)]
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    return np.clip(np.rint(np.stack([y, u, v], -1)), 0, 255).astype(np.uint8)


def _pair_colours() -> np.ndarray:
    """REF with each horizontal pixel pair set to one colour (4:2:2 carries one chroma/pair)."""
    return np.repeat(REF[:, ::2], 2, axis=1)


@pytest.mark.parametrize("enc", ["yuv422", "uyvy", "yuv422_yuy2", "yuyv"])
def test_packed_yuv422(enc):
    rgb = _pair_colours()
    yuv = _bt601_yuv(rgb)
    y, u, v = yuv[..., 0], yuv[:, ::2, 1], yuv[:, ::2, 2]
    packed = np.empty((rgb.shape[0], rgb.shape[1] // 2, 4), np.uint8)
    if enc in ("yuv422", "uyvy"):  # U Y0 V Y1
        planes = (u, y[:, ::2], v, y[:, 1::2])
    else:  # Y0 U Y1 V
        planes = (y[:, ::2], u, y[:, 1::2], v)
    for i, plane in enumerate(planes):
        packed[..., i] = plane
    out = image_to_rgb(make_msg(enc, packed.reshape(rgb.shape[0], -1), pad=6))
    assert np.abs(out.astype(int) - rgb.astype(int)).max() <= 4


def test_nv21():
    rgb = np.repeat(np.repeat(REF[::2, ::2], 2, axis=0), 2, axis=1)  # one colour per 2x2 block
    yuv = _bt601_yuv(rgb)
    vu = np.stack([yuv[::2, ::2, 2], yuv[::2, ::2, 1]], -1).reshape(rgb.shape[0] // 2, -1)
    planes = np.concatenate([yuv[..., 0], vu], axis=0)
    msg = make_msg("nv21", planes)
    msg.height = rgb.shape[0]
    out = image_to_rgb(msg)
    assert np.abs(out.astype(int) - rgb.astype(int)).max() <= 4


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
@pytest.mark.parametrize("bits", [8, 16])
def test_bayer(pattern, bits):
    # large constant-colour blocks: away from block edges demosaicing must give the colour back
    colours = np.array([[200, 40, 90], [10, 220, 130], [90, 90, 250], [250, 180, 20]], np.uint8)
    rgb = np.repeat(np.repeat(colours.reshape(2, 2, 3), 16, axis=0), 16, axis=1)  # 32x32
    chan = {"r": 0, "g": 1, "b": 2}
    mosaic = np.empty(rgb.shape[:2], np.uint8)
    for dy in range(2):
        for dx in range(2):
            mosaic[dy::2, dx::2] = rgb[dy::2, dx::2, chan[pattern[2 * dy + dx]]]
    px = mosaic[:, :, None] if bits == 8 else (mosaic.astype("<u2")[:, :, None] * 257)
    msg = make_msg(f"bayer_{pattern}{bits}", px)
    msg.width = 32
    out = image_to_rgb(msg)
    for by in range(2):
        for bx in range(2):
            block = out[by * 16 + 3:by * 16 + 13, bx * 16 + 3:bx * 16 + 13].reshape(-1, 3)
            assert np.abs(block.astype(int) - colours[2 * by + bx]).max() <= 2


@pytest.mark.parametrize("data_type", [bytes, bytearray, list, np.ndarray, array.array,
                                       memoryview])
def test_data_containers(data_type):
    out = image_to_rgb(make_msg("bgr8", REF[:, :, ::-1], pad=2, data_type=data_type))
    np.testing.assert_array_equal(out, REF)


def test_last_row_without_padding_is_accepted():
    msg = make_msg("rgb8", REF, pad=10)
    msg.data = msg.data[:-10]
    np.testing.assert_array_equal(image_to_rgb(msg), REF)


def test_encoding_is_case_insensitive_and_listed():
    assert "rgb8" in SUPPORTED_ENCODINGS and "yuv422_yuy2" in SUPPORTED_ENCODINGS
    np.testing.assert_array_equal(image_to_rgb(make_msg("RGB8", REF)), REF)


def test_real_rclpy_rosbags_and_mcap_messages():
    """The same function decodes rclpy, rosbags and mcap_ros2 message objects."""
    from mcap_ros2._dynamic import generate_dynamic
    from rclpy.serialization import serialize_message
    from rosbags.typesys import Stores, get_typestore
    from sensor_msgs.msg import Image

    msg = Image(height=REF.shape[0], width=REF.shape[1], encoding="bgr8", is_bigendian=0,
                step=REF.shape[1] * 3 + 2)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 5, 7
    rows = np.concatenate([REF[:, :, ::-1].reshape(REF.shape[0], -1),
                           np.zeros((REF.shape[0], 2), np.uint8)], axis=1)
    msg.data = rows.tobytes()
    cdr = serialize_message(msg)
    store = get_typestore(Stores.ROS2_JAZZY)
    via_rosbags = store.deserialize_cdr(cdr, "sensor_msgs/msg/Image")
    text, _ = store.generate_msgdef("sensor_msgs/msg/Image", ros_version=2)
    via_mcap = generate_dynamic("sensor_msgs/msg/Image", text)["sensor_msgs/msg/Image"](cdr)
    for m in (msg, via_rosbags, via_mcap):
        np.testing.assert_array_equal(image_to_rgb(m), REF)
        np.testing.assert_array_equal(message_to_rgb(m), REF)
        assert stamp_ns(m) == 5_000_000_007


def _compressed(data, fmt="jpeg"):
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=2)),
                           format=fmt, data=data)


def test_compressed_png_exact_and_jpeg_close(demo_data):
    img = load_image(next(iter(sorted((demo_data / "images").glob("*.jpg")))))
    ok, png = cv2.imencode(".png", img[:, :, ::-1])
    assert ok
    np.testing.assert_array_equal(compressed_to_rgb(_compressed(png.tobytes(), "png")), img)
    ok, jpg = cv2.imencode(".jpg", img[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    msg = _compressed(array.array("B", jpg.tobytes()), "rgb8; jpeg compressed bgr8")
    out = message_to_rgb(msg)
    assert out.shape == img.shape
    assert np.abs(out.astype(int) - img.astype(int)).mean() < 4.0
    assert encoded_bytes(msg) == jpg.tobytes()  # handed to the VLM unchanged
    assert encoded_bytes(make_msg("rgb8", REF)) is None


@pytest.mark.parametrize("change,match", [
    (dict(encoding="32FC1"), "unsupported Image encoding '32FC1'; supported: .*rgb8"),
    (dict(encoding=""), "unsupported Image encoding"),
    (dict(step=30 * 3 - 1), "step 89 is smaller than width 30 x 3"),
    (dict(height=0, width=0), "zero-size"),
    (dict(data=b""), "truncated"),
    (dict(height=25), "truncated"),
    (dict(data="text"), "data is text"),
    (dict(data=[1, 2, 999]), "not a byte sequence"),
    (dict(height="x"), "non-integer field 'height'"),
    (dict(height=100_000, width=100_000), "pixel limit"),
])
def test_bad_images_raise_clear_errors(change, match):
    msg = make_msg("rgb8", REF)
    for k, v in change.items():
        setattr(msg, k, v)
    with pytest.raises(ImageDecodeError, match=match):
        image_to_rgb(msg)


def test_odd_width_yuv_and_tiny_images_rejected():
    msg = make_msg("uyvy", np.zeros((4, 30), np.uint8), w=15)
    with pytest.raises(ImageDecodeError, match="even"):
        image_to_rgb(msg)
    with pytest.raises(ImageDecodeError, match="unusable size"):
        image_to_rgb(make_msg("rgb8", REF[:4, :4], w=4))


def test_missing_fields_raise():
    with pytest.raises(ImageDecodeError, match="non-integer field 'height'"):
        image_to_rgb(SimpleNamespace(encoding="rgb8"))


@pytest.mark.parametrize("data,fmt,match", [
    (b"\xff\xd8\xff\xe0" + bytes(200), "jpeg", "not a decodable image"),
    (b"", "png", "empty data"),
    (b"\x89PNG\r\n", "png", "not a decodable image"),
    (b"\x00" * 64, "16UC1; compressedDepth png", "depth images"),
])
def test_bad_compressed(data, fmt, match):
    with pytest.raises(ImageDecodeError, match=match):
        compressed_to_rgb(_compressed(data, fmt))


def test_truncated_jpeg_of_real_image_is_rejected_or_decoded_whole(demo_data):
    img = load_image(next(iter(sorted((demo_data / "images").glob("*.jpg")))))
    ok, jpg = cv2.imencode(".jpg", img)
    cut = jpg.tobytes()[:200]  # header only: no scan data
    with pytest.raises(ImageDecodeError):
        compressed_to_rgb(_compressed(cut))
