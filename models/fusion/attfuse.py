"""AttFuse (OPV2V, Xu et al. 2022): per-cell scaled dot-product attention across agents.

At every BEV cell the ego feature is the query and every valid agent's feature (ego included) is a
key and value: w_j = softmax_j(x_0 . x_j / sqrt(C)) (Eq. 1 of the CoBEVT supp.), out = sum_j w_j x_j.
Like OPV2V's AttentionFusion there are no projection weights (parameter-free). Absent agents get
-inf logits.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from models.fusion.base import FusionModule, check_inputs, zero_invalid

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "attfuse", "factory": "AttFusion", "rank": 4, "preset_kwargs": {},
          "paper": {"camera_iou": (51.9, 60.5, 46.2), "lidar_ap70": 0.815}}


class AttFusion(FusionModule):
    """Ego-query attention over agents at each cell; [B, L, C, H, W] -> [B, C, H, W]."""

    preset_kwargs = METHOD["preset_kwargs"]  # the sizes per preset, where a plugin's class carries them

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask)
        x = zero_invalid(features, valid_mask)  # [B, L, C, H, W]
        q = x[:, :1]  # [B, 1, C, H, W]
        logits = (q * x).sum(dim=2) / math.sqrt(x.shape[2])  # [B, L, H, W]
        logits = logits.masked_fill(~valid_mask[:, :, None, None], float("-inf"))
        w = torch.softmax(logits, dim=1)  # [B, L, H, W]
        w = torch.nan_to_num(w, nan=0.0)  # a batch item without any valid agent -> zeros
        return (w[:, :, None] * x).sum(dim=1)  # [B, C, H, W]
