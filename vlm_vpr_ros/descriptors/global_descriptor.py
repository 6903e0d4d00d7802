"""The global-descriptor interface every VPR model implements (weight-free or deep)."""

from __future__ import annotations

import abc
from typing import Any, Iterable, Mapping, Sequence

import numpy as np


class GlobalDescriptor(abc.ABC):
    """Turns RGB images into L2-normalised float32 global descriptors.

    Life cycle: ``create_descriptor(name, config)`` → (``fit(images)`` when ``needs_fit``, done by
    the map builder on the map's own images) → ``describe(images)``. Fitted state is exported with
    ``state_arrays()`` into the map folder (``descriptor_state.npz``, no pickle) and restored with
    ``load_state()`` when a map is loaded, so queries use the map's codebook/PCA.

    Images are ``numpy.ndarray`` of shape (H, W, 3), dtype uint8, **RGB** order.
    """

    #: registry name, e.g. ``"vlad_rootsift"`` or ``"eigenplaces"``
    name: str = ""
    #: True when the descriptor must learn state (codebook, PCA) from the map's images
    needs_fit: bool = False

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.config: dict[str, Any] = dict(config or {})

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Output dimension (after fitting, for fitted descriptors)."""

    @property
    def preprocessing(self) -> dict[str, Any]:
        """How an image is prepared (resize, colour, normalisation); recorded in the manifest."""
        return {}

    def identity(self) -> dict[str, Any]:
        """What must match between a map and a query-time descriptor (stored in the manifest)."""
        return {
            "name": self.name,
            "dim": int(self.dim),
            "config": dict(self.config),
            "preprocessing": self.preprocessing,
        }

    def fit(self, images: Iterable[np.ndarray], progress: bool = True) -> None:
        """Learn state from reference images (no-op for pretrained descriptors)."""

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Fitted state as plain arrays (saved with the map); empty for pretrained models."""
        return {}

    def load_state(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore state produced by :meth:`state_arrays`."""

    @abc.abstractmethod
    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        """Return an (N, dim) float32 array of L2-normalised descriptors."""

    def describe_one(self, image: np.ndarray) -> np.ndarray:
        """Descriptor of a single image, shape (dim,)."""
        return self.describe([image])[0]

    def close(self) -> None:
        """Release resources (GPU memory, thread pools)."""


def l2_normalize(x: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Row-wise L2 normalisation in float32."""
    x = np.asarray(x, dtype=np.float32)
    norms = np.linalg.norm(x, axis=-1, keepdims=True)
    return (x / np.maximum(norms, eps)).astype(np.float32)
