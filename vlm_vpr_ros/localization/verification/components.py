"""Interfaces of the verification stage: local features, matchers, and their registry.

A *local feature* turns an RGB image into keypoints + descriptors (:class:`LocalFeatures`); a
*matcher* pairs the features of two images; the geometry check (:mod:`.geometry`) keeps the
matches consistent with one epipolar geometry. Both are registered by name (hloc style): an
unknown name is a :class:`~vlm_vpr_ros.errors.ConfigError` listing the choices. Learned ones
(:mod:`.learned`: ``disk``, ``aliked``, ``lightglue``, ``lighterglue``; :mod:`.learned_xfeat`:
``xfeat``, ``mnn``) register themselves from modules that import torch only when one is
created.
"""

from __future__ import annotations

import abc
import importlib
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from vlm_vpr_ros.config import choose
from vlm_vpr_ros.types import LocalFeatures

__all__ = ["Component", "LocalFeatureExtractor", "LocalFeatures", "Matcher", "available_features",
           "available_matchers", "create_feature", "create_matcher", "register_feature",
           "register_matcher"]


class LocalFeatureExtractor(abc.ABC):
    """Keypoints and descriptors of RGB uint8 images (H, W, 3)."""

    name: str = ""
    #: dtype the descriptors are stored in (map feature store, match inputs)
    descriptor_dtype: np.dtype = np.dtype(np.uint8)
    descriptor_dim: int = 128

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.config: dict[str, Any] = dict(config or {})

    def identity(self) -> dict[str, Any]:
        """What must agree between features stored in a map and those of a query."""
        return {"name": self.name, "config": dict(self.config),
                "descriptor_dim": int(self.descriptor_dim),
                "dtype": np.dtype(self.descriptor_dtype).name}

    @abc.abstractmethod
    def extract(self, image: np.ndarray, max_keypoints: int) -> LocalFeatures:
        """Features of one image, at most ``max_keypoints`` (strongest first)."""


class Matcher(abc.ABC):
    """Tentative correspondences between a query and reference images."""

    name: str = ""
    #: whether threads may match one query's candidates concurrently (numpy/BLAS on one
    #: thread each; verification/share.py); a model with its own threads or device says no
    shares_threads: bool = False

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        self.config: dict[str, Any] = dict(config or {})

    def prepare(self, query: LocalFeatures) -> Any:
        """Per-query state reused for every candidate (e.g. normalized descriptors)."""
        return query

    @abc.abstractmethod
    def match(self, prepared: Any, query: LocalFeatures,
              ref: LocalFeatures) -> np.ndarray:
        """(m, 2) int array of (query row, reference row) pairs."""


@dataclass(frozen=True)
class Component:
    """A registered local feature or matcher: name, factory, default config, one-line doc."""

    name: str
    factory: Callable[[Mapping[str, Any]], Any]
    defaults: Mapping[str, Any]
    summary: str


_FEATURES: dict[str, Component] = {}
_MATCHERS: dict[str, Component] = {}
#: modules whose import registers components (learned ones need torch + kornia: lazy)
_PROVIDERS = ("vlm_vpr_ros.localization.verification.sift",
              "vlm_vpr_ros.localization.verification.learned",
              "vlm_vpr_ros.localization.verification.learned_xfeat")
_loaded = False


def register_feature(c: Component) -> Component:
    _FEATURES[c.name] = c
    return c


def register_matcher(c: Component) -> Component:
    _MATCHERS[c.name] = c
    return c


def _load() -> None:
    global _loaded
    if not _loaded:
        for mod in _PROVIDERS:
            importlib.import_module(mod)  # learned*.py import torch only when used
        _loaded = True


def available_features() -> dict[str, Component]:
    _load()
    return dict(sorted(_FEATURES.items()))


def available_matchers() -> dict[str, Component]:
    _load()
    return dict(sorted(_MATCHERS.items()))


def create_feature(name: str, config: Mapping[str, Any] | None = None) -> LocalFeatureExtractor:
    c: Component = choose(name, available_features(), "local feature")
    return c.factory({**c.defaults, **dict(config or {})})


def create_matcher(name: str, config: Mapping[str, Any] | None = None) -> Matcher:
    c: Component = choose(name, available_matchers(), "matcher")
    return c.factory({**c.defaults, **dict(config or {})})
