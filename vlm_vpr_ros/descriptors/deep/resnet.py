"""ResNet-50 in plain torch, parameter-for-parameter compatible with torchvision's ``resnet50``.

torchvision is deliberately not a dependency (its compiled extension fails to import next to the
CPU-only torch wheel). The modules below create exactly the state_dict entries torchvision does:
same attribute names, same registration order, same shapes (ResNet v1.5: the stride sits on the
3x3 convolution of each bottleneck; BatchNorm eps 1e-5). Each VPR model wraps the stages in the
container its official code uses, so official checkpoints load with ``strict=True``.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import nn

#: (blocks, bottleneck width) of the four ResNet-50 stages
RESNET50_STAGES = ((3, 64), (4, 128), (6, 256), (3, 512))
EXPANSION = 4


class Bottleneck(nn.Module):
    """1x1 reduce → 3x3 (carries the stride) → 1x1 expand, plus identity or projection."""

    def __init__(self, in_ch: int, width: int, stride: int = 1) -> None:
        super().__init__()
        out_ch = width * EXPANSION
        self.conv1 = nn.Conv2d(in_ch, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out_ch, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out_ch)
        self.relu = nn.ReLU(inplace=True)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_ch != out_ch:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_ch, out_ch, 1, stride=stride, bias=False), nn.BatchNorm2d(out_ch))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.downsample is None else self.downsample(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + shortcut)


def _stage(in_ch: int, width: int, blocks: int, stride: int) -> nn.Sequential:
    layers = [Bottleneck(in_ch, width, stride)]
    layers += [Bottleneck(width * EXPANSION, width) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


def resnet50_parts(n_stages: int = 4) -> "OrderedDict[str, nn.Module]":
    """Stem and the first ``n_stages`` residual stages, named as torchvision names them
    (``conv1``, ``bn1``, ``relu``, ``maxpool``, ``layer1``...). Output channels: 256·2^(n-1)."""
    if not 1 <= n_stages <= 4:
        raise ValueError(f"n_stages must be 1..4, got {n_stages}")
    parts: OrderedDict[str, nn.Module] = OrderedDict()
    parts["conv1"] = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
    parts["bn1"] = nn.BatchNorm2d(64)
    parts["relu"] = nn.ReLU(inplace=True)
    parts["maxpool"] = nn.MaxPool2d(3, stride=2, padding=1)
    in_ch = 64
    for i, (blocks, width) in enumerate(RESNET50_STAGES[:n_stages]):
        parts[f"layer{i + 1}"] = _stage(in_ch, width, blocks, stride=1 if i == 0 else 2)
        in_ch = width * EXPANSION
    return parts


def resnet50_sequential(n_stages: int = 4, named: bool = False) -> nn.Sequential:
    """The stages as one Sequential: numbered children (``0``, ``1``, ``4``.. as CosPlace/BoQ
    slice torchvision's children) or, with ``named``, torchvision's attribute names."""
    parts = resnet50_parts(n_stages)
    return nn.Sequential(parts) if named else nn.Sequential(*parts.values())


def resnet50_out_channels(n_stages: int) -> int:
    return RESNET50_STAGES[n_stages - 1][1] * EXPANSION
