"""The env's rgb_array picture of one fused frame, three panels on the receiver's BEV grid (heading up):
ground truth | the fused prediction's errors against it (v2vsim.recording.bev colours) | the feature
cells every CAV sent, each in its colour, placed where they lie in the receiver's frame."""

from __future__ import annotations

from typing import Any

import numpy as np

from v2vsim.comm.codec import Message
from v2vsim.config import BevConfig
from v2vsim.recording.bev import ERROR_CLASSES, GT_CLASSES, error_image, gt_image
from v2vsim.world.geometry import BevGrid, body_to_world, world_to_body

SENDER_RGB = np.array([(255, 200, 40), (60, 200, 255), (120, 255, 120), (255, 110, 200), (200, 140, 255),
                       (255, 150, 80), (80, 255, 220), (230, 230, 230)], np.uint8)
GAP = 4  # pixels between panels


def _palette(classes: list[tuple[int, str, tuple[int, int, int]]]) -> np.ndarray:
    lut = np.zeros((256, 3), np.uint8)
    for idx, _, rgb in classes:
        lut[idx] = rgb
    return lut


_GT_LUT, _ERR_LUT = _palette(GT_CLASSES), _palette(ERROR_CLASSES)


def sent_cells_image(gt: dict[str, np.ndarray], sent: dict[str, tuple[bytes, Message]], receiver: str,
                     world: Any, bev: BevConfig, feature_cells: int) -> np.ndarray:
    """(S, S, 3): road in grey, and every sent feature cell as a square in its sender's colour."""
    img = np.where(gt["road"][..., None], np.uint8(50), np.uint8(15)).astype(np.uint8).repeat(3, axis=2)
    grid, fine = BevGrid(bev.size_m, feature_cells), BevGrid(bev.size_m, bev.cells)
    centres = grid.cell_centres().reshape(-1, 2)  # sender body frame, row-major like the sparse indices
    half = max(1, bev.cells // feature_cells // 2)
    me = world.actor(receiver).pose
    for n, (sender, (_, msg)) in enumerate(sorted(sent.items())):
        cells = msg.extras["cells"].astype(np.int64) if msg.kind == "sparse" else np.arange(len(centres))
        pose = world.actor(sender).pose
        rc = fine.xy_to_rc(world_to_body(body_to_world(centres[cells], pose), me)).astype(np.int64)
        colour = SENDER_RGB[n % len(SENDER_RGB)]
        for r, c in rc:
            if -half <= r < bev.cells + half and -half <= c < bev.cells + half:
                img[max(0, r - half):r + half, max(0, c - half):c + half] = colour
    return img


def render_frame(last: dict[str, Any], bev: BevConfig, feature_cells: int) -> np.ndarray:
    """The three panels side by side, (S, 3S + 2 GAP, 3) uint8; black before the first step."""
    s = bev.cells
    out = np.zeros((s, 3 * s + 2 * GAP, 3), np.uint8)
    if not last:
        return out
    gt = last["gt"]
    out[:, :s] = _GT_LUT[gt_image(gt)]
    out[:, s + GAP:2 * s + GAP] = _ERR_LUT[error_image(last["pred"].probs["vehicle"], gt)]
    out[:, 2 * s + 2 * GAP:] = sent_cells_image(gt, last["sent"], last["receiver"], last["world"], bev, feature_cells)
    return out
