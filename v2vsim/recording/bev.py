"""What the recording draws on the ego's BEV grid (ego heading up, as DESIGN.md's grid).

Ground truth as classes; per method the vehicle probability as a colour map (not a thresholded
mask, so a reviewer sees how sure it was) and an error image against the visible-vehicle
ground truth, which is what the IoU scores; detection boxes as outlines in pixel coordinates.
"""

from __future__ import annotations

import numpy as np
import torch
from matplotlib import colormaps

from models.nms import box_corners
from v2vsim.evaluation.metrics import THRESHOLD
from v2vsim.world.geometry import BevGrid

GT_CLASSES = [(0, "background", (20, 20, 20)), (1, "road", (90, 90, 90)), (2, "lane", (230, 230, 230)),
              (3, "vehicle", (255, 80, 60)), (4, "vehicle (not visible)", (120, 60, 160))]
# Error classes: scored cells in three colours; not-visible vehicles are apart (IoU ignores them).
TP, FP, FN, HIDDEN, HIDDEN_PREDICTED = 3, 4, 5, 6, 7
ERROR_CLASSES = [(0, "background", (12, 12, 12)), (1, "road", (48, 48, 52)), (2, "lane", (90, 90, 96)),
                 (TP, "true positive", (50, 205, 90)), (FP, "false positive", (240, 70, 50)),
                 (FN, "false negative", (60, 150, 255)), (HIDDEN, "vehicle not visible (not scored)", (110, 60, 150)),
                 (HIDDEN_PREDICTED, "predicted on a not-visible vehicle (not scored)", (220, 140, 230))]
PRED_BOX_RGB = (255, 220, 0)
GT_BOX_RGB = (255, 255, 255)
_LUT = (colormaps["magma"](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)  # (256, 3)


def gt_image(gt: dict[str, np.ndarray]) -> np.ndarray:
    """(H, W) uint8 GT_CLASSES ids: road, lane, visible and not-visible vehicles."""
    img = np.zeros(gt["road"].shape, np.uint8)
    img[gt["road"]] = 1
    img[gt["lane"]] = 2
    img[gt["dynamic"] & ~gt["visible"]] = 4
    img[gt["visible"]] = 3
    return img


def probability_image(p: np.ndarray) -> np.ndarray:
    """(H, W) probability in [0, 1] -> (H, W, 3) uint8 magma colour map (black 0, pale yellow 1)."""
    idx = (np.clip(p, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    return np.take(_LUT, idx, axis=0)


def _error_lut() -> np.ndarray:
    """Class of every (predicted, visible, hidden, road, lane) combination, as bits 0..4 of an index."""
    lut = np.zeros(32, np.uint8)
    for code in range(32):
        pred, visible, hidden, road, lane = ((code >> b) & 1 for b in range(5))
        cls = 2 if lane else 1 if road else 0
        if hidden:
            cls = HIDDEN_PREDICTED if pred else HIDDEN
        elif pred or visible:
            cls = TP if pred and visible else FP if pred else FN
        lut[code] = cls
    return lut


_ERROR_LUT = _error_lut()


def error_image(p_vehicle: np.ndarray, gt: dict[str, np.ndarray]) -> np.ndarray:
    """(H, W) uint8 ERROR_CLASSES ids of the thresholded prediction against the visible vehicles
    (a not-visible vehicle is one in `dynamic` but not in `visible`, which the IoU ignores)."""
    hidden = gt["dynamic"] & ~gt["visible"]
    code = (p_vehicle >= THRESHOLD).view(np.uint8) | (gt["visible"].view(np.uint8) << 1)
    code |= (hidden.view(np.uint8) << 2) | (gt["road"].view(np.uint8) << 3) | (gt["lane"].view(np.uint8) << 4)
    return _ERROR_LUT[code]


def box_strips(grid: BevGrid, boxes: np.ndarray) -> np.ndarray:
    """(K, >=5) ego-frame boxes (x, y, l, w, yaw, ...) -> (K, 5, 2) closed outlines in pixel
    coordinates (u = column, v = row)."""
    b = np.asarray(boxes, np.float64).reshape(len(boxes), -1)[:, :5] if len(boxes) else np.zeros((0, 5))
    corners = box_corners(torch.from_numpy(b)).numpy()  # (K, 4, 2)
    closed = np.concatenate([corners, corners[:, :1]], axis=1)
    return grid.xy_to_rc(closed)[..., ::-1].astype(np.float32)
