"""F-Cooper (Chen et al. 2019) feature fusion: element-wise max over the valid agents (maxout)."""

from __future__ import annotations

import torch
from torch import Tensor

from models.fusion.base import FusionModule, check_inputs


class FCooperFusion(FusionModule):
    """out[c, h, w] = max over valid agents j of features[j, c, h, w]; absent agents are -inf."""

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask)
        m = valid_mask[:, :, None, None, None]  # [B, L, 1, 1, 1]
        neg = torch.full((), float("-inf"), dtype=features.dtype, device=features.device)
        out = torch.where(m, features, neg).amax(dim=1)  # [B, C, H, W]
        any_valid = valid_mask.any(dim=1)[:, None, None, None]
        return torch.where(any_valid, out, torch.zeros((), dtype=out.dtype, device=out.device))
