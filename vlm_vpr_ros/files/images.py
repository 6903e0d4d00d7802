"""Reading images from files and encoded bytes into RGB uint8 arrays.

The pixel budget is checked *before* decoding, for every format: the header is read by Pillow
(``Image.open`` is lazy: it parses the header of JPEG, PNG, WebP, TIFF, GIF, BMP, PNM,
JPEG 2000 ... and allocates no pixels), so a 10 KB WebP that says 16383x16383 is refused before
OpenCV would allocate 800 MB for it. Data whose header neither Pillow nor the built-in PNG/JPEG
reader understands is refused ("not a decodable image") without being handed to the decoder.
A file larger than :data:`MAX_FILE_BYTES` is refused before it is read."""

from __future__ import annotations

import io
import os
import re
import struct
import warnings
from pathlib import Path

import cv2
import numpy as np

from vlm_vpr_ros.errors import ImageDecodeError

#: bounds that reject absurd inputs before they reach the descriptor
MAX_PIXELS = 100_000_000
#: an image file larger than this is not read at all (an uncompressed 1e8-pixel RGB image
#: is 300 MB)
MAX_FILE_BYTES = 512 * 1024 * 1024


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


_pillow_quiet = False


def _quiet_pillow(image_module) -> None:
    """Pillow warns about images between 89M and 179M px when it opens them: our own budget
    (:data:`MAX_PIXELS`) decides, so that one warning category is silenced (once)."""
    global _pillow_quiet
    if not _pillow_quiet:
        warnings.filterwarnings("ignore", category=image_module.DecompressionBombWarning)
        _pillow_quiet = True


def header_size(data: bytes, what: str = "image") -> tuple[int, int] | None:
    """(width, height) from the image header without decoding any pixel: Pillow for every
    format it knows, the built-in PNG/JPEG reader when Pillow cannot identify the data; None
    when neither can read a header. ImageDecodeError for a header past Pillow's own
    decompression-bomb limit."""
    from PIL import Image, UnidentifiedImageError

    _quiet_pillow(Image)
    try:
        with Image.open(io.BytesIO(data)) as im:  # lazy: header only, no pixel allocated
            w, h = im.size
        return int(w), int(h)
    except Image.DecompressionBombError as exc:  # Pillow's own limit (2 x 89.5M px)
        px = re.search(r"\((\d+) pixels\)", str(exc))
        n = f"{int(px.group(1)):,} px, " if px else ""
        raise ImageDecodeError(f"{what}: unusable size (too large: {n}at most "
                               f"{MAX_PIXELS:,})") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, struct.error,
            EOFError, IndexError, TypeError, KeyError, ZeroDivisionError, MemoryError):
        return _header_size(data, what)


def decode_image_bytes(data: bytes | bytearray | memoryview, what: str = "image") -> np.ndarray:
    """Decode JPEG/PNG/WebP/TIFF/... bytes into (H, W, 3) uint8 RGB; raise ImageDecodeError
    naming ``what`` if impossible or when the image is smaller than 8 px or larger than 1e8 px
    (checked from the header, before any pixel is decoded)."""
    raw = bytes(data)
    if not raw:
        raise ImageDecodeError(f"{what}: empty data")
    size = header_size(raw, what)
    if size is None:
        raise ImageDecodeError(f"{what}: not a decodable image ({len(raw)} bytes with no "
                               "JPEG, PNG, WebP, TIFF, GIF, BMP ... header)")
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
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ImageDecodeError(f"{path}: unusable file size {size:,} bytes (at most "
                                   f"{MAX_FILE_BYTES:,})")
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


def fit_rgb(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    """An RGB image whose longer side is at most ``max_side`` (INTER_AREA; the image itself
    when it fits) and the scale back to the original (original pixel = frame pixel * scale):
    the frame the learned local features run on."""
    rgb = check_rgb(image)
    h, w = rgb.shape[:2]
    s = max_side / max(h, w)
    if s >= 1.0:
        return rgb, 1.0
    out = cv2.resize(rgb, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return out, max(h, w) / max(out.shape[:2])
