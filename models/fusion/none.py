"""No fusion: the ego's own features (the single-agent baseline)."""

from __future__ import annotations

from torch import Tensor

from models.fusion.base import FusionModule, check_inputs

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "none", "factory": "NoFusion", "rank": 1, "preset_kwargs": {},
          "paper": {"camera_iou": (37.7, 57.8, 43.7), "lidar_ap70": None}}


class NoFusion(FusionModule):
    """Returns features[:, 0] (ego slot); neighbours are never read."""

    preset_kwargs = METHOD["preset_kwargs"]  # the sizes per preset, where a plugin's class carries them

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask)
        return features[:, 0]  # [B, C, H, W]
