"""The CAV side of perception: one CAV's sensor frame encoded into BEV features, and its own decoded
outputs (the late-fusion message, the confidence a CAV ranks its cells by). Each model runs on the device its
weights sit on (v2vsim.perception.device); what these functions return is numpy on the host."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from models.heads import decode_detections, segmentation_probabilities
from v2vsim.config import Scenario
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.precision import Precision, autocast
from v2vsim.sensors.sensing import SensorFrame


def encoder_inputs(sf: SensorFrame, sc: Scenario, modality: str | None = None
                   ) -> list[Tensor] | tuple[Tensor, Tensor, Tensor]:
    """A SensorFrame as the encoder takes it: body-frame points, or (images, intrinsics, extrinsics).
    `modality`: the CAV's sensor (default perception.modality; a mixed fleet's CAV: its type's)."""
    if (modality or sc.perception.modality) == "lidar":
        return [torch.from_numpy(body_frame_points(sf, sc))]
    cams = sf.cameras
    images = torch.from_numpy(cams.images).permute(0, 3, 1, 2).float().div(255.0)[None]  # [1, M, 3, h, w]
    intr = torch.from_numpy(cams.rig.intrinsics).float()[None]
    extr = torch.from_numpy(cams.rig.extrinsics).float()[None]
    return images, intr, extr


def body_frame_points(sf: SensorFrame, sc: Scenario) -> np.ndarray:
    """LiDAR-frame points (origin at the sensor) moved to the body frame (origin on the ground)."""
    pts = sf.lidar.points.copy()
    pts[:, 2] += sc.sensors.lidar.height_m
    return pts


@torch.no_grad()
def encode(encoder: nn.Module, sf: SensorFrame, sc: Scenario, precision: Precision = "fp32",
           modality: str | None = None) -> np.ndarray:
    """[C, F, F] float32 BEV features of one CAV in its own frame; `modality`: as for encoder_inputs."""
    if (modality or sc.perception.modality) == "lidar":
        return encode_points(encoder, body_frame_points(sf, sc), precision)
    device = model_device(encoder)
    with autocast(precision, device.type):
        return to_host(encoder(*(t.to(device) for t in encoder_inputs(sf, sc, "camera")))[0].float())


@torch.no_grad()
def encode_points(encoder: nn.Module, points: np.ndarray, precision: Precision = "fp32") -> np.ndarray:
    """A LiDAR encoder on one body-frame cloud [P, 4] -> [C, F, F] float32 features."""
    device = model_device(encoder)
    cloud = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)).to(device)
    with autocast(precision, device.type):
        return to_host(encoder([cloud])[0].float())


def heads_float(model: nn.Module, fused: Tensor, precision: Precision, boxes: bool = True) -> dict[str, Tensor]:
    """The heads on a fused map [B, C, F, F] (on the model's device), every output back in float32 and left on
    that device; `boxes=False`: the segmentation heads only (no detection head run)."""
    with autocast(precision, fused.device.type):
        out = model.heads(fused) if boxes else model.heads.segmentation(fused)
    return {k: v.float() for k, v in out.items()}


@torch.no_grad()
def late_outputs(model: nn.Module, features: np.ndarray, boxes: bool = True,
                 precision: Precision = "fp32") -> tuple[np.ndarray, np.ndarray]:
    """A CAV's own decoded outputs for late fusion: probabilities [3, S, S] (vehicle, road, lane) and
    boxes [K, 6] (x, y, l, w, yaw, score) in its body frame (none decoded with `boxes=False`: [0, 6])."""
    fused = torch.from_numpy(np.ascontiguousarray(features, dtype=np.float32))[None].to(model_device(model))
    out = heads_float(model, fused, precision)
    probs = segmentation_probabilities(out["dynamic"], out["static"])
    maps = np.stack([to_host(probs[k][0]) for k in ("vehicle", "road", "lane")])
    found = np.zeros((0, 6), np.float32)
    if boxes and "det_cls" in out:
        found = to_host(decode_detections(out["det_cls"], out["det_reg"], model.anchors)[0])
    return maps.astype(np.float32), found.astype(np.float32)


def pooled_confidence(p_vehicle: np.ndarray, cells: int) -> np.ndarray:
    """A vehicle probability map [S, S] max-pooled to the feature grid [cells, cells]: what a CAV ranks its
    feature cells by under comm.share topk (Where2comm's spatial confidence map, Eq. 2)."""
    return torch.nn.functional.adaptive_max_pool2d(torch.from_numpy(p_vehicle)[None, None], cells)[0, 0].numpy()


def vehicle_confidence(model: nn.Module, features: np.ndarray, precision: Precision = "fp32") -> np.ndarray:
    """The single-agent heads' vehicle probability on features [C, F, F], pooled to [F, F] (pooled_confidence)."""
    maps, _ = late_outputs(model, features, boxes=False, precision=precision)
    return pooled_confidence(maps[0], features.shape[-1])
