"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` → (H, W, 3) uint8 RGB.

Duck-typed: only the fields ``height, width, encoding, is_bigendian, step, data`` (Image) or
``format, data`` (CompressedImage) are read, so rclpy messages, ``mcap_ros2`` decoded messages and
``rosbags`` dataclasses all work. ``data`` may be ``bytes``, ``bytearray``, ``memoryview``,
``array.array('B')`` (rclpy), a uint8 numpy array (rosbags) or a list of ints.

Row padding (``step`` larger than ``width × bytes per pixel``) is honoured and a last row without
its padding is accepted; ``is_bigendian`` selects the byte order of 16-bit encodings. 16-bit
samples are reduced to 8 bits by keeping the high byte (full-range scaling, as cv_bridge does).
Every problem raises :class:`~vlm_vpr_ros.errors.ImageDecodeError` with a readable message.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from vlm_vpr_ros.errors import ImageDecodeError
from vlm_vpr_ros.files.images import MAX_PIXELS, check_rgb, decode_image_bytes


@dataclass(frozen=True)
class _Layout:
    channels: int  # samples per pixel as stored (2 for packed YUV 4:2:2)
    depth: int  # bytes per sample: 1 or 2
    kind: str  # "rgb", "bgr", "mono", "yuv", "bayer" or "nv21"
    cv_code: int | None = None  # OpenCV conversion to RGB for yuv/bayer/nv21


def _bayer(code: int, depth: int = 1) -> _Layout:
    return _Layout(1, depth, "bayer", code)


# OpenCV names Bayer patterns after the 2x2 block starting at (1, 1); ROS after (0, 0).
_BAYER = {"rggb": cv2.COLOR_BayerBG2RGB, "bggr": cv2.COLOR_BayerRG2RGB,
          "gbrg": cv2.COLOR_BayerGR2RGB, "grbg": cv2.COLOR_BayerGB2RGB}

_LAYOUTS: dict[str, _Layout] = {
    "rgb8": _Layout(3, 1, "rgb"), "bgr8": _Layout(3, 1, "bgr"),
    "rgba8": _Layout(4, 1, "rgb"), "bgra8": _Layout(4, 1, "bgr"),
    "mono8": _Layout(1, 1, "mono"), "8uc1": _Layout(1, 1, "mono"),
    "8uc3": _Layout(3, 1, "bgr"), "8uc4": _Layout(4, 1, "bgr"),
    "rgb16": _Layout(3, 2, "rgb"), "bgr16": _Layout(3, 2, "bgr"),
    "rgba16": _Layout(4, 2, "rgb"), "bgra16": _Layout(4, 2, "bgr"),
    "mono16": _Layout(1, 2, "mono"), "16uc1": _Layout(1, 2, "mono"),
    "16uc3": _Layout(3, 2, "bgr"), "16uc4": _Layout(4, 2, "bgr"),
    # packed YUV 4:2:2: ROS "yuv422" is UYVY, "yuv422_yuy2" is YUYV
    "yuv422": _Layout(2, 1, "yuv", cv2.COLOR_YUV2RGB_UYVY),
    "uyvy": _Layout(2, 1, "yuv", cv2.COLOR_YUV2RGB_UYVY),
    "yuv422_yuy2": _Layout(2, 1, "yuv", cv2.COLOR_YUV2RGB_YUY2),
    "yuyv": _Layout(2, 1, "yuv", cv2.COLOR_YUV2RGB_YUY2),
    "nv21": _Layout(1, 1, "nv21", cv2.COLOR_YUV2RGB_NV21),
    **{f"bayer_{p}8": _bayer(c) for p, c in _BAYER.items()},
    **{f"bayer_{p}16": _bayer(c, 2) for p, c in _BAYER.items()},
}

#: the ``Image.encoding`` strings understood (case-insensitive)
SUPPORTED_ENCODINGS: tuple[str, ...] = tuple(sorted(_LAYOUTS))


def _as_uint8(data: Any, what: str) -> np.ndarray:
    """A flat uint8 view (no copy when possible) of a message's ``data`` field."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise ImageDecodeError(f"{what}: data has dtype {data.dtype}, expected uint8")
        return data.reshape(-1)
    if isinstance(data, str):
        raise ImageDecodeError(f"{what}: data is text, expected bytes")
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        pass
    try:
        return np.asarray(data, dtype=np.uint8).reshape(-1)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ImageDecodeError(f"{what}: data is not a byte sequence ({exc})") from None


def _int_field(msg: Any, name: str, what: str) -> int:
    try:
        return int(getattr(msg, name))
    except (AttributeError, TypeError, ValueError):
        raise ImageDecodeError(f"{what}: missing or non-integer field {name!r}") from None


def image_to_rgb(msg: Any) -> np.ndarray:
    """Pixels of a ``sensor_msgs/Image`` as contiguous (H, W, 3) uint8 RGB."""
    raw_enc = str(getattr(msg, "encoding", ""))
    what = f"Image ({raw_enc or 'no encoding'})"
    layout = _LAYOUTS.get(raw_enc.strip().lower())
    if layout is None:
        raise ImageDecodeError(f"unsupported Image encoding {raw_enc!r}; supported: "
                               f"{', '.join(SUPPORTED_ENCODINGS)}")
    h, w = _int_field(msg, "height", what), _int_field(msg, "width", what)
    step = _int_field(msg, "step", what)
    if h <= 0 or w <= 0:
        raise ImageDecodeError(f"{what}: zero-size image {w}x{h}")
    if h * w > MAX_PIXELS:
        raise ImageDecodeError(f"{what}: {w}x{h} exceeds the {MAX_PIXELS} pixel limit")
    if layout.kind in ("yuv", "nv21") and w % 2:
        raise ImageDecodeError(f"{what}: width {w} must be even for chroma-subsampled data")
    if layout.kind == "nv21" and h % 2:
        raise ImageDecodeError(f"{what}: height {h} must be even for nv21")
    row_bytes = w * layout.channels * layout.depth
    if step < row_bytes:
        raise ImageDecodeError(f"{what}: step {step} is smaller than width {w} x "
                               f"{layout.channels * layout.depth} bytes per pixel = {row_bytes}")
    rows = h * 3 // 2 if layout.kind == "nv21" else h
    buf = _as_uint8(getattr(msg, "data", b""), what)
    need = (rows - 1) * step + row_bytes
    if buf.size < need:
        raise ImageDecodeError(f"{what}: {w}x{h} with step {step} needs {need} data bytes, "
                               f"got {buf.size} (truncated)")
    # rows of the payload without their padding; a view, copied once below
    px = np.lib.stride_tricks.as_strided(buf, shape=(rows, row_bytes), strides=(step, 1),
                                         writeable=False)
    px = np.ascontiguousarray(px)
    if layout.depth == 2:
        order = ">" if bool(getattr(msg, "is_bigendian", 0)) else "<"
        px = (px.view(np.dtype(order + "u2")) >> 8).astype(np.uint8)
    return check_rgb(_to_rgb(px, layout, h, w), what=what)


def _to_rgb(px: np.ndarray, layout: _Layout, h: int, w: int) -> np.ndarray:
    if layout.kind == "nv21":
        return cv2.cvtColor(px.reshape(h * 3 // 2, w), layout.cv_code)
    px = px.reshape(h, w, layout.channels)
    if layout.kind in ("yuv", "bayer"):
        src = px if layout.kind == "yuv" else px[:, :, 0]
        return cv2.cvtColor(np.ascontiguousarray(src), layout.cv_code)
    if layout.kind == "mono":
        return np.repeat(px, 3, axis=2)
    if layout.kind == "bgr":
        return px[:, :, 2::-1]
    return px[:, :, :3]


def compressed_to_rgb(msg: Any) -> np.ndarray:
    """Pixels of a ``sensor_msgs/CompressedImage`` (JPEG, PNG, ... as OpenCV reads them)."""
    fmt = str(getattr(msg, "format", "") or "")
    what = f"CompressedImage ({fmt or 'no format'})"
    if "compresseddepth" in fmt.replace(" ", "").lower():
        raise ImageDecodeError(f"{what}: depth images cannot be localized")
    buf = _as_uint8(getattr(msg, "data", b""), what)
    return check_rgb(decode_image_bytes(buf.tobytes(), what=what), what=what)


def encoded_bytes(msg: Any) -> bytes | None:
    """The JPEG/PNG payload of a CompressedImage (handed to a VLM as is), else None."""
    fmt = str(getattr(msg, "format", "") or "").lower()
    if not hasattr(msg, "format") or not any(k in fmt for k in ("jpeg", "jpg", "png")):
        return None
    if "compresseddepth" in fmt.replace(" ", ""):
        return None
    return _as_uint8(getattr(msg, "data", b""), "CompressedImage").tobytes()


def is_compressed(msg: Any) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def message_to_rgb(msg: Any) -> np.ndarray:
    """Dispatch on the fields: CompressedImage (``format``) or Image (``encoding``)."""
    return compressed_to_rgb(msg) if is_compressed(msg) else image_to_rgb(msg)


def stamp_ns(msg: Any) -> int:
    """Nanoseconds of ``msg.header.stamp`` (0 when the message has no header)."""
    try:
        st = msg.header.stamp
        return int(st.sec) * 1_000_000_000 + int(st.nanosec)
    except (AttributeError, TypeError, ValueError):
        return 0
