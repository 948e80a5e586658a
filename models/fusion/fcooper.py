"""F-Cooper (Chen et al. 2019) feature fusion: element-wise max over the valid agents (maxout)."""

from __future__ import annotations

import torch
from torch import Tensor

from models.fusion.base import FusionModule, check_inputs

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "fcooper", "factory": "FCooperFusion", "rank": 5, "preset_kwargs": {},
          "paper": {"camera_iou": (52.5, 60.4, 46.5), "lidar_ap70": 0.790}}


class FCooperFusion(FusionModule):
    """out[c, h, w] = max over valid agents j of features[j, c, h, w]; absent agents are -inf."""

    preset_kwargs = METHOD["preset_kwargs"]  # the sizes per preset, where a plugin's class carries them

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask)
        m = valid_mask[:, :, None, None, None]  # [B, L, 1, 1, 1]
        neg = torch.full((), float("-inf"), dtype=features.dtype, device=features.device)
        out = torch.where(m, features, neg).amax(dim=1)  # [B, C, H, W]
        any_valid = valid_mask.any(dim=1)[:, None, None, None]
        return torch.where(any_valid, out, torch.zeros((), dtype=out.dtype, device=out.device))
