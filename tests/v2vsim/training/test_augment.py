"""Yaw augmentation: masks and extrinsics turn together, cells from outside the recording are marked and
left out of the loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from v2vsim.training.augment import rotate_masks, yaw_rotate_batch, yaw_rotation
from v2vsim.training.losses import perception_loss
from v2vsim.world.geometry import BevGrid


def _cell(x: float, y: float, size_m: float, f: int) -> tuple[int, int]:
    r, c = np.floor(BevGrid(size_m, f).xy_to_rc([x, y])).astype(int)
    return int(r), int(c)


def test_zero_angle_is_the_identity() -> None:
    masks = torch.rand(2, 1, 16, 16) > 0.5
    out, outside = rotate_masks(masks, torch.zeros(2), 32.0)
    assert torch.equal(out, masks) and not outside.any()


def test_a_quarter_turn_takes_the_front_to_the_left() -> None:
    masks = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    masks[0, 0, 1, 3] = True  # x = 2.5 m ahead, y = 0.5 m left (8 m grid, 1 m cells)
    out, outside = rotate_masks(masks, torch.tensor([math.pi / 2]), 8.0)
    assert out.sum() == 1 and out[0, 0, 4, 1]  # turned +x -> +y: x = -0.5, y = 2.5
    assert not outside.any()  # a square turned by 90 degrees covers itself


def test_corners_come_from_outside_at_45_degrees() -> None:
    out, outside = rotate_masks(torch.ones(1, 1, 32, 32, dtype=torch.bool), torch.tensor([math.pi / 4]), 32.0)
    assert outside[0, 0, 0] and outside[0, -1, -1] and not outside[0, 16, 16]
    assert torch.equal(out[:, 0], ~outside)


def test_masks_follow_the_camera_rays() -> None:
    """A ground point seen along a camera ray lands, after the turn, in the cell the turned extrinsics put
    that ray's point in: the model sees the same pixels, and its target moved with its geometry."""
    size_m, f = 40.0, 64
    cam_to_agent = torch.eye(4)
    cam_to_agent[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV -> body
    cam_to_agent[:3, 3] = torch.tensor([1.0, 0.0, 1.6])
    p = torch.tensor([9.3, -4.1, 0.0, 1.0])  # a ground point in the agent frame
    p_cam = torch.linalg.inv(cam_to_agent) @ p
    theta = torch.tensor([0.35])
    masks = torch.zeros(1, f, f, dtype=torch.bool)
    r0, c0 = _cell(p[0].item(), p[1].item(), size_m, f)
    masks[0, r0 - 1:r0 + 2, c0 - 1:c0 + 2] = True  # 3 x 3 cells: nearest-cell sampling moves by < 1 cell
    batch = {"extrinsics": cam_to_agent.expand(1, 1, 1, 4, 4).clone(), "valid": torch.ones(1, 1, dtype=torch.bool),
             **{k: masks.clone() for k in ("vehicle", "dynamic", "visible_self", "road", "lane")}}
    out = yaw_rotate_batch(batch, theta, size_m)
    q = out["extrinsics"][0, 0, 0] @ p_cam
    assert torch.allclose(q, yaw_rotation(theta)[0] @ p, atol=1e-5)
    r, c = _cell(q[0].item(), q[1].item(), size_m, f)
    assert out["road"][0, r, c] and out["vehicle"][0, r, c]
    assert not out["road"][0, r0, c0]  # it moved: 20 degrees at 10 m is about 6 cells


def test_the_loss_ignores_cells_from_outside() -> None:
    f = 32
    out = {"dynamic": torch.randn(1, 2, f, f), "static": torch.randn(1, 3, f, f)}
    batch = {k: torch.zeros(1, f, f, dtype=torch.bool) for k in ("vehicle", "dynamic", "visible_self", "road", "lane")}
    batch["outside"] = torch.zeros(1, f, f, dtype=torch.bool)
    batch["outside"][:, :8] = True
    base = perception_loss(out, batch, "self", None)
    changed = {**batch, **{k: batch[k].clone() for k in ("road", "visible_self", "dynamic")}}
    changed["road"][:, :8] = True  # only cells from outside change
    changed["visible_self"][:, :4] = changed["dynamic"][:, :4] = True
    other = perception_loss(out, changed, "self", None)
    assert float(other["static"]) == pytest.approx(float(base["static"]))
    assert float(other["dyn"]) == pytest.approx(float(base["dyn"]))


def test_lidar_and_multi_agent_batches_are_refused() -> None:
    with pytest.raises(ValueError, match="camera samples"):
        yaw_rotate_batch({"valid": torch.ones(1, 1, dtype=torch.bool)}, torch.zeros(1), 40.0)
    with pytest.raises(ValueError, match="single-agent batches"):
        two = {"extrinsics": torch.eye(4).expand(1, 2, 4, 4, 4), "valid": torch.ones(1, 2, dtype=torch.bool)}
        yaw_rotate_batch(two, torch.zeros(1), 40.0)
