"""Training losses of a stage's outputs against a dataset batch: the perception loss (on the vehicles of
the stage's target) and DiscoNet's distillation loss; the per-term losses themselves are models.losses."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from models.heads import AnchorTargetAssigner
from models.losses import (
    IGNORE_INDEX,
    dense_focal_loss,
    detection_loss,
    dynamic_target,
    segmentation_loss,
    static_target,
)


def perception_loss(out: dict[str, Tensor], batch: dict, target: str, assigner: AnchorTargetAssigner | None,
                    lane_weight: float = 1.0) -> dict[str, Tensor]:
    """Focal (dynamic) + CE (static; the lane class weighted by `lane_weight`) + anchor detection loss;
    `target` "self" or "coop"."""
    dev = out["dynamic"].device
    vehicle = (batch["visible_self"] if target == "self" else batch["vehicle"]).to(dev)
    ignore = batch["dynamic"].to(dev) & ~vehicle
    static = static_target(batch["road"].to(dev), batch["lane"].to(dev))
    if "outside" in batch:  # cells a yaw-augmented sample turned in from outside the recording
        outside = batch["outside"].to(dev)
        ignore = ignore | outside
        static = static.masked_fill(outside, IGNORE_INDEX)
    losses = {
        "dyn": dense_focal_loss(out["dynamic"], dynamic_target(vehicle, ignore)),
        "static": segmentation_loss(out["static"], static, torch.tensor([1.0, 1.0, lane_weight], device=dev)),
    }
    if assigner is not None and "det_cls" in out:
        pos_key, hid_key = ("boxes_self", "boxes_self_hidden") if target == "self" else ("boxes", "boxes_hidden")
        labels, regs = [], []
        for pos, hid in zip(batch[pos_key], batch[hid_key], strict=True):
            t = assigner(pos.to(dev))
            h = assigner(hid.to(dev)).labels
            lab = t.labels.clone()
            lab[(h != 0) & (lab != 1)] = -1  # anchors on vehicles nobody saw: neither positive nor negative
            labels.append(lab)
            regs.append(t.reg)
        losses["det"] = detection_loss(out["det_cls"], out["det_reg"], torch.stack(labels), torch.stack(regs))["total"]
    losses["total"] = sum(losses.values())
    return losses


def distill_loss(student: Tensor, teacher: Tensor) -> Tensor:
    """Mean per-cell KL(teacher || student) of the channel distributions, [B, C, F, F] each."""
    kl = F.kl_div(F.log_softmax(student, dim=1), F.log_softmax(teacher, dim=1), log_target=True, reduction="none")
    return kl.sum(dim=1).mean()
