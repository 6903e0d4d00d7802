"""MixVPR (ResNet-50 cropped after ``layer3``, 320x320 input), state_dict-compatible.

Keys: ``backbone.model.{conv1,bn1,layer1..layer3}`` (torchvision names; ``layer4``/``fc`` are
dropped) and ``aggregator.mix.{i}.mix.{0,1,3}`` (LayerNorm, Linear, ReLU, Linear over the
flattened H·W positions), ``aggregator.channel_proj``, ``aggregator.row_proj``. The descriptor is
``out_channels x out_rows`` flattened and L2-normalised (256x2 = 512-D, 1024x4 = 4096-D).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vlm_vpr_ros.descriptors.deep.resnet import resnet50_out_channels, resnet50_sequential

#: the layer3 feature map of a 320x320 input is 20x20; the mixer widths depend on it
INPUT_HW = (320, 320)
FEATURE_HW = (20, 20)


class CroppedResNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.model = resnet50_sequential(3, named=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class FeatureMixer(nn.Module):
    """Residual MLP applied along the flattened spatial axis of each channel."""

    def __init__(self, width: int, mlp_ratio: float = 1.0) -> None:
        super().__init__()
        hidden = int(width * mlp_ratio)
        self.mix = nn.Sequential(
            nn.LayerNorm(width), nn.Linear(width, hidden), nn.ReLU(), nn.Linear(hidden, width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.mix(x)


class MixVPRAggregator(nn.Module):
    def __init__(self, in_channels: int = 1024, in_hw: tuple[int, int] = FEATURE_HW,
                 out_channels: int = 256, mix_depth: int = 4, mlp_ratio: float = 1.0,
                 out_rows: int = 2) -> None:
        super().__init__()
        positions = in_hw[0] * in_hw[1]
        self.mix = nn.Sequential(*[FeatureMixer(positions, mlp_ratio) for _ in range(mix_depth)])
        self.channel_proj = nn.Linear(in_channels, out_channels)
        self.row_proj = nn.Linear(positions, out_rows)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.mix(x.flatten(2))                           # (B, C, HW)
        x = self.channel_proj(x.transpose(1, 2))             # (B, HW, out_channels)
        x = self.row_proj(x.transpose(1, 2))                 # (B, out_channels, out_rows)
        return F.normalize(x.flatten(1), p=2.0, dim=-1)


class MixVPRNet(nn.Module):
    def __init__(self, out_channels: int = 256, out_rows: int = 2) -> None:
        super().__init__()
        self.backbone = CroppedResNet()
        self.aggregator = MixVPRAggregator(in_channels=resnet50_out_channels(3),
                                           out_channels=out_channels, out_rows=out_rows)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(x))
