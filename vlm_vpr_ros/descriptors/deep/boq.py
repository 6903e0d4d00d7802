"""Bag-of-Queries (BoQ) with a ResNet-50 backbone cropped after ``layer3`` (16384-D).

Keys: ``backbone.net.{0,1,4,5,6}`` (conv1, bn1, layer1..layer3 — the naming of the released
checkpoint) and ``aggregator.{proj_c, norm_input, boqs.{i}.*, fc}``. Each BoQ block runs a
transformer encoder layer over the input tokens, refines its learnable queries with
self-attention, and lets them cross-attend to the tokens; the per-block outputs are stacked,
mixed by ``fc`` into ``row_dim`` rows and flattened (512 x 32 = 16384-D, L2-normalised).

The official ``forward`` returns ``(descriptor, attentions)``; :class:`BoQNet` returns only the
descriptor unless ``return_attention=True``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vlm_vpr_ros.descriptors.deep.resnet import resnet50_out_channels, resnet50_sequential

INPUT_HW = (384, 384)


class CroppedResNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.net = resnet50_sequential(3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class BoQBlock(nn.Module):
    def __init__(self, dim: int, num_queries: int, heads: int) -> None:
        super().__init__()
        # parameters of the module itself come first in state_dict order (``queries``)
        self.encoder = nn.TransformerEncoderLayer(d_model=dim, nhead=heads,
                                                  dim_feedforward=4 * dim, dropout=0.0,
                                                  batch_first=True)
        self.queries = nn.Parameter(torch.randn(1, num_queries, dim))
        self.self_attn = nn.MultiheadAttention(dim, num_heads=heads, batch_first=True)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, num_heads=heads, batch_first=True)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        x = self.encoder(x)
        q = self.queries.expand(x.size(0), -1, -1)
        q = self.norm_q(q + self.self_attn(q, q, q, need_weights=False)[0])
        out, attn = self.cross_attn(q, x, x)
        return x, self.norm_out(out), attn


class BoQAggregator(nn.Module):
    def __init__(self, in_channels: int = 1024, proj_channels: int = 512, num_queries: int = 64,
                 num_layers: int = 2, row_dim: int = 32) -> None:
        super().__init__()
        self.proj_c = nn.Conv2d(in_channels, proj_channels, kernel_size=3, padding=1)
        self.norm_input = nn.LayerNorm(proj_channels)
        self.boqs = nn.ModuleList(
            [BoQBlock(proj_channels, num_queries, heads=proj_channels // 64)
             for _ in range(num_layers)])
        self.fc = nn.Linear(num_layers * num_queries, row_dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        x = self.norm_input(self.proj_c(x).flatten(2).transpose(1, 2))   # (B, HW, C)
        outs, attns = [], []
        for block in self.boqs:
            x, out, attn = block(x)
            outs.append(out)
            attns.append(attn)
        rows = self.fc(torch.cat(outs, dim=1).transpose(1, 2))            # (B, C, row_dim)
        return F.normalize(rows.flatten(1), p=2.0, dim=-1), attns


class BoQNet(nn.Module):
    def __init__(self, return_attention: bool = False) -> None:
        super().__init__()
        self.backbone = CroppedResNet()
        self.aggregator = BoQAggregator(in_channels=resnet50_out_channels(3))
        self.return_attention = return_attention

    def forward(self, x: torch.Tensor):
        desc, attns = self.aggregator(self.backbone(x))
        return (desc, attns) if self.return_attention else desc
