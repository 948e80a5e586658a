"""Learned latency compensation at the receiver: first-order extrapolation of a late feature message.

A neighbour's BEV features captured d frames before the ego fuses them show moving vehicles where they
*were* (DESIGN.md, "Latency matters through pose"). FFNet (Yu et al., "Flow-Based Feature Fusion for
Vehicle-Infrastructure Cooperative 3D Object Detection", NeurIPS 2023, arXiv:2311.01682) predicts the
features at the fusion time from their linear form, Eq. (10) of the NeurIPS paper (the "feature flow"):

    F(t0 + Δ) ≈ F(t0) + Δ · F'(t0),

with the first-order derivative F'(t0) estimated by a network from consecutive frames. FFNet computes the
derivative at the sender and ships it beside the features; our variant runs at the RECEIVER from the two
latest messages of one sender, so no byte is added on the wire:

    new          the latest message, captured at t1 (features [C, F, F] in the sender's frame at t1)
    old_aligned  the message before it, captured at t0 < t1, warped into the sender's frame at t1
                 (`align_previous`, with the pose of the t0 capture in the t1 capture frame)
    steps        age of `new` when it is fused / (t1 - t0)   (e.g. 200 ms old, messages 100 ms apart: 2.0)
    output       new + steps · D(new, new - old_aligned)

D (`FeatureExtrapolation.derivative`) is the per-interval change of the features, a small conv net. Its last
convolution starts at zero, so an untrained module is the identity, and steps = 0 returns `new` exactly.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from models.warp import warp_to_ego


class FeatureExtrapolation(nn.Module):
    """forward(new [B, C, F, F], old_aligned [B, C, F, F], steps [B]) -> [B, C, F, F] = new + steps · D.

    D = conv3x3(2C -> H) - ReLU - conv3x3(H -> H) - ReLU - conv3x3(H -> C) over cat([new, new - old_aligned]),
    the last convolution zero-initialised (H = `hidden`, default C)."""

    def __init__(self, channels: int, hidden: int | None = None) -> None:
        super().__init__()
        hidden = hidden or channels
        self.channels = channels
        self.net = nn.Sequential(
            nn.Conv2d(2 * channels, hidden, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, hidden, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, channels, 3, padding=1),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def derivative(self, new: Tensor, old_aligned: Tensor) -> Tensor:
        """The change of the features per message interval, [B, C, F, F]."""
        return self.net(torch.cat([new, new - old_aligned], dim=1))  # [B, 2C, F, F] -> [B, C, F, F]

    def forward(self, new: Tensor, old_aligned: Tensor, steps: Tensor) -> Tensor:
        if new.shape != old_aligned.shape or steps.shape != new.shape[:1]:
            raise ValueError(f"new {tuple(new.shape)}, old_aligned {tuple(old_aligned.shape)} and steps "
                             f"{tuple(steps.shape)} do not match ([B, C, F, F] twice and [B])")
        moving = steps != 0  # [B]; the others are returned exactly (and cost nothing)
        if not bool(moving.any()):
            return new
        d = self.derivative(new[moving], old_aligned[moving])  # [M, C, F, F]
        out = new.clone()
        out[moving] = new[moving] + steps[moving].to(new.dtype)[:, None, None, None] * d
        return out


def align_previous(old: Tensor, rel_pose: Tensor, bev_size_m: float, fill: Tensor | None = None) -> Tensor:
    """The older message of a sender in the frame of its newer one.

    old: [B, C, F, F] features in the sender's frame at the older capture; rel_pose: [B, 3] (dx, dy, dyaw) of
    that older capture pose in the newer capture's body frame (v2vsim.world.geometry.relative_pose(new, old));
    bev_size_m: the grid's extent S. Returns [B, C, F, F] on the newer grid (models.warp.warp_to_ego, bilinear).
    Cells the older map does not cover are zeros, or taken from `fill` [B, C, F, F] (pass `new`: no change
    there). A zero relative pose returns `old` itself (no resampling)."""
    warped, inside = warp_to_ego(old, rel_pose.to(old.dtype), bev_size_m)  # [B, C, F, F], [B, F, F]
    if fill is not None:
        warped = torch.where(inside[:, None], warped, fill)
    still = (rel_pose == 0).all(dim=-1)  # [B]
    return torch.where(still[:, None, None, None], old, warped)


def compensate(module: FeatureExtrapolation, new: Tensor, old: Tensor, rel_pose: Tensor, steps: Tensor,
               bev_size_m: float) -> Tensor:
    """Extrapolate late messages: `new` [B, C, F, F] from `old` [B, C, F, F] (the sender's message before,
    in its own frame, at pose `rel_pose` [B, 3] in the frame of `new`) by `steps` [B] message intervals."""
    return module(new, align_previous(old, rel_pose, bev_size_m, fill=new), steps)


def extrapolation_steps(age_s: float, interval_s: float) -> float:
    """Age of the newer message at fusion in units of the time between the two messages (0 without one)."""
    return age_s / interval_s if interval_s > 0 else 0.0
