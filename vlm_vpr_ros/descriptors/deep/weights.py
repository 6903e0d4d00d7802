"""Checkpoints of the deep VPR models: where they are looked for, loading with a clear error
when they are missing or do not fit, and fetching them on a connected machine.

Search order: an explicit ``weights`` path, else ``<torch hub dir>/checkpoints/<release>``, i.e.
``$TORCH_HOME/hub/checkpoints`` (``~/.cache/torch/hub/checkpoints`` by default) — the file the
official ``torch.hub.load(...)`` call caches, so a checkpoint fetched either way is found.
Loading is ``torch.load(weights_only=True)`` + ``load_state_dict(strict=True)``; there is no
fallback to random weights.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import nn

from vlm_vpr_ros.descriptors.deep.specs import ModelSpec
from vlm_vpr_ros.errors import ConfigError, DescriptorError
from vlm_vpr_ros.files.atomic import atomic_path, commit_temp, file_sha256

log = logging.getLogger(__name__)

#: checkpoint containers that wrap the state_dict (PyTorch Lightning ``.ckpt``; the official
#: DISK release, read by the verification stage)
_WRAPPER_KEYS = ("state_dict", "extractor")
_MAX_LISTED = 8


def build_model(spec: ModelSpec) -> nn.Module:
    """The torch module of ``spec`` with its default (untrained) initialisation."""
    module_name, cls_name = spec.builder.split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    return cls(**spec.builder_kwargs)


def resolve_torch_device(device: str, what: str) -> torch.device:
    """``cpu``, or ``cuda`` / ``cuda:N`` where torch has CUDA; else a ConfigError naming
    ``what`` (the learned local features and matchers: XFeat, DISK, ALIKED, LightGlue)."""
    if not isinstance(device, str) or device.split(":")[0] not in ("cpu", "cuda"):
        raise ConfigError(f"{what} device {device!r}: choices: cpu, cuda, cuda:N")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"{what} device {device!r}: CUDA is not available in this torch "
                          f"({torch.__version__}); use device=cpu")
    try:
        return torch.device(device)
    except RuntimeError as exc:
        raise ConfigError(f"{what} device {device!r}: {exc}") from None


def hub_checkpoint_dir() -> Path:
    """``<torch.hub.get_dir()>/checkpoints`` (honours ``TORCH_HOME``)."""
    return Path(torch.hub.get_dir()) / "checkpoints"


def default_weights_path(spec: ModelSpec) -> Path:
    return hub_checkpoint_dir() / spec.release


def how_to_get(spec: ModelSpec) -> str:
    return (f"get it with 'vlm-vpr weights fetch {spec.name}' on a connected machine, or "
            f"download {spec.human_url} and pass its path as weights=PATH (--weights PATH)")


def resolve_weights(spec: ModelSpec, weights: str | os.PathLike[str] | None) -> Path:
    """The checkpoint file to load; DescriptorError naming what was expected and where."""
    if weights:
        path = Path(weights).expanduser()
        if not path.is_file():
            raise DescriptorError(f"{spec.name}: checkpoint {path} does not exist "
                                  f"(expected the official file {spec.release}); "
                                  + how_to_get(spec))
        return path
    path = default_weights_path(spec)
    if not path.is_file():
        raise DescriptorError(f"{spec.name}: no checkpoint given and {spec.release} is not in "
                              f"the torch hub cache ({path.parent}, set by TORCH_HOME); "
                              + how_to_get(spec))
    return path


def read_state_dict(path: str | os.PathLike[str], what: str = "checkpoint"
                    ) -> dict[str, torch.Tensor]:
    """Read a plain (or Lightning-wrapped) state_dict safely (``weights_only=True``)."""
    path = Path(path)
    try:
        head = path.read_bytes()[:512] if path.stat().st_size < 1 << 20 else b""
    except OSError as exc:
        raise DescriptorError(f"cannot read {what} {path}: {exc}") from exc
    if b"<html" in head.lower() or b"<!doctype" in head.lower():
        raise DescriptorError(f"{what} {path} is not a loadable torch checkpoint: it is an "
                              "HTML page (a download that returned a web page?)")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError, EOFError, KeyError, AttributeError, IndexError,
            TypeError, OverflowError, MemoryError, struct.error, pickle.UnpicklingError,
            zipfile.BadZipFile) as exc:  # garbage bytes reach the unpickler's every corner
        raise DescriptorError(f"{what} {path} is not a loadable torch checkpoint "
                              f"(read with weights_only=True): {type(exc).__name__}: "
                              f"{_short(exc)}") from exc
    for key in _WRAPPER_KEYS:
        if isinstance(obj, Mapping) and isinstance(obj.get(key), Mapping):
            obj = obj[key]
    if not isinstance(obj, Mapping) or not all(
            isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
        raise DescriptorError(f"{what} {path} does not hold a state_dict of named tensors "
                              f"(got {type(obj).__name__})")
    return dict(obj)


def _short(exc: BaseException) -> str:
    """The informative line of torch.load's (long) error text."""
    text = str(exc)
    marker = "WeightsUnpickler error:"
    if marker in text:
        text = text.split(marker, 1)[1]
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return (lines[0] if lines else type(exc).__name__)[:300]


def _listed(items: list[str]) -> str:
    more = f" ... (+{len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return ", ".join(items[:_MAX_LISTED]) + more


def check_state_dict(model: nn.Module, state: Mapping[str, torch.Tensor], source: str) -> None:
    """Raise DescriptorError listing missing, unexpected and wrongly shaped keys."""
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    missing = [k for k in expected if k not in state]
    unexpected = [k for k in state if k not in expected]
    shapes = [f"{k} {tuple(state[k].shape)} != {expected[k]}" for k in expected
              if k in state and tuple(state[k].shape) != expected[k]]
    if missing or unexpected or shapes:
        parts = []
        if shapes:
            parts.append(f"wrong shape: {_listed(shapes)}")
        if missing:
            parts.append(f"missing: {_listed(missing)}")
        if unexpected:
            parts.append(f"unexpected: {_listed(unexpected)}")
        raise DescriptorError(f"{source} does not fit this model ("
                              + "; ".join(parts) + ")")


def load_weights(model: nn.Module, path: str | os.PathLike[str], name: str = "") -> None:
    """Load a checkpoint file into ``model`` with ``strict=True`` after a readable check."""
    what = f"{name} checkpoint" if name else "checkpoint"
    state = read_state_dict(path, what)
    check_state_dict(model, state, f"{what} {path}")
    model.load_state_dict(state, strict=True)
    log.info("loaded %s from %s (%d tensors)", what, path, len(state))


def save_state_dict(state: Mapping[str, torch.Tensor], path: str | os.PathLike[str]) -> Path:
    """Write a plain state_dict atomically (temporary file + ``os.replace``)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(dict(state), tmp)
    return path


def recipe_state_dict(model: nn.Module) -> dict[str, torch.Tensor]:
    """Deterministic weights from key names (the recipe of ``shared/vpr_conformance``).

    For tests and benchmarks only: these are NOT trained weights.
    """
    out: dict[str, torch.Tensor] = {}
    for key, t in model.state_dict().items():
        g = torch.Generator().manual_seed(zlib.crc32(key.encode("utf-8")))
        shape = tuple(t.shape)
        if key.endswith("num_batches_tracked"):
            w = torch.zeros_like(t)
        elif key.endswith("running_var"):
            w = torch.rand(shape, generator=g) + 0.5
        elif key.endswith("running_mean"):
            w = torch.randn(shape, generator=g) * 0.1
        elif t.dim() >= 2:
            w = torch.randn(shape, generator=g) * (1.0 / math.sqrt(math.prod(shape[1:])))
        elif key.endswith(".weight"):
            w = 1 + 0.1 * torch.randn(shape, generator=g)
        else:
            w = torch.randn(shape, generator=g) * 0.1
        out[key] = w
    return out


def fetch(spec: ModelSpec, dest: str | os.PathLike[str] | None = None, url: str | None = None,
          force: bool = False, progress: bool = True) -> Path:
    """Download the official checkpoint, check that it fits the model, store it atomically
    where the loader looks (or in ``dest``). Returns the file's path."""
    target = (Path(dest).expanduser() / spec.release) if dest else default_weights_path(spec)
    if target.is_file() and not force:
        log.info("%s already present: %s", spec.name, target)
        return target
    urls = [url] if url else spec.download_urls
    if not urls:
        raise DescriptorError(f"{spec.name}: no download URL known; see {spec.official_repo}")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.part{os.getpid()}")
    errors: list[str] = []
    try:
        for u in urls:
            log.info("downloading %s from %s", spec.name, u)
            try:
                torch.hub.download_url_to_file(u, str(tmp), progress=progress)
            except (OSError, ValueError) as exc:  # URLError is an OSError
                errors.append(f"{u}: {exc}")
                continue
            try:
                state = read_state_dict(tmp, f"file downloaded from {u}")
                check_state_dict(build_model(spec), state, f"file downloaded from {u}")
            except DescriptorError as exc:
                raise DescriptorError(f"{exc}. If the server sent a web page instead of the "
                                      f"file, download {spec.human_url} in a browser and copy "
                                      f"it to {target}") from exc
            commit_temp(tmp, target)
            log.info("stored %s (%s)", target, file_sha256(target)[:16])
            return target
    finally:
        tmp.unlink(missing_ok=True)
    raise DescriptorError(f"could not download {spec.name} ({'; '.join(errors)}); download "
                          f"{spec.human_url} by hand and copy it to {target}")


def describe_weights(spec: ModelSpec, weights: str | None = None) -> dict[str, Any]:
    """Where a checkpoint is expected and whether it is there (for ``vlm-vpr weights list``)."""
    path = Path(weights).expanduser() if weights else default_weights_path(spec)
    return {"model": spec.name, "dim": spec.dim, "release": spec.release, "path": str(path),
            "present": path.is_file(), "url": spec.human_url}
