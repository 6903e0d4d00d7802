"""CosPlace / EigenPlaces ``GeoLocalizationNet`` (ResNet-50, 512-D), state_dict-compatible.

Both releases share one architecture: ResNet-50 up to ``layer4`` (children 0..7 of torchvision's
model, i.e. keys ``backbone.0``, ``backbone.1``, ``backbone.4``..``backbone.7``), then
``aggregation = [channel L2-norm, GeM(p, eps=1e-6), flatten, Linear(2048, dim), L2-norm]``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vlm_vpr_ros.descriptors.deep.resnet import resnet50_out_channels, resnet50_sequential


class L2Norm(nn.Module):
    def __init__(self, dim: int = 1) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(x, p=2.0, dim=self.dim)


class GeM(nn.Module):
    """Generalised-mean pooling over the whole feature map with a learnable exponent ``p``."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), (x.size(-2), x.size(-1)))
        return pooled.pow(1.0 / self.p)


class GeoLocalizationNet(nn.Module):
    """Backbone + GeM aggregation; ``forward`` returns (B, dim) L2-normalised descriptors."""

    def __init__(self, fc_output_dim: int = 512) -> None:
        super().__init__()
        self.backbone = resnet50_sequential(4)
        features = resnet50_out_channels(4)
        self.aggregation = nn.Sequential(
            L2Norm(), GeM(), nn.Flatten(), nn.Linear(features, fc_output_dim), L2Norm())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.aggregation(self.backbone(x))
