"""One GlobalDescriptor for every deep VPR model: weights, device, batching, preprocessing.

Images go in as RGB uint8 (H, W, 3) arrays and are prepared exactly like the official test
pipelines (see :attr:`DeepDescriptor.preprocessing`): scale to [0, 1] (``ToTensor``), resize
where the model has a fixed input size, ImageNet normalisation. Extraction runs in batches of
``batch_size`` under ``torch.inference_mode()`` with the model in ``eval()``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from vlm_vpr_ros.config import from_mapping
from vlm_vpr_ros.descriptors.global_descriptor import GlobalDescriptor, l2_normalize
from vlm_vpr_ros.descriptors.deep import weights as W
from vlm_vpr_ros.descriptors.deep.specs import IMAGENET_MEAN, IMAGENET_STD, ModelSpec
from vlm_vpr_ros.errors import ConfigError, DescriptorError
from vlm_vpr_ros.files.images import check_rgb

log = logging.getLogger(__name__)

DEVICES = ("auto", "cpu", "cuda")
#: show a progress bar only when one call describes at least this many images
PROGRESS_MIN_IMAGES = 256


@dataclass(frozen=True)
class DeepConfig:
    #: checkpoint path; None = ``$TORCH_HOME/hub/checkpoints/<official file name>``
    weights: str | None = None
    #: "auto" (cuda when available), "cpu", "cuda" or "cuda:N"
    device: str = "auto"
    #: images per forward pass; None = 1 on CPU (batching does not pay off there, see
    #: docs/models.md), 8 on CUDA
    batch_size: int | None = None
    #: float16 autocast on GPU (ignored with a warning on CPU)
    fp16: bool = False
    #: [H, W] resize before the network (CosPlace/EigenPlaces only; the others are fixed)
    resize: list[int] | None = None


def resolve_device(name: str) -> torch.device:
    base = name.split(":")[0]
    if base not in DEVICES:
        raise ConfigError(f"unknown device {name!r}; choices: {', '.join(DEVICES)} (or cuda:N)")
    if base == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if base == "cuda" and not torch.cuda.is_available():
        raise DescriptorError(f"device {name!r} requested but CUDA is not available "
                              "(use device=cpu or device=auto)")
    try:
        return torch.device(name)
    except RuntimeError as exc:
        raise ConfigError(f"invalid device {name!r}: {exc}") from exc


def _check_resize(spec: ModelSpec, resize: Any) -> list[int] | None:
    if resize is None:
        return None
    if (not isinstance(resize, (list, tuple)) or len(resize) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in resize)):
        raise ConfigError(f"{spec.name}: resize must be [H, W] (two integers), got {resize!r}")
    hw = [int(v) for v in resize]
    if spec.input_hw is not None:
        if hw == list(spec.input_hw):
            return None  # the fixed size anyway
        raise ConfigError(f"{spec.name}: the input size is fixed at {list(spec.input_hw)} by the "
                          f"released weights; resize={hw} is not possible")
    if not all(32 <= v <= 4096 for v in hw):
        raise ConfigError(f"{spec.name}: resize values must be within 32..4096, got {hw}")
    return hw


def _resize_like_pil(x: torch.Tensor, hw: list[int]) -> torch.Tensor:
    """Bicubic resize of 8-bit values as Pillow does it on a uint8 image: separable, horizontal
    pass then vertical pass, each rounded back to 0..255 (antialiased, a = -0.5)."""
    if x.shape[-1] != hw[1]:
        x = F.interpolate(x, size=(x.shape[-2], hw[1]), mode="bicubic", align_corners=False,
                          antialias=True).round_().clamp_(0, 255)
    if x.shape[-2] != hw[0]:
        x = F.interpolate(x, size=(hw[0], hw[1]), mode="bicubic", align_corners=False,
                          antialias=True).round_().clamp_(0, 255)
    return x


class DeepDescriptor(GlobalDescriptor):
    """A pretrained VPR network behind the GlobalDescriptor interface."""

    needs_fit = False

    def __init__(self, spec: ModelSpec, config: Mapping[str, Any] | None = None,
                 state_dict: Mapping[str, torch.Tensor] | None = None) -> None:
        """``state_dict`` (tests/benchmarks only) replaces loading the checkpoint file."""
        cfg = from_mapping(DeepConfig, config, f"{spec.name} descriptor")
        resize = _check_resize(spec, cfg.resize)
        if cfg.batch_size is not None and (not isinstance(cfg.batch_size, int)
                                           or not 1 <= cfg.batch_size <= 1024):
            raise ConfigError(f"{spec.name}: batch_size must be 1..1024, got {cfg.batch_size!r}")
        if cfg.weights is not None and not isinstance(cfg.weights, (str, os.PathLike)):
            raise ConfigError(f"{spec.name}: weights must be a file path, got {cfg.weights!r}")
        if not isinstance(cfg.fp16, bool):
            raise ConfigError(f"{spec.name}: fp16 must be true or false, got {cfg.fp16!r}")
        super().__init__(asdict(cfg))
        self.spec = spec
        self.name = spec.name
        self.resize = resize
        self.device = resolve_device(str(cfg.device))
        self.batch_size = cfg.batch_size or (8 if self.device.type == "cuda" else 1)
        self.fp16 = bool(cfg.fp16) and self.device.type == "cuda"
        if cfg.fp16 and not self.fp16:
            log.warning("%s: fp16 needs a CUDA device; running float32 on %s", spec.name,
                        self.device)
        self.model = W.build_model(spec)
        if state_dict is not None:
            W.check_state_dict(self.model, state_dict, f"{spec.name} state_dict")
            self.model.load_state_dict(dict(state_dict), strict=True)
            self.weights_path, self.weights_sha256 = None, None
        else:
            self.weights_path = W.resolve_weights(spec, cfg.weights)
            W.load_weights(self.model, self.weights_path, spec.name)
            self.weights_sha256 = W.file_sha256(self.weights_path)
        self.model.eval().to(self.device)
        self._mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 3, 1, 1)

    # -- identity ------------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.spec.dim

    @property
    def input_hw(self) -> list[int] | None:
        """Network input size, or None for native resolution."""
        hw = self.spec.input_hw or self.resize
        return list(hw) if hw else None

    @property
    def preprocessing(self) -> dict[str, Any]:
        hw = self.input_hw
        return {
            "color": "RGB", "scale": "1/255",
            "resize": hw,
            "interpolation": None if hw is None else
            ("bicubic" if self.spec.input_hw else "bilinear"),
            "antialias": hw is not None,
            "resize_on": None if hw is None else ("uint8" if self.spec.resize_uint8 else "float"),
            "mean": list(IMAGENET_MEAN), "std": list(IMAGENET_STD),
        }

    def identity(self) -> dict[str, Any]:
        """Portable identity: no path, device or batch size, so maps move between machines."""
        config = {} if self.spec.input_hw else {"resize": self.resize}
        return {"name": self.name, "dim": self.dim, "release": self.spec.release,
                "config": config, "preprocessing": self.preprocessing,
                "weights_sha256": self.weights_sha256}

    # -- extraction ----------------------------------------------------------------------------
    def prepare(self, images: Sequence[np.ndarray]) -> torch.Tensor:
        """RGB uint8 images → normalised (N, 3, H, W) float32 on the device (images of
        different sizes are only allowed when the model resizes to a fixed size)."""
        if len({im.shape for im in images}) > 1:
            if self.input_hw is None:
                raise DescriptorError(f"{self.name}: images of different sizes cannot share a "
                                      "batch at native resolution")
            return torch.cat([self.prepare([im]) for im in images])
        x = torch.from_numpy(np.stack(images)).to(self.device).permute(0, 3, 1, 2).float()
        hw = self.input_hw
        if hw is not None and list(x.shape[-2:]) != hw:
            if self.spec.resize_uint8:
                x = _resize_like_pil(x, hw) / 255.0
            else:
                mode = "bicubic" if self.spec.input_hw else "bilinear"
                x = F.interpolate(x / 255.0, size=hw, mode=mode, align_corners=False,
                                  antialias=True)
        else:
            x = x / 255.0
        return (x - self._mean) / self._std

    def forward(self, x: torch.Tensor) -> np.ndarray:
        """Network on a prepared batch → (N, dim) float32 L2-normalised numpy array."""
        with torch.inference_mode(), torch.autocast("cuda", dtype=torch.float16,
                                                    enabled=self.fp16):
            y = self.model(x)
        return y.float().cpu().numpy()

    def _batches(self, images: Sequence[np.ndarray]) -> Iterator[list[np.ndarray]]:
        batch: list[np.ndarray] = []
        for im in images:
            if batch and (len(batch) >= self.batch_size or
                          (self.input_hw is None and im.shape != batch[0].shape)):
                yield batch
                batch = []
            batch.append(im)
        if batch:
            yield batch

    def describe(self, images: Sequence[np.ndarray]) -> np.ndarray:
        images = [check_rgb(im, f"{self.name} input {i}") for i, im in enumerate(images)]
        out = np.zeros((len(images), self.dim), np.float32)
        bar = None
        if len(images) >= PROGRESS_MIN_IMAGES:
            from tqdm import tqdm

            bar = tqdm(total=len(images), desc=self.name, unit="img", disable=None, leave=False)
        start = 0
        try:
            for batch in self._batches(images):
                out[start:start + len(batch)] = self.forward(self.prepare(batch))
                start += len(batch)
                if bar is not None:
                    bar.update(len(batch))
        except torch.cuda.OutOfMemoryError as exc:
            raise DescriptorError(f"{self.name}: out of GPU memory with batch_size="
                                  f"{self.batch_size}; use a smaller batch_size") from exc
        finally:
            if bar is not None:
                bar.close()
        if not np.isfinite(out).all():
            raise DescriptorError(f"{self.name}: non-finite descriptor values"
                                  + (" (try fp16=false)" if self.fp16 else ""))
        return l2_normalize(out)

    def close(self) -> None:
        self.model.to("cpu")
        if self.device.type == "cuda":
            torch.cuda.empty_cache()
