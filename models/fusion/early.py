"""Early-fusion bracket (OPV2V "early"): ship raw points, merge them in the ego frame, encode once.

Not a fusion module: the ego encoder runs on the merged cloud and the result goes straight to the
heads (fusion "none" over a single agent).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from models.warp import transform_points

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "early", "bracket": True, "rank": 3, "paper": {"camera_iou": None, "lidar_ap70": 0.800}}


def merge_points_to_ego(points: Sequence[Tensor], rel_poses: Tensor, valid: Tensor | None = None) -> Tensor:
    """Concatenate every valid agent's cloud in the ego body frame.

    points: L tensors [P_j, >=4] (x, y, z, intensity, ...) in each agent's body frame (slot 0 = ego);
    rel_poses: [L, 3] (dx, dy, dyaw) of each agent in the ego body frame; valid: [L] bool (default all).
    z is kept (all body frames sit on the ground plane). Returns [sum P_j, C].
    """
    if valid is None:
        valid = torch.ones(len(points), dtype=torch.bool)
    if len(points) != rel_poses.shape[0] or len(points) != valid.shape[0]:
        raise ValueError(f"{len(points)} clouds, {rel_poses.shape[0]} poses, {valid.shape[0]} flags")
    moved = [transform_points(p, rel_poses[j]) for j, p in enumerate(points) if bool(valid[j])]
    if not moved:
        return points[0].new_zeros(0, points[0].shape[1])
    return torch.cat(moved, dim=0)
