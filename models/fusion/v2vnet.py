"""V2VNet (Wang et al. 2020) spatially-aware message passing, receiver-side form.

For k = 1..K (K = 2):
    m_{j->0} = ReLU(Conv3x3([h_j ; h_0]))                 message CNN on neighbour + ego features
    m_0      = mean over VALID neighbours j != 0 of m_j   (zero when there is none)
    h_0      = ConvGRU(m_0, h_0)
The output is h_0. Features arrive once per frame, so only the ego's state is iterated (the
neighbours' states are what they sent); the concat conv is evaluated as W_n * h_j + W_e * h_0
(the same operator; the neighbour term is computed once, not once per iteration).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.fusion.base import FusionModule, check_inputs, zero_invalid

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "v2vnet", "factory": "V2VNetFusion", "rank": 6,
          "preset_kwargs": {"paper": {"iterations": 2}, "tiny": {"iterations": 2}},
          "paper": {"camera_iou": (53.5, 60.2, 47.5), "lidar_ap70": 0.822}}


class ConvGRUCell(nn.Module):
    """Convolutional GRU (3x3): h' = (1 - z) h + z tanh(W [x ; r h])."""

    def __init__(self, in_channels: int, hidden: int) -> None:
        super().__init__()
        self.gates = nn.Conv2d(in_channels + hidden, 2 * hidden, 3, padding=1)
        self.cand = nn.Conv2d(in_channels + hidden, hidden, 3, padding=1)

    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        z, r = torch.sigmoid(self.gates(torch.cat([x, h], dim=1))).chunk(2, dim=1)
        n = torch.tanh(self.cand(torch.cat([x, r * h], dim=1)))
        return (1 - z) * h + z * n


class V2VNetFusion(FusionModule):
    """Message CNN + masked mean aggregation + ConvGRU, `iterations` rounds; [B, L, C, H, W] -> [B, C, H, W]."""

    preset_kwargs = METHOD["preset_kwargs"]  # the sizes per preset, where a plugin's class carries them

    def __init__(self, channels: int, iterations: int = 2) -> None:
        super().__init__(channels)
        self.iterations = iterations
        self.message = nn.Conv2d(2 * channels, channels, 3, padding=1)  # on [h_j ; h_0]
        self.gru = ConvGRUCell(channels, channels)

    def forward(self, features: Tensor, valid_mask: Tensor) -> Tensor:
        check_inputs(features, valid_mask, self.channels)
        x = zero_invalid(features, valid_mask)  # [B, L, C, H, W]
        b, l, c, h, w = x.shape
        w_n, w_e = self.message.weight[:, :c], self.message.weight[:, c:]  # split of the concat conv
        nb = x[:, 1:].reshape(b * (l - 1), c, h, w)
        nb_term = F.conv2d(nb, w_n, self.message.bias, padding=1).reshape(b, l - 1, c, h, w)
        nb_valid = valid_mask[:, 1:, None, None, None]  # [B, L-1, 1, 1, 1]
        count = nb_valid.sum(dim=1).clamp(min=1).to(x.dtype)  # [B, 1, 1, 1]
        state = x[:, 0]  # [B, C, H, W]
        for _ in range(self.iterations):
            ego_term = F.conv2d(state, w_e, None, padding=1)[:, None]  # [B, 1, C, H, W]
            msgs = F.relu(nb_term + ego_term)  # [B, L-1, C, H, W]
            msgs = torch.where(nb_valid, msgs, torch.zeros((), dtype=msgs.dtype, device=msgs.device))
            state = self.gru(msgs.sum(dim=1) / count, state)
        return state
