"""Where reference images are read from: a local folder or a pyarrow filesystem URI.

``--images`` may be a folder (``/data/refs``) or a URI understood by
``pyarrow.fs.FileSystem.from_uri``: ``file:///data/refs``, ``s3://bucket/refs``,
``gs://bucket/refs`` (credentials come from the usual environment of each worker, e.g.
``AWS_*`` variables or an instance role). Image ids (the CSV's ``file`` column) are paths
relative to that root, with ``/`` separators.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from vlm_vpr_ros.errors import ConfigError, ImageDecodeError
from vlm_vpr_ros.files.images import decode_image_bytes

_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


def is_uri(root: str | Path) -> bool:
    return bool(_SCHEME.match(str(root)))


class ImageSource:
    """Reads ``root/<id>`` as bytes and decodes it into RGB; picklable (sent to Ray workers)."""

    def __init__(self, root: str | Path) -> None:
        self.root = str(root)
        self._fs: Any = None
        self._base = ""
        if is_uri(self.root):
            self._open_fs()

    def _open_fs(self) -> None:
        try:
            from pyarrow import fs as pafs
        except ImportError as exc:  # pragma: no cover - pyarrow comes with ray[data]
            raise ConfigError(f"reading images from {self.root} needs pyarrow "
                              "(installed with ray[data])") from exc
        try:
            self._fs, self._base = pafs.FileSystem.from_uri(self.root)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"--images {self.root}: not a usable filesystem URI ({exc})") \
                from None
        self._base = self._base.rstrip("/")

    def __getstate__(self) -> dict:
        return {"root": self.root}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["root"])

    def uri(self, ref_id: str) -> str:
        if self._fs is None:
            return str(Path(self.root) / ref_id)
        return f"{self.root.rstrip('/')}/{ref_id}"

    def check(self) -> None:
        """ConfigError when the root does not exist (checked once, on the driver)."""
        if self._fs is None:
            if not Path(self.root).is_dir():
                raise ConfigError(f"--images {self.root}: not a folder")
            return
        from pyarrow import fs as pafs

        try:
            info = self._fs.get_file_info(self._base)
        except OSError as exc:
            raise ConfigError(f"--images {self.root}: cannot be listed ({exc})") from None
        if info.type == pafs.FileType.NotFound:
            raise ConfigError(f"--images {self.root}: does not exist")

    def read_bytes(self, ref_id: str) -> bytes:
        try:
            if self._fs is None:
                return (Path(self.root) / ref_id).read_bytes()
            with self._fs.open_input_stream(f"{self._base}/{ref_id}") as fh:
                return fh.readall()
        except (OSError, ValueError) as exc:
            raise ImageDecodeError(f"cannot read image {self.uri(ref_id)}: {exc}") from exc

    def load(self, ref_id: str) -> np.ndarray:
        """(H, W, 3) uint8 RGB; ImageDecodeError when missing or not decodable."""
        return decode_image_bytes(self.read_bytes(ref_id), what=self.uri(ref_id))
