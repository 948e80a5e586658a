"""Move BEV maps, points and boxes from a sender's body frame into the ego body frame.

Convention (v2vsim.world.geometry.BevGrid): row r, column c of an S x S metre grid with H x W cells
has body-frame centre x = S/2 - (r + 0.5) S/H, y = S/2 - (c + 0.5) S/W.

grid_sample's normalised coordinates (align_corners=False) put the centre of column c at
u = (2c + 1)/W - 1 and of row r at v = (2r + 1)/H - 1, hence for a square S x S area

    (u, v) = (-2 y / S, -2 x / S)  =  P p,   P = (2/S) J,   J = [[0, -1], [-1, 0]]   (J^2 = I).

A sender with pose (dx, dy, dyaw) in the ego body frame maps its point p_s to
p_e = R(dyaw) p_s + t. For every ego cell we sample the sender map at
p_s = R^T (p_e - t), i.e. n_s = P R^T P^-1 n_e - P R^T t. Because J R^T J = R,

    theta = [[ cos, -sin, (2/S)(cos*dy - sin*dx) ],
             [ sin,  cos, (2/S)(cos*dx + sin*dy) ]]        (cos, sin of dyaw)

which is what affine_grid expects (output normalised coords -> input normalised coords).
Checks: a sender one cell ahead (dx = S/H) gives v_s = v_e + 2/H, so ego row r reads source
row r + 1: the sender's centre feature lands one row up (closer to the front). dyaw = +90 deg
maps the sender's front (its +x) onto the ego's +y, the ego's left (columns near 0).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def se2_to_theta(rel_poses: Tensor, bev_size_m: float) -> Tensor:
    """[..., 3] sender poses (dx, dy, dyaw) in the ego body frame -> [..., 2, 3] affine_grid thetas."""
    dx, dy, yaw = rel_poses.unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    k = 2.0 / bev_size_m
    row0 = torch.stack([c, -s, k * (c * dy - s * dx)], dim=-1)
    row1 = torch.stack([s, c, k * (c * dx + s * dy)], dim=-1)
    return torch.stack([row0, row1], dim=-2)


def warp_to_ego(
    features: Tensor, rel_poses: Tensor, bev_size_m: float = 100.0, mode: str = "bilinear"
) -> tuple[Tensor, Tensor]:
    """Warp sender BEV maps into the ego grid.

    features: [L, C, H, W] or [B, L, C, H, W] in each sender's own BEV grid (same extent S).
    rel_poses: [L, 3] or [B, L, 3] (dx, dy, dyaw) of each sender in the ego body frame; the ego
    itself is (0, 0, 0) and is returned unchanged.
    Returns (warped like features, mask [L, H, W] / [B, L, H, W] bool: the cell centre sampled
    inside the sender's map). Sampling outside gives zeros.
    """
    lead = features.shape[:-3]
    c, h, w = features.shape[-3:]
    if rel_poses.shape[:-1] != lead or rel_poses.shape[-1] != 3:
        raise ValueError(f"rel_poses {tuple(rel_poses.shape)} does not match features {tuple(features.shape)}")
    flat = features.reshape(-1, c, h, w)
    theta = se2_to_theta(rel_poses.reshape(-1, 3).to(flat.dtype), bev_size_m)  # [N, 2, 3]
    grid = F.affine_grid(theta, [flat.shape[0], c, h, w], align_corners=False)  # [N, H, W, 2]
    warped = F.grid_sample(flat, grid, mode=mode, padding_mode="zeros", align_corners=False)
    eps = 1e-6
    mask = (grid.abs() <= 1.0 + eps).all(dim=-1)  # [N, H, W]
    return warped.reshape(features.shape), mask.reshape(*lead, h, w)


def transform_points(points: Tensor, rel_pose: Tensor) -> Tensor:
    """[P, >=2] xy (+ any extra columns kept) in the sender frame -> same in the ego frame."""
    dx, dy, yaw = rel_pose.to(points.dtype).unbind(-1)
    c, s = torch.cos(yaw), torch.sin(yaw)
    x = c * points[:, 0] - s * points[:, 1] + dx
    y = s * points[:, 0] + c * points[:, 1] + dy
    return torch.cat([x[:, None], y[:, None], points[:, 2:]], dim=1)


def transform_boxes(boxes: Tensor, rel_pose: Tensor) -> Tensor:
    """[N, >=5] boxes (x, y, l, w, yaw, ...) in the sender frame -> ego frame (yaw wrapped to [-pi, pi))."""
    out = transform_points(boxes, rel_pose)
    yaw = out[:, 4] + rel_pose[2].to(boxes.dtype)
    out[:, 4] = torch.remainder(yaw + torch.pi, 2 * torch.pi) - torch.pi
    return out
