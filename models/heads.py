"""Decoder and output heads (CoBEVT supp. Table A2 decoder rows; Sec. 3.3 detection head).

Decoder: 3 x [bilinear x2, Conv3x3, BN, ReLU]: C x 32 x 32 -> c1 x 64 x 64 -> c2 x 128 x 128 -> c3 x 256 x 256
(paper c = 128/64/32). A finer fusion grid (the LiDAR preset's 64 x 64, or 128 x 128) skips the first
upsamplings (scale 1: the conv runs at the input resolution), so every grid ends at the same 256 x 256
segmentation and 128 x 128 detection maps, and the decoder keeps its three conv stages and sizes.
Dynamic head Conv1x1 -> 2 (background, vehicle), static head Conv1x1 -> 3
(background, road, lane), softmax. One shared decoder feeds both heads (the paper trains two
separate models that differ only in the last layer; the split is a training choice).
Detection (LiDAR): two 3x3 convs (cls, reg) on the decoder's 128 x 128 stage, 2 anchors per cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.nms import rotated_iou_pairs, rotated_nms
from models.presets import get_preset

MAX_DETECTIONS = 100  # boxes decode_detections keeps per item (late fusion ships at most this many)
BOX_CODE_SIZE = 6  # (dx/d, dy/d, log l/la, log w/wa, sin 2dyaw, cos 2dyaw)


def decoder_scales(in_cells: int, out_cells: int = 256, stages: int = 3) -> tuple[int, ...]:
    """Upsampling factor of each decoder stage (1 or 2, the x2 ones last) from in_cells to out_cells:
    32 -> 256: (2, 2, 2); 64 -> 256: (1, 2, 2); 128 -> 256: (1, 1, 2)."""
    ups = round(math.log2(out_cells / in_cells)) if in_cells > 0 else -1
    if ups < 0 or ups > stages or in_cells * 2**ups != out_cells:
        allowed = ", ".join(str(out_cells >> k) for k in range(stages + 1))
        raise ValueError(f"a {in_cells} x {in_cells} feature map cannot be decoded to {out_cells} x {out_cells} "
                         f"with {stages} x2 upsamplings; allowed: {allowed}")
    return (1,) * (stages - ups) + (2,) * ups


class BevDecoder(nn.Module):
    """Table A2 decoder: 3 x [bilinear upsample x2, Conv3x3, BN, ReLU]; returns every stage. `scales`
    (decoder_scales) replaces the first upsamplings by the identity for a finer input grid."""

    def __init__(self, in_channels: int, channels: tuple[int, int, int] = (128, 64, 32),
                 scales: tuple[int, ...] = (2, 2, 2)) -> None:
        super().__init__()
        stages, cin = [], in_channels
        for c, scale in zip(channels, scales, strict=True):
            stages.append(
                nn.Sequential(
                    nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False) if scale == 2 else nn.Identity(),
                    nn.Conv2d(cin, c, 3, padding=1, bias=False),
                    nn.BatchNorm2d(c),
                    nn.ReLU(inplace=True),
                )
            )
            cin = c
        self.stages = nn.ModuleList(stages)
        self.channels = tuple(channels)
        self.scales = tuple(scales)

    def forward(self, x: Tensor) -> list[Tensor]:
        """[B, C, F, F] -> [[B, c1, s1 F, ..], [B, c2, s1 s2 F, ..], [B, c3, 256, 256]] (F = 32: 64, 128, 256)."""
        outs = []
        for stage in self.stages:
            x = stage(x)
            outs.append(x)
        return outs


def make_anchors(
    cells: int, bev_size_m: float, size: tuple[float, float] = (4.5, 1.9), yaws: tuple[float, ...] = (0.0, math.pi / 2)
) -> Tensor:
    """[cells * cells * A, 5] anchors (x, y, l, w, yaw) at BevGrid cell centres, order (row, col, anchor)."""
    res = bev_size_m / cells
    coord = bev_size_m / 2 - (torch.arange(cells, dtype=torch.float32) + 0.5) * res
    xs, ys = torch.meshgrid(coord, coord, indexing="ij")  # x along rows, y along columns
    a = len(yaws)
    out = torch.empty(cells, cells, a, 5)
    out[..., 0] = xs[..., None]
    out[..., 1] = ys[..., None]
    out[..., 2] = size[0]
    out[..., 3] = size[1]
    out[..., 4] = torch.tensor(yaws, dtype=torch.float32)
    return out.reshape(-1, 5)


def _half_turn(a: Tensor) -> Tensor:
    """Wrap to [-pi/2, pi/2): a BEV box is the same box after a half turn."""
    return torch.remainder(a + math.pi / 2, math.pi) - math.pi / 2


def encode_boxes(boxes: Tensor, anchors: Tensor) -> Tensor:
    """[N, 5] boxes vs. [N, 5] anchors -> [N, 6] codes (dx/d, dy/d, log l/la, log w/wa, sin 2dyaw, cos 2dyaw).

    d = anchor diagonal (PointPillars/SECOND encoding); heading is regressed modulo pi through the
    doubled angle, so the code is continuous and unambiguous for a symmetric box.
    """
    d = torch.hypot(anchors[:, 2], anchors[:, 3])
    dyaw = _half_turn(boxes[:, 4] - anchors[:, 4])
    return torch.stack(
        [
            (boxes[:, 0] - anchors[:, 0]) / d,
            (boxes[:, 1] - anchors[:, 1]) / d,
            torch.log(boxes[:, 2] / anchors[:, 2]),
            torch.log(boxes[:, 3] / anchors[:, 3]),
            torch.sin(2 * dyaw),
            torch.cos(2 * dyaw),
        ],
        dim=1,
    )


def decode_boxes(codes: Tensor, anchors: Tensor) -> Tensor:
    """Inverse of encode_boxes: [N, 6] codes, [N, 5] anchors -> [N, 5] boxes (yaw in [-pi, pi))."""
    d = torch.hypot(anchors[:, 2], anchors[:, 3])
    yaw = anchors[:, 4] + 0.5 * torch.atan2(codes[:, 4], codes[:, 5])
    return torch.stack(
        [
            anchors[:, 0] + codes[:, 0] * d,
            anchors[:, 1] + codes[:, 1] * d,
            anchors[:, 2] * torch.exp(codes[:, 2].clamp(max=4.0)),
            anchors[:, 3] * torch.exp(codes[:, 3].clamp(max=4.0)),
            torch.remainder(yaw + math.pi, 2 * math.pi) - math.pi,
        ],
        dim=1,
    )


class DetectionHead(nn.Module):
    """Sec. 3.3: "two 3x3 convolution layers for classification and regression"; A anchors per cell."""

    def __init__(self, in_channels: int, num_anchors: int = 2) -> None:
        super().__init__()
        self.num_anchors = num_anchors
        self.cls = nn.Conv2d(in_channels, num_anchors, 3, padding=1)
        self.reg = nn.Conv2d(in_channels, num_anchors * BOX_CODE_SIZE, 3, padding=1)
        nn.init.constant_(self.cls.bias, -math.log((1 - 0.01) / 0.01))  # focal-loss prior p = 0.01
        nn.init.normal_(self.reg.weight, std=1e-3)
        nn.init.zeros_(self.reg.bias)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """[B, c, H, W] -> cls [B, A, H, W], reg [B, A*6, H, W]."""
        return self.cls(x), self.reg(x)


def flatten_det(cls: Tensor, reg: Tensor) -> tuple[Tensor, Tensor]:
    """cls [B, A, H, W], reg [B, A*6, H, W] -> [B, H*W*A], [B, H*W*A, 6] in make_anchors order."""
    b, a, h, w = cls.shape
    cls_f = cls.permute(0, 2, 3, 1).reshape(b, h * w * a)
    reg_f = reg.view(b, a, BOX_CODE_SIZE, h, w).permute(0, 3, 4, 1, 2).reshape(b, h * w * a, BOX_CODE_SIZE)
    return cls_f, reg_f


def decode_detections(
    cls: Tensor,
    reg: Tensor,
    anchors: Tensor,
    score_threshold: float = 0.3,
    top_k: int = MAX_DETECTIONS,
    nms_iou: float | None = 0.15,
    pre_nms: int = 500,
) -> list[Tensor]:
    """Head outputs -> per batch item [K, 6] boxes (x, y, l, w, yaw, score) in the ego body frame.

    Sigmoid scores, score threshold, the `pre_nms` best, rotated NMS (if nms_iou), then the `top_k` best.
    """
    cls_f, reg_f = flatten_det(cls, reg)
    out = []
    for b in range(cls_f.shape[0]):
        scores = torch.sigmoid(cls_f[b])
        idx = torch.nonzero(scores >= score_threshold).squeeze(1)
        idx = idx[scores[idx].argsort(descending=True)[:pre_nms]]
        boxes = decode_boxes(reg_f[b, idx], anchors[idx].to(reg_f))
        s = scores[idx]
        if nms_iou is not None:
            keep = rotated_nms(boxes, s, nms_iou, max_out=top_k)
            boxes, s = boxes[keep], s[keep]
        out.append(torch.cat([boxes, s[:, None]], dim=1)[:top_k])
    return out


@dataclass
class AnchorTargets:
    """labels [K] (1 positive, 0 negative, -1 ignored), reg [K, 6] codes (valid where labels == 1)."""

    labels: Tensor
    reg: Tensor


class AnchorTargetAssigner:
    """Anchor-to-GT matching by rotated BEV IoU (PointPillars car: pos >= 0.6, neg < 0.45).

    Every GT box also claims its best anchor (if it overlaps any). Only anchor/GT pairs whose
    circumscribed circles overlap are evaluated.
    """

    def __init__(self, anchors: Tensor, pos_iou: float = 0.6, neg_iou: float = 0.45) -> None:
        self.anchors = anchors
        self.pos_iou = pos_iou
        self.neg_iou = neg_iou

    def __call__(self, gt: Tensor) -> AnchorTargets:
        """gt: [G, >=5] boxes (x, y, l, w, yaw) in the ego body frame."""
        anchors = self.anchors.to(gt.device)
        k = anchors.shape[0]
        labels = torch.zeros(k, device=gt.device)
        reg = torch.zeros(k, BOX_CODE_SIZE, device=gt.device)
        if gt.shape[0] == 0:
            return AnchorTargets(labels, reg)
        gt = gt[:, :5].to(anchors.dtype)
        ra = 0.5 * torch.hypot(anchors[:, 2], anchors[:, 3])
        rg = 0.5 * torch.hypot(gt[:, 2], gt[:, 3])
        dist = torch.cdist(anchors[:, :2], gt[:, :2])  # [K, G]
        ai, gi = torch.nonzero(dist < ra[:, None] + rg[None, :], as_tuple=True)
        iou = torch.zeros(k, gt.shape[0], device=gt.device)
        iou[ai, gi] = rotated_iou_pairs(anchors[ai], gt[gi])
        best_iou, best_gt = iou.max(dim=1)  # per anchor
        labels[(best_iou >= self.neg_iou) & (best_iou < self.pos_iou)] = -1
        pos = best_iou >= self.pos_iou
        gt_best_iou, gt_best_anchor = iou.max(dim=0)  # per GT
        has = gt_best_iou > 0
        forced = gt_best_anchor[has]  # each GT's best anchor is positive for that GT
        pos[forced] = True
        best_gt[forced] = torch.nonzero(has).squeeze(1)
        labels[pos] = 1
        reg[pos] = encode_boxes(gt[best_gt[pos]], anchors[pos])
        return AnchorTargets(labels, reg)


def segmentation_probabilities(dynamic_logits: Tensor, static_logits: Tensor | None = None) -> dict[str, Tensor]:
    """Logits -> per-class probability maps [B, H, W]: vehicle; road = p_road + p_lane; lane = p_lane."""
    out = {"vehicle": torch.softmax(dynamic_logits, dim=1)[:, 1]}
    if static_logits is not None:
        p = torch.softmax(static_logits, dim=1)
        out["road"] = p[:, 1] + p[:, 2]
        out["lane"] = p[:, 2]
    return out


class BevHeads(nn.Module):
    """Decoder + dynamic/static segmentation heads (+ LiDAR detection head on the 128 x 128 stage) for an
    in_cells x in_cells fused map; `seg_cells`: the segmentation grid (the detection grid is half of it)."""

    def __init__(
        self,
        in_channels: int,
        decoder_channels: tuple[int, int, int] = (128, 64, 32),
        detection: bool = False,
        num_anchors: int = 2,
        in_cells: int = 32,
        seg_cells: int = 256,
    ) -> None:
        super().__init__()
        self.in_cells, self.seg_cells, self.det_cells = in_cells, seg_cells, seg_cells // 2
        self.decoder = BevDecoder(in_channels, decoder_channels, decoder_scales(in_cells, seg_cells))
        self.dynamic = nn.Conv2d(decoder_channels[2], 2, 1)  # background, vehicle
        # Focal-loss prior (Lin et al. 2017, Sec. 4.1): start at p(vehicle) = 0.01 so that the decoder
        # learns to light up vehicles. From p = 0.5 it found the shortcut of all-dead (ReLU) features on
        # vehicle cells, where p stays at softmax(bias) < 0.5 for good (vehicle IoU 0 at AP50 0.79).
        with torch.no_grad():
            self.dynamic.bias.copy_(torch.tensor([0.0, -math.log((1 - 0.01) / 0.01)]))
        self.static = nn.Conv2d(decoder_channels[2], 3, 1)  # background, road, lane
        self.detection = DetectionHead(decoder_channels[1], num_anchors) if detection else None

    def forward(self, fused: Tensor) -> dict[str, Tensor]:
        """[B, C, F, F] -> {"dynamic": [B, 2, S, S], "static": [B, 3, S, S] (logits, S = seg_cells),
        "det_cls": [B, A, S/2, S/2], "det_reg": [B, A*6, S/2, S/2] (LiDAR only)}."""
        s1, s2, s3 = self.decoder(fused)
        out = {"dynamic": self.dynamic(s3), "static": self.static(s3)}
        if self.detection is not None:
            out["det_cls"], out["det_reg"] = self.detection(s2)
        return out

    def segmentation(self, fused: Tensor) -> dict[str, Tensor]:
        """forward's "dynamic" and "static" alone, without the detection head (for a reader of the maps only)."""
        s3 = self.decoder(fused)[-1]
        return {"dynamic": self.dynamic(s3), "static": self.static(s3)}


    def for_inference(self) -> BevHeads:
        """The same function, cheaper on a CPU (outputs equal to ~1e-6): each decoder BatchNorm folded
        into its conv, and every conv in channels-last layout (NHWC: the 3x3 conv at 8F x 8F, most of
        the decoder's time, runs ~1.5x faster here). For the frozen models of a run; not for training
        (the folded state_dict has no BatchNorm keys)."""
        self.eval()
        for stage in self.decoder.stages:
            conv, bn = stage[1], stage[2]
            if isinstance(bn, nn.BatchNorm2d):
                stage[1] = torch.nn.utils.fusion.fuse_conv_bn_eval(conv, bn)
                stage[2] = nn.Identity()
        return self.to(memory_format=torch.channels_last)


def build_bev_heads(modality: str, preset: str, in_cells: int | None = None) -> BevHeads:
    """Heads of `preset` for an in_cells x in_cells fused map (default: the preset's LiDAR grid); the
    detection head only for modality "lidar"."""
    if modality not in ("lidar", "camera"):
        raise ValueError(f"unknown modality {modality!r}; allowed: camera, lidar")
    p = get_preset(preset)
    return BevHeads(p.channels, p.decoder_channels, detection=modality == "lidar", num_anchors=len(p.anchor_yaws),
                    in_cells=in_cells or p.cells, seg_cells=p.seg_cells)


def resize_logits(logits: Tensor, cells: int) -> Tensor:
    """Bilinear resize of [B, K, H, W] logits to cells x cells (e.g. when the scenario grid differs)."""
    if logits.shape[-1] == cells and logits.shape[-2] == cells:
        return logits
    return F.interpolate(logits, size=(cells, cells), mode="bilinear", align_corners=False)
