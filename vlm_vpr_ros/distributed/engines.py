"""Where reference images are described: the engine protocol, the work itself (the same in
this process and inside a Ray worker) and the local engine. The Ray engine is
:mod:`vlm_vpr_ros.distributed.ray_engine`."""

from __future__ import annotations

import logging
from typing import Any, Iterator, Mapping, Protocol, Sequence

import numpy as np

from vlm_vpr_ros.descriptors import GlobalDescriptor
from vlm_vpr_ros.mapping.image_sources import ImageSource
from vlm_vpr_ros.errors import ImageDecodeError

log = logging.getLogger(__name__)

#: one described batch: row indices, ok flags, (k, dim) descriptors, reasons ("" when ok)
BatchResult = tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]


class Engine(Protocol):
    """Where the images are described (in this process, or on a Ray cluster)."""

    workers: int

    def fit(self, name: str, config: Mapping[str, Any], sample_ids: list[str]
            ) -> dict[str, np.ndarray]: ...

    def map(self, items: list[tuple[int, str]], name: str, config: Mapping[str, Any],
            state: Mapping[str, np.ndarray], identity: Mapping[str, Any]
            ) -> Iterator[BatchResult]: ...

    def close(self) -> None: ...


def fit_on_sample(desc: GlobalDescriptor, source: ImageSource, sample_ids: Sequence[str],
                  progress: bool = False) -> dict[str, np.ndarray]:
    """Fit ``desc`` on the images of ``sample_ids`` (unreadable ones skipped, as the local
    build does) and return its state arrays."""

    def images() -> Iterator[np.ndarray]:
        for ref in sample_ids:
            try:
                yield source.load(ref)
            except ImageDecodeError as exc:
                log.warning("skipping reference: %s", exc)

    desc.fit(images(), progress=progress)
    return desc.state_arrays()


def describe_items(desc: GlobalDescriptor, source: ImageSource,
                   items: Sequence[tuple[int, str]]) -> BatchResult:
    """Describe one batch. Unreadable images and images on which the descriptor raises are
    returned as not ok with the reason; the rest of the batch is kept."""
    idx = np.array([i for i, _ in items], dtype=np.int64)
    ok = np.zeros(len(items), bool)
    feats = np.zeros((len(items), desc.dim), np.float32)
    reasons = [""] * len(items)
    images, where = [], []
    for k, (_, ref) in enumerate(items):
        try:
            images.append(source.load(ref))
            where.append(k)
        except ImageDecodeError as exc:
            log.warning("skipping reference: %s", exc)
            reasons[k] = str(exc)
    if images:
        try:
            feats[where] = desc.describe(images)
            ok[where] = True
        # A descriptor may fail on one odd image with any exception type (a library bug, a
        # shape it does not expect): describe one by one so only that image is lost.
        except Exception as exc:  # noqa: BLE001
            log.warning("batch failed (%s: %s); describing its images one by one",
                        type(exc).__name__, exc)
            for k, im in zip(where, images):
                try:
                    feats[k] = desc.describe([im])[0]
                    ok[k] = True
                except Exception as one:  # noqa: BLE001
                    reasons[k] = f"descriptor failed on {source.uri(items[k][1])}: " \
                                 f"{type(one).__name__}: {one}"
                    log.warning("skipping reference: %s", reasons[k])
    return idx, ok, feats, reasons


class LocalEngine:
    """Describes in this process with the driver's descriptor (no Ray needed)."""

    workers = 1

    def __init__(self, desc: GlobalDescriptor, source: ImageSource, batch_size: int) -> None:
        self.desc, self.source, self.batch_size = desc, source, batch_size

    def fit(self, name, config, sample_ids):
        return fit_on_sample(self.desc, self.source, sample_ids, progress=False)

    def map(self, items, name, config, state, identity):
        for s in range(0, len(items), self.batch_size):
            yield describe_items(self.desc, self.source, items[s:s + self.batch_size])

    def close(self) -> None:
        pass
