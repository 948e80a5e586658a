"""The intermediate-fusion interface (CoBEVT supp. Sec. 3.3: "all the comparison methods have the
same configurations except for the fusion component").

A fusion method is an ``nn.Module`` constructed as ``Method(channels, **preset_kwargs)`` with

    forward(features: Tensor [B, L, C, H, W], valid_mask: Tensor [B, L] bool) -> Tensor [B, C, H, W]

- ``features`` are already warped into the ego BEV grid (models.warp.warp_to_ego).
- Slot 0 is the ego (always valid); slots 1..L-1 are neighbours in any order.
- Absent agents (``valid_mask`` False) must be ignored EXACTLY: whatever their features hold
  (garbage, inf, NaN) the output is bit-for-bit unchanged. Exclude them with ``torch.where``,
  -inf softmax logits or -inf in max, never by multiplying with the mask alone (0 * inf = NaN),
  and never normalise across the agent axis with batch statistics (BatchNorm would leak them).
- Symmetric methods must be invariant to the order of the neighbours.

The FuseBEVT module (models.fusion.cobevt) follows the same contract structurally; methods in this
package subclass :class:`FusionModule`. Adding a method = one file here + one registration in models.registry
(+ optional sizes in models.presets); from another package: an entry point in group "v2vsim.fusion"
(examples/fusion_plugin). A method registered from outside is checked against this contract when it loads
(models.fusion.contract.check_fusion_module).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch
from torch import Tensor, nn


class FusionModule(nn.Module, ABC):
    """Base class of the fusion methods: see the module docstring for the contract."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.channels = channels

    @abstractmethod
    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        """[B, L, C, H, W], [B, L] bool -> [B, C, H, W]."""


def check_inputs(features: Tensor, valid_mask: Tensor, channels: int | None = None) -> None:
    """Raise ValueError unless features is [B, L, C, H, W] and valid_mask [B, L] bool."""
    if features.dim() != 5:
        raise ValueError(f"features must be [B, L, C, H, W], got {tuple(features.shape)}")
    if valid_mask.shape != features.shape[:2] or valid_mask.dtype != torch.bool:
        raise ValueError(f"valid_mask must be bool {tuple(features.shape[:2])}, got {valid_mask.dtype} "
                         f"{tuple(valid_mask.shape)}")
    if channels is not None and features.shape[2] != channels:
        raise ValueError(f"expected {channels} channels, got {features.shape[2]}")


def zero_invalid(features: Tensor, valid_mask: Tensor) -> Tensor:
    """Replace absent agents' features by exact zeros (torch.where: no NaN/inf can leak)."""
    zero = torch.zeros((), dtype=features.dtype, device=features.device)
    return torch.where(valid_mask[:, :, None, None, None], features, zero)
