"""Reading images from files and encoded bytes into RGB uint8 arrays."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.errors import ImageDecodeError

#: bounds that reject absurd inputs before they reach the descriptor
MAX_PIXELS = 100_000_000


MIN_SIDE = 8


def _check_size(w: int, h: int, what: str) -> None:
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ImageDecodeError(f"{what}: unusable size {w}x{h} (too small: at least "
                               f"{MIN_SIDE}x{MIN_SIDE} px)")
    if h * w > MAX_PIXELS:
        raise ImageDecodeError(f"{what}: unusable size {w}x{h} (too large: {w * h:,} px, at "
                               f"most {MAX_PIXELS:,})")


_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _header_size(data: bytes, what: str) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding (None for other formats or
    a header that cannot be read), so a huge image is refused before its pixels exist."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        w, h = struct.unpack(">II", data[16:24])
        return w, h
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):  # walk the JPEG segments to the first start-of-frame
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        seg = struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker in _SOF:
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        if seg < 2:
            return None
        i += 2 + seg
    return None


def decode_image_bytes(data: bytes | bytearray | memoryview, what: str = "image") -> np.ndarray:
    """Decode JPEG/PNG/... bytes into (H, W, 3) uint8 RGB; raise ImageDecodeError naming
    ``what`` if impossible or when the image is smaller than 8 px or larger than 1e8 px."""
    raw = bytes(data)
    if not raw:
        raise ImageDecodeError(f"{what}: empty data")
    size = _header_size(raw, what)
    if size is not None:
        _check_size(size[0], size[1], what)
    buf = np.frombuffer(raw, dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise ImageDecodeError(f"{what}: not a decodable image ({buf.size} bytes)")
    _check_size(img.shape[1], img.shape[0], what)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def load_image(path: str | os.PathLike[str]) -> np.ndarray:
    """Read an image file into (H, W, 3) uint8 RGB."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageDecodeError(f"cannot read image {path}: {exc}") from exc
    return decode_image_bytes(data, what=str(path))


def check_rgb(image: np.ndarray, what: str = "image") -> np.ndarray:
    """Validate an (H, W, 3) uint8 array (the core's image type) and return it contiguous."""
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3:
        shape = getattr(image, "shape", None)
        raise ImageDecodeError(f"{what}: expected an (H, W, 3) RGB array, got shape {shape}")
    if image.dtype != np.uint8:
        raise ImageDecodeError(f"{what}: expected uint8 pixels, got {image.dtype}")
    h, w = image.shape[:2]
    if h < 8 or w < 8 or h * w > MAX_PIXELS:
        raise ImageDecodeError(f"{what}: unusable size {w}x{h}")
    return np.ascontiguousarray(image)


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """Encode an RGB array as JPEG bytes."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ImageDecodeError("JPEG encoding failed")
    return buf.tobytes()
