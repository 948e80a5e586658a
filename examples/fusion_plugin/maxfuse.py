"""MaxFuse: an example fusion method for v2vsim, registered from outside the package through the entry point
`maxfuse = "maxfuse:MaxFusion"` in group "v2vsim.fusion" (pyproject.toml).

The fusion contract (v2vsim's models/fusion/base.py, checked when v2vsim loads the plugin): built as
``MaxFusion(channels)``; forward(features [B, L, C, H, W], valid_mask [B, L] bool) -> [B, C, H, W]; slot 0 is the
ego (always present); an absent agent (valid_mask False) must not change the output by a bit, whatever its
features hold (NaN and inf included).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class MaxFusion(nn.Module):
    """out = ego + mix([ego, max over the agents present]): F-Cooper's element-wise maxout, mixed into the ego's own
    map by a 1 x 1 convolution. The convolution starts at zero, so untrained MaxFuse returns the ego's map (no
    fusion) and training learns how much of the pooled neighbours to add, cell by cell."""

    # Optional: keyword arguments (beyond `channels`) per v2vsim model preset, e.g. {"paper": {"hidden": 256}}.
    preset_kwargs: dict[str, dict] = {}
    # Optional: a zoo folder shipped in this package (manifest.json + <encoder>_<preset>/maxfuse.pt, as
    # `v2vsim train --stage maxfuse --out FOLDER` writes it); v2vsim loads it under `perception.weights: auto` when it
    # was trained on the installed zoo's encoder and wire. This example ships none: train it (README.md).
    weights = None

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.channels = channels
        self.mix = nn.Conv2d(2 * channels, channels, kernel_size=1)
        nn.init.zeros_(self.mix.weight)
        nn.init.zeros_(self.mix.bias)

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        ego = features[:, 0]
        present = valid_mask[:, :, None, None, None]
        # absent agents become -inf before the max (never `features * mask`: 0 * inf is NaN)
        pooled = torch.where(present, features, torch.full((), float("-inf"), dtype=features.dtype,
                                                           device=features.device)).amax(dim=1)
        return ego + self.mix(torch.cat([ego, pooled], dim=1))
