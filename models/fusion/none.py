"""No fusion: the ego's own features (the single-agent baseline)."""

from __future__ import annotations

from torch import Tensor

from models.fusion.base import FusionModule, check_inputs


class NoFusion(FusionModule):
    """Returns features[:, 0] (ego slot); neighbours are never read."""

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask)
        return features[:, 0]  # [B, C, H, W]
