"""Training losses: segmentation cross entropy (Table A2 heads) and anchor detection losses (Sec. 3.3).

Detection follows PointPillars: sigmoid focal loss (alpha 0.25, gamma 2) on the anchors that are
not ignored, smooth-L1 on the box codes of positive anchors, both normalised by the positives.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from models.heads import flatten_det

IGNORE_INDEX = -100


def static_target(road: Tensor, lane: Tensor) -> Tensor:
    """Road/lane masks [B, H, W] -> class map (0 background, 1 road, 2 lane); lane takes precedence."""
    t = torch.zeros(road.shape, dtype=torch.long, device=road.device)
    t[road.bool()] = 1
    t[lane.bool()] = 2
    return t


def dynamic_target(vehicle: Tensor, ignore: Tensor | None = None) -> Tensor:
    """Vehicle mask [B, H, W] -> class map (0 background, 1 vehicle); `ignore` cells (e.g. invisible
    vehicles, OPV2V protocol) get IGNORE_INDEX."""
    t = vehicle.bool().long()
    if ignore is not None:
        t = t.masked_fill(ignore.bool(), IGNORE_INDEX)
    return t


def segmentation_loss(logits: Tensor, target: Tensor, class_weights: Tensor | None = None) -> Tensor:
    """Pixel-wise cross entropy: logits [B, K, H, W], target [B, H, W] long (IGNORE_INDEX skipped)."""
    return F.cross_entropy(logits, target, weight=class_weights, ignore_index=IGNORE_INDEX)


def sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """Element-wise focal loss (Lin et al. 2017) for binary targets in {0, 1}."""
    p = torch.sigmoid(logits)
    ce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = p * targets + (1 - p) * (1 - targets)
    a_t = alpha * targets + (1 - alpha) * (1 - targets)
    return a_t * (1 - p_t) ** gamma * ce


def detection_loss(
    cls: Tensor, reg: Tensor, labels: Tensor, reg_targets: Tensor, reg_weight: float = 2.0, beta: float = 1.0 / 9.0
) -> dict[str, Tensor]:
    """cls [B, A, H, W], reg [B, A*6, H, W]; labels [B, K] (1/0/-1 ignore), reg_targets [B, K, 6]
    (K = H*W*A in make_anchors order) -> {"cls", "reg", "total"}."""
    cls_f, reg_f = flatten_det(cls, reg)  # [B, K], [B, K, 6]
    pos = labels == 1
    care = labels >= 0
    n_pos = pos.sum().clamp(min=1).to(cls_f.dtype)
    focal = sigmoid_focal_loss(cls_f, pos.to(cls_f.dtype))
    cls_loss = torch.where(care, focal, torch.zeros_like(focal)).sum() / n_pos
    if pos.any():
        reg_loss = F.smooth_l1_loss(reg_f[pos], reg_targets[pos], beta=beta, reduction="sum") / n_pos
    else:
        reg_loss = reg_f.sum() * 0.0
    return {"cls": cls_loss, "reg": reg_loss, "total": cls_loss + reg_weight * reg_loss}


def dense_focal_loss(logits: Tensor, target: Tensor, alpha: float = 0.5, gamma: float = 2.0) -> Tensor:
    """Focal loss (Lin et al. 2017) over a 2-class segmentation: logits [B, 2, H, W], target [B, H, W]
    in {0, 1, IGNORE_INDEX}; summed over the cells that count and normalised by the positive cells
    (as the detection focal loss), so that a sparse class is not drowned by the background."""
    care = target != IGNORE_INDEX
    t = target.clamp(min=0)
    logp = torch.log_softmax(logits, dim=1).gather(1, t[:, None]).squeeze(1)  # log p_t [B, H, W]
    a_t = torch.where(t == 1, torch.full_like(logp, alpha), torch.full_like(logp, 1 - alpha))
    loss = -a_t * (1 - logp.exp()) ** gamma * logp
    n_pos = ((t == 1) & care).sum().clamp(min=1).to(loss.dtype)
    return torch.where(care, loss, torch.zeros_like(loss)).sum() / n_pos
