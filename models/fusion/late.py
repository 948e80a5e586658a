"""Late-fusion bracket (OPV2V "late"): every CAV runs the full single-agent model and ships its outputs;
the ego merges them in its own frame.

Segmentation: warp each agent's probability maps with models.warp (bilinear), take the max over the
valid agents that see the cell. Detection: move each agent's boxes into the ego frame and run
rotated NMS over the union.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from models.nms import rotated_nms
from models.warp import transform_boxes, warp_to_ego

# This method's entry in the registry, read without importing this file (models.registry: METHOD's keys).
METHOD = {"name": "late", "bracket": True, "rank": 2, "paper": {"camera_iou": None, "lidar_ap70": 0.781}}


def late_fuse_probabilities(
    probs: Tensor, rel_poses: Tensor, valid: Tensor, bev_size_m: float = 100.0
) -> Tensor:
    """Max-merge per-agent probability maps in the ego grid.

    probs: [L, K, H, W] or [B, L, K, H, W] in each agent's own grid; rel_poses [.., L, 3];
    valid [.., L] bool. Cells seen by no valid agent get 0. Returns [K, H, W] or [B, K, H, W].
    """
    warped, cell = warp_to_ego(probs, rel_poses, bev_size_m)  # [.., L, K, H, W], [.., L, H, W]
    ok = (cell & valid[..., None, None])[..., None, :, :]  # [.., L, 1, H, W]
    neg = torch.full((), float("-inf"), dtype=probs.dtype, device=probs.device)
    out = torch.where(ok, warped, neg).amax(dim=-4)  # [.., K, H, W]
    return torch.where(torch.isfinite(out), out, torch.zeros((), dtype=out.dtype, device=out.device))


def late_fuse_boxes(
    boxes: Sequence[Tensor],
    rel_poses: Tensor,
    valid: Tensor | None = None,
    iou_threshold: float = 0.15,
    max_out: int | None = None,
    extent_m: float | None = None,
) -> Tensor:
    """Union of every valid agent's boxes [N_j, 6] (x, y, l, w, yaw, score) in the ego frame + rotated NMS.

    rel_poses: [L, 3] agent poses in the ego body frame. extent_m: keep only boxes whose centre lies on
    the ego's extent_m x extent_m grid (a neighbour sees beyond it; ground truth and every other method
    stop there, as OpenCOOD's range mask does). Returns [K, 6] sorted by score.
    """
    if valid is None:
        valid = torch.ones(len(boxes), dtype=torch.bool)
    moved = [transform_boxes(b, rel_poses[j]) for j, b in enumerate(boxes) if bool(valid[j]) and b.numel()]
    if not moved:
        return rel_poses.new_zeros(0, 6)
    allb = torch.cat(moved, dim=0)
    if extent_m is not None:
        allb = allb[(allb[:, 0].abs() < extent_m / 2) & (allb[:, 1].abs() < extent_m / 2)]
    keep = rotated_nms(allb[:, :5], allb[:, 5], iou_threshold, max_out)
    return allb[keep]
