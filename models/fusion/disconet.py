"""DiscoNet (Li et al. 2021) collaboration graph: per-cell edge weights, softmax over valid agents.

w_{0j}(h, w) = MLP_1x1([x_0 ; x_j])(h, w)  (1x1 convs, 2C -> C -> C/4 -> C/16 -> 1, as the original
PixelWeightedFusion 256-128-32-8-1 with ReLUs; BatchNorm is dropped so that absent agents cannot
leak through batch statistics), softmax over the valid agents j (ego included), out = sum_j w x_j.

The knowledge-distillation teacher (an early-fusion model whose intermediate features supervise the
student's fused features) belongs to training, not to this module.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from models.fusion.base import FusionModule, check_inputs, zero_invalid

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "disconet", "factory": "DiscoNetFusion", "rank": 7, "preset_kwargs": {},
          "paper": {"camera_iou": (52.9, 60.7, 45.8), "lidar_ap70": None}}


class DiscoNetFusion(FusionModule):
    """Edge-weighted per-cell fusion; [B, L, C, H, W] -> [B, C, H, W]."""

    preset_kwargs = METHOD["preset_kwargs"]  # the sizes per preset, where a plugin's class carries them

    def __init__(self, channels: int) -> None:
        super().__init__(channels)
        h1, h2, h3 = channels, max(channels // 4, 4), max(channels // 16, 2)
        self.edge = nn.Sequential(
            nn.Conv2d(2 * channels, h1, 1), nn.ReLU(inplace=True),
            nn.Conv2d(h1, h2, 1), nn.ReLU(inplace=True),
            nn.Conv2d(h2, h3, 1), nn.ReLU(inplace=True),
            nn.Conv2d(h3, 1, 1),
        )  # fmt: skip

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask, self.channels)
        x = zero_invalid(features, valid_mask)  # [B, L, C, H, W]
        b, l, c, h, w = x.shape
        pair = torch.cat([x[:, :1].expand(b, l, c, h, w), x], dim=2)  # [B, L, 2C, H, W]
        logits = self.edge(pair.reshape(b * l, 2 * c, h, w)).reshape(b, l, h, w)  # [B, L, H, W]
        logits = logits.masked_fill(~valid_mask[:, :, None, None], float("-inf"))
        wts = torch.nan_to_num(torch.softmax(logits, dim=1), nan=0.0)  # [B, L, H, W]
        return (wts[:, :, None] * x).sum(dim=1)  # [B, C, H, W]
