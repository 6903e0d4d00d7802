"""Reading images from files and encoded bytes into RGB uint8 arrays."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.errors import ImageDecodeError

#: bounds that reject absurd inputs before they reach the descriptor
MAX_PIXELS = 100_000_000


def decode_image_bytes(data: bytes | bytearray | memoryview, what: str = "image") -> np.ndarray:
    """Decode JPEG/PNG/... bytes into (H, W, 3) uint8 RGB; raise ImageDecodeError if impossible."""
    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    if buf.size == 0:
        raise ImageDecodeError(f"{what}: empty data")
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise ImageDecodeError(f"{what}: not a decodable image ({buf.size} bytes)")
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
