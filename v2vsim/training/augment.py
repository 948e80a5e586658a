"""Yaw augmentation of camera training samples: the same scene seen by an agent turned about its vertical axis.

A camera model learns where things are from the extrinsics, but the targets of a dataset recorded in lanes
almost always show the agent's road straight ahead, and the model learns that as a prior (docs/results.md, camera
track: a lane-changing ego gets its road drawn straight while the ground truth is tilted). Turning the agent
frame by theta is exact for cameras: each camera-to-agent extrinsic becomes R_z(theta) E, and each BEV target
is rotated by the same theta. Cells whose source lies outside the recorded grid are marked "outside" and
left out of the loss. Boxes are not rotated: camera models have no detection head.

BEV grid as v2vsim.world.geometry.BevGrid: row 0 = front (+x), column 0 = left (+y), cell (r, c) centre at
x = S/2 - (r + 0.5) S/F, y = S/2 - (c + 0.5) S/F. Positive theta turns +x towards +y (counter-clockwise
seen from above).
"""

from __future__ import annotations

import torch
from torch import Tensor

from models.warp import warp_to_ego

MASKS = ("vehicle", "dynamic", "visible_self", "road", "lane")


def yaw_rotation(theta: Tensor) -> Tensor:
    """[B] radians -> [B, 4, 4] homogeneous rotations about z."""
    c, s = torch.cos(theta), torch.sin(theta)
    r = torch.eye(4, dtype=theta.dtype).repeat(len(theta), 1, 1)
    r[:, 0, 0], r[:, 0, 1], r[:, 1, 0], r[:, 1, 1] = c, -s, s, c
    return r


def rotate_masks(masks: Tensor, theta: Tensor, size_m: float) -> tuple[Tensor, Tensor]:
    """[B, K, F, F] masks turned by theta [B] -> (rotated masks [B, K, F, F], outside [B, F, F] bool).

    The turned frame is the ego grid of a "sender" at pose (0, 0, theta), so this is models.warp's
    warp_to_ego with nearest sampling: each output cell takes the cell its centre came from."""
    poses = torch.stack([torch.zeros_like(theta), torch.zeros_like(theta), theta], dim=-1).float()  # [B, 3]
    warped, inside = warp_to_ego(masks.float(), poses, size_m, mode="nearest")
    return warped > 0.5, ~inside


def yaw_rotate_batch(batch: dict, theta: Tensor, size_m: float) -> dict:
    """A copy of a collated camera batch (torch_dataset.collate) with the agent frame turned by theta [B]
    radians: "extrinsics" [B, L, M, 4, 4] left-multiplied by R_z(theta), the masks rotated, and "outside"
    [B, F, F] added (cells the recording did not cover; the loss ignores them)."""
    if "extrinsics" not in batch:
        raise ValueError("yaw augmentation needs camera samples (extrinsics); LiDAR batches are not supported")
    if batch["valid"].shape[1] != 1:
        raise ValueError("yaw augmentation turns one agent's frame; it needs single-agent batches (max_agents 1)")
    out = dict(batch)
    rot = yaw_rotation(theta.to(batch["extrinsics"].dtype))
    out["extrinsics"] = rot[:, None, None] @ batch["extrinsics"]
    turned, out["outside"] = rotate_masks(torch.stack([batch[k] for k in MASKS], dim=1), theta, size_m)
    out.update(zip(MASKS, turned.unbind(1), strict=True))
    return out
