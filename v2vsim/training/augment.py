"""Yaw augmentation of camera training samples: the same scene seen by an agent turned about its vertical axis.

A camera model learns where things are from the extrinsics, but the targets of a dataset recorded in lanes
almost always show the agent's road straight ahead, and the model learns that as a prior (README, camera
track: a lane-changing ego gets its road drawn straight while the ground truth is tilted). Turning the agent
frame by theta is exact for cameras: each camera-to-agent extrinsic becomes R_z(theta) E, and each BEV target
is rotated by the same theta. Cells whose source lies outside the recorded grid are marked "outside" and
left out of the loss. Boxes are not rotated: camera models have no detection head.

BEV grid as v2vsim.geometry.BevGrid: row 0 = front (+x), column 0 = left (+y), cell (r, c) centre at
x = S/2 - (r + 0.5) S/F, y = S/2 - (c + 0.5) S/F. Positive theta turns +x towards +y (counter-clockwise
seen from above).
"""

from __future__ import annotations

import torch
from torch import Tensor

MASKS = ("vehicle", "dynamic", "visible_self", "road", "lane")


def yaw_rotation(theta: Tensor) -> Tensor:
    """[B] radians -> [B, 4, 4] homogeneous rotations about z."""
    c, s = torch.cos(theta), torch.sin(theta)
    r = torch.eye(4, dtype=theta.dtype).repeat(len(theta), 1, 1)
    r[:, 0, 0], r[:, 0, 1], r[:, 1, 0], r[:, 1, 1] = c, -s, s, c
    return r


def rotate_masks(masks: Tensor, theta: Tensor, size_m: float) -> tuple[Tensor, Tensor]:
    """[B, F, F] masks turned by theta [B] -> (rotated masks [B, F, F], outside [B, F, F] bool).

    Nearest cell: each output cell takes the cell its centre came from, R(-theta) p."""
    b, f, _ = masks.shape
    res = size_m / f
    coord = size_m / 2 - (torch.arange(f, dtype=torch.float64) + 0.5) * res
    x, y = torch.meshgrid(coord, coord, indexing="ij")  # [F, F] each: output cell centres
    c, s = torch.cos(theta.double())[:, None, None], torch.sin(theta.double())[:, None, None]
    xs, ys = c * x + s * y, -s * x + c * y  # R(-theta) p, [B, F, F]
    rows = torch.floor((size_m / 2 - xs) / res).long()
    cols = torch.floor((size_m / 2 - ys) / res).long()
    outside = (rows < 0) | (rows >= f) | (cols < 0) | (cols >= f)
    flat = rows.clamp(0, f - 1) * f + cols.clamp(0, f - 1)
    out = masks.reshape(b, f * f).gather(1, flat.reshape(b, f * f)).reshape(b, f, f)
    return out.masked_fill(outside, False) if out.dtype == torch.bool else out.masked_fill(outside, 0), outside


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
    outside = None
    for k in MASKS:
        out[k], outside = rotate_masks(batch[k], theta, size_m)
    out["outside"] = outside
    return out
