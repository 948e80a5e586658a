"""Rotated BEV boxes: corners, exact IoU by convex-polygon intersection, rotated NMS.

A box is (x, y, l, w, yaw): centre, length along the heading, width, heading (rad, CCW from +x).
Used by the LiDAR detection head (CoBEVT supp. Sec. 3.3), late fusion and the AP metrics.

The intersection of two convex quadrilaterals is the convex hull of (corners of A inside B)
+ (corners of B inside A) + (edge-edge crossings); all 24 candidates are computed for every
pair at once, sorted by angle about their centroid and integrated with the shoelace formula.
Pairs whose circumscribed circles do not touch are skipped (IoU 0) so that sparse scenes
with a few hundred boxes stay cheap.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

# Unit-box corners, counter-clockwise starting front-left (same order as v2vsim.world.geometry.box_corners).
_UNIT_CORNERS = ((0.5, 0.5), (-0.5, 0.5), (-0.5, -0.5), (0.5, -0.5))


def box_corners(boxes: Tensor) -> Tensor:
    """[..., 5] (x, y, l, w, yaw) -> [..., 4, 2] corners, CCW from front-left."""
    unit = boxes.new_tensor(_UNIT_CORNERS)  # [4, 2]
    local = unit * boxes[..., None, 2:4]  # [..., 4, 2]
    c, s = torch.cos(boxes[..., 4])[..., None], torch.sin(boxes[..., 4])[..., None]  # [..., 1]
    x = local[..., 0] * c - local[..., 1] * s + boxes[..., None, 0]
    y = local[..., 0] * s + local[..., 1] * c + boxes[..., None, 1]
    return torch.stack([x, y], dim=-1)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _inside(points: Tensor, boxes: Tensor, tol: float) -> Tensor:
    """points [K, 4, 2] tested against boxes [K, 5] -> [K, 4] bool (boundary counts as inside)."""
    rel = points - boxes[:, None, :2]
    c, s = torch.cos(boxes[:, 4])[:, None], torch.sin(boxes[:, 4])[:, None]
    u = rel[..., 0] * c + rel[..., 1] * s
    v = -rel[..., 0] * s + rel[..., 1] * c
    half_l = boxes[:, None, 2] * 0.5 * (1 + tol) + tol
    half_w = boxes[:, None, 3] * 0.5 * (1 + tol) + tol
    return (u.abs() <= half_l) & (v.abs() <= half_w)


def intersection_area_pairs(a: Tensor, b: Tensor, tol: float = 1e-9) -> Tensor:
    """Intersection area of paired boxes a[k], b[k]: [K, 5], [K, 5] -> [K] (float64 inside)."""
    a, b = a.double(), b.double()
    ca, cb = box_corners(a), box_corners(b)  # [K, 4, 2]
    in_a = _inside(ca, b, tol)  # corners of A inside B
    in_b = _inside(cb, a, tol)
    # Edge crossings: p + t r (edge of A) meets q + u s (edge of B); [K, 4, 4].
    p, r = ca[:, :, None, :], (ca.roll(-1, dims=1) - ca)[:, :, None, :]
    q, s = cb[:, None, :, :], (cb.roll(-1, dims=1) - cb)[:, None, :, :]
    denom = _cross(r, s)  # [K, 4, 4]
    qp = q - p
    safe = torch.where(denom.abs() > tol, denom, torch.ones_like(denom))
    t = _cross(qp, s) / safe
    u = _cross(qp, r) / safe
    hit = (denom.abs() > tol) & (t >= -tol) & (t <= 1 + tol) & (u >= -tol) & (u <= 1 + tol)
    cross_pts = (p + t[..., None] * r).reshape(-1, 16, 2)
    pts = torch.cat([ca, cb, cross_pts], dim=1)  # [K, 24, 2]
    valid = torch.cat([in_a, in_b, hit.reshape(-1, 16)], dim=1)  # [K, 24]
    n = valid.sum(1)  # [K]
    w = valid.double()
    centroid = (pts * w[..., None]).sum(1) / n.clamp(min=1)[:, None]  # [K, 2]
    rel = pts - centroid[:, None, :]
    ang = torch.atan2(rel[..., 1], rel[..., 0])
    ang = torch.where(valid, ang, torch.full_like(ang, 10.0))  # invalid sort last
    order = ang.argsort(dim=1)
    rel = rel.gather(1, order[..., None].expand(-1, -1, 2))
    valid = valid.gather(1, order)
    # Invalid tail points repeat the first vertex: they add zero area to the closed polygon.
    rel = torch.where(valid[..., None], rel, rel[:, :1, :])
    area = 0.5 * _cross(rel, rel.roll(-1, dims=1)).sum(1).abs()
    return torch.where(n >= 3, area, torch.zeros_like(area))


def rotated_iou_pairs(a: Tensor, b: Tensor) -> Tensor:
    """IoU of paired rotated boxes: [K, 5], [K, 5] -> [K] (dtype of a)."""
    if a.shape[0] == 0:
        return a.new_zeros(0)
    inter = intersection_area_pairs(a, b)
    area_a = a[:, 2].double() * a[:, 3].double()
    area_b = b[:, 2].double() * b[:, 3].double()
    union = (area_a + area_b - inter).clamp(min=1e-12)
    return (inter / union).clamp(0.0, 1.0).to(a.dtype)


def rotated_iou_matrix(a: Tensor, b: Tensor, chunk: int = 65536) -> Tensor:
    """Rotated BEV IoU of every box in a [N, 5] with every box in b [M, 5] -> [N, M].

    Boxes are (x, y, l, w, yaw). Only pairs whose circumscribed circles overlap are
    evaluated (the rest are exactly 0), in chunks of `chunk` pairs.
    """
    a, b = a[:, :5], b[:, :5]
    out = a.new_zeros(a.shape[0], b.shape[0])
    if a.shape[0] == 0 or b.shape[0] == 0:
        return out
    ra = 0.5 * torch.hypot(a[:, 2], a[:, 3])  # [N]
    rb = 0.5 * torch.hypot(b[:, 2], b[:, 3])  # [M]
    dist = torch.cdist(a[:, None, :2].double().squeeze(1), b[:, :2].double())  # [N, M]
    ii, jj = torch.nonzero(dist <= (ra[:, None] + rb[None, :]).double() + 1e-6, as_tuple=True)
    for start in range(0, ii.numel(), chunk):
        i, j = ii[start : start + chunk], jj[start : start + chunk]
        out[i, j] = rotated_iou_pairs(a[i], b[j])
    return out


def rotated_iou_matrices(pairs: list[tuple[Tensor, Tensor]], chunk: int = 65536) -> list[Tensor]:
    """rotated_iou_matrix of many (a [N_i, 5], b [M_i, 5]) pairs at once -> [N_i, M_i] each: the candidate pairs of
    all of them go through rotated_iou_pairs together, so a run's AP over hundreds of frames pays its many small
    tensor operations once rather than once a frame."""
    outs, ii, jj, ia, jb = [], [], [], [], []
    for n, (a, b) in enumerate(pairs):
        a, b = a[:, :5], b[:, :5]
        outs.append(a.new_zeros(a.shape[0], b.shape[0]))
        if a.shape[0] == 0 or b.shape[0] == 0:
            continue
        ra = 0.5 * torch.hypot(a[:, 2], a[:, 3])  # [N]
        rb = 0.5 * torch.hypot(b[:, 2], b[:, 3])  # [M]
        dist = torch.cdist(a[:, :2].double(), b[:, :2].double())  # [N, M]
        i, j = torch.nonzero(dist <= (ra[:, None] + rb[None, :]).double() + 1e-6, as_tuple=True)
        ii.append(torch.full_like(i, n))
        jj.append(i * b.shape[0] + j)  # flat index into the pair's output
        ia.append(a[i])
        jb.append(b[j])
    if not ii:
        return outs
    which, flat, boxes_a, boxes_b = torch.cat(ii), torch.cat(jj), torch.cat(ia), torch.cat(jb)
    iou = torch.cat([rotated_iou_pairs(boxes_a[s : s + chunk], boxes_b[s : s + chunk])
                     for s in range(0, boxes_a.shape[0], chunk)])
    for n in torch.unique(which).tolist():
        sel = which == n
        outs[n].view(-1)[flat[sel]] = iou[sel].to(outs[n].dtype)
    return outs


def rotated_nms(boxes: Tensor, scores: Tensor, iou_threshold: float, max_out: int | None = None) -> Tensor:
    """Greedy rotated NMS: boxes [N, >=5], scores [N] -> kept indices [K] by descending score.

    A box is dropped when its IoU with an already kept, higher-scoring box exceeds the threshold.
    """
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = scores.argsort(descending=True)
    iou = rotated_iou_matrix(boxes[order, :5], boxes[order, :5]).cpu().numpy() > iou_threshold  # [N, N]
    n = order.numel()
    suppressed = np.zeros(n, dtype=bool)
    keep: list[int] = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        if max_out is not None and len(keep) >= max_out:
            break
        suppressed |= iou[i]
    return order[torch.as_tensor(keep, dtype=torch.long, device=order.device)]
