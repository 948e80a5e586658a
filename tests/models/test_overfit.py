"""End-to-end: tiny PointPillars + warp + fusion + decoder + heads overfits one synthetic batch.

Proves gradients flow from the segmentation and detection losses back through the fusion, the
warp and the PFN. Two CAVs see one synthetic scene (a road with a lane marking and two vehicles)
from different poses; the loss must fall by at least 10x.
"""

from __future__ import annotations

import math
import time

import torch

from models.build import build_cooperative
from models.heads import AnchorTargetAssigner
from models.losses import detection_loss, segmentation_loss, static_target
from models.warp import transform_points
from v2vsim.world.geometry import BevGrid

BEV = 51.2  # a smaller area keeps the test fast; the grids are the tiny preset's (F = 32, 256 x 256 out)


def _scene(gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Ego-frame points (road along x, |y| < 6 m, lane marking |y| < 0.4 m, two boxes) and GT boxes."""
    boxes = torch.tensor([[10.0, 2.5, 4.5, 1.9, 0.1], [-8.0, -3.0, 4.4, 1.8, -0.2]])
    road = torch.rand(6000, 2, generator=gen) * torch.tensor([BEV, 12.0]) - torch.tensor([BEV / 2, 6.0])
    road_pts = torch.cat([road, torch.zeros(6000, 1), torch.where(road[:, 1:].abs() < 0.4, 0.9, 0.1)], 1)
    cars = []
    for b in boxes:
        u = torch.rand(800, 3, generator=gen) - 0.5
        local = u[:, :2] * b[2:4]
        c, s = math.cos(b[4]), math.sin(b[4])
        xy = torch.stack([c * local[:, 0] - s * local[:, 1] + b[0], s * local[:, 0] + c * local[:, 1] + b[1]], 1)
        cars.append(torch.cat([xy, (u[:, 2:] + 0.5) * 1.5, torch.full((800, 1), 0.5)], 1))
    return torch.cat([road_pts, *cars]), boxes


def _rasterise(boxes: torch.Tensor, grid: BevGrid) -> torch.Tensor:
    """[S, S] 0/1 vehicle mask: cells whose centre lies in a box."""
    xy = torch.as_tensor(grid.cell_centres(), dtype=torch.float32)  # [S, S, 2]
    mask = torch.zeros(xy.shape[:2], dtype=torch.long)
    for b in boxes:
        rel = xy - b[:2]
        c, s = math.cos(b[4]), math.sin(b[4])
        u, v = rel[..., 0] * c + rel[..., 1] * s, -rel[..., 0] * s + rel[..., 1] * c
        mask |= ((u.abs() <= b[2] / 2) & (v.abs() <= b[3] / 2)).long()
    return mask


def _to_frame(points: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """Ego-frame points -> the body frame of an agent at `pose` (dx, dy, dyaw) in the ego frame."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    inv = torch.tensor([-(c * pose[0] + s * pose[1]), s * pose[0] - c * pose[1], -pose[2]])
    return transform_points(points, inv)




def test_tiny_pointpillars_pipeline_overfits_one_batch() -> None:
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    model = build_cooperative("pointpillars", "fcooper", "tiny", bev_size_m=BEV)
    pts, gt = _scene(gen)
    poses = torch.tensor([[[0.0, 0.0, 0.0], [6.0, -2.0, 0.3]]])
    clouds = [[pts, _to_frame(pts, poses[0, 1])]]
    assert torch.allclose(transform_points(clouds[0][1], poses[0, 1]), pts, atol=1e-4)
    valid = torch.ones(1, 2, dtype=torch.bool)
    grid = BevGrid(BEV, 256)
    dyn = _rasterise(gt, grid)[None]
    y = torch.as_tensor(grid.cell_centres()[..., 1], dtype=torch.float32)[None]
    sta = static_target(y.abs() < 6.0, y.abs() < 0.4)
    targets = AnchorTargetAssigner(model.anchors)(gt)
    assert (targets.labels == 1).sum() >= 2

    opt = torch.optim.Adam(model.parameters(), lr=5e-3)
    losses = []
    start = time.perf_counter()
    for _ in range(150):  # ~70 steps needed (about 0.07 s each on one thread)
        out = model(clouds, poses, valid)
        det = detection_loss(out["det_cls"], out["det_reg"], targets.labels[None], targets.reg[None])
        loss = segmentation_loss(out["dynamic"], dyn) + segmentation_loss(out["static"], sta) + det["total"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if losses[-1] * 10 <= losses[0]:
            break
    assert losses[-1] * 10 <= losses[0], f"loss {losses[0]:.3f} -> {losses[-1]:.3f} in {len(losses)} steps"
    assert time.perf_counter() - start < 120
