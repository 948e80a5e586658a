"""models.warp: SE(2) feature warping into the ego BEV grid (BevGrid convention)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from models.warp import transform_boxes, transform_points, warp_to_ego
from v2vsim.world.geometry import BevGrid

S, H = 32.0, 32  # 1 m cells
RES = S / H


def _pose(dx: float, dy: float, yaw: float) -> torch.Tensor:
    return torch.tensor([[dx, dy, yaw]])


@pytest.mark.parametrize("k", [1, 3, 7])
def test_translation_ahead_shifts_rows_up(k: int) -> None:
    f = torch.randn(1, 4, H, H)
    w, mask = warp_to_ego(f, _pose(k * RES, 0.0, 0.0), S)
    # ego row r reads sender row r + k: the sender's content moves k rows up (towards the front)
    torch.testing.assert_close(w[0, :, : H - k], f[0, :, k:], atol=1e-5, rtol=0)
    assert torch.all(w[0, :, H - k :] == 0)
    assert mask[0, : H - k].all() and not mask[0, H - k :].any()


def test_single_cell_ahead() -> None:
    f = torch.zeros(1, 1, H, H)
    f[0, 0, H // 2, H // 2] = 1.0  # sender's own cell (just behind-right of its centre)
    w, _ = warp_to_ego(f, _pose(RES, 0.0, 0.0), S)
    assert torch.nonzero(w[0, 0] > 0.5).tolist() == [[H // 2 - 1, H // 2]]


@pytest.mark.parametrize("k", [1, 5])
def test_translation_left_shifts_columns(k: int) -> None:
    f = torch.randn(2, 3, H, H)
    w, mask = warp_to_ego(f, torch.tensor([[0.0, k * RES, 0.0]] * 2), S)  # sender k cells to the left
    torch.testing.assert_close(w[:, :, :, : H - k], f[:, :, :, k:], atol=1e-5, rtol=0)
    assert not mask[:, :, H - k :].any()


def test_rotation_90_is_exact_and_points_left() -> None:
    f = torch.randn(1, 5, H, H)
    w, mask = warp_to_ego(f, _pose(0.0, 0.0, math.pi / 2), S)
    torch.testing.assert_close(w, torch.rot90(f, 1, dims=(-2, -1)), atol=1e-4, rtol=0)
    assert mask.all()
    g = torch.zeros(1, 1, H, H)
    g[0, 0, 2, H // 2] = 1.0  # in front of the sender
    w, _ = warp_to_ego(g, _pose(0.0, 0.0, math.pi / 2), S)
    r, c = torch.nonzero(w[0, 0] > 0.5)[0].tolist()
    assert c == 2 and abs(r - H / 2) <= 1  # the sender faces the ego's left: lands left of the ego


@pytest.mark.parametrize("pose", [(3.0, -2.0, 0.5), (-4.0, 5.0, 2.4), (6.0, 1.0, -1.7), (0.0, 0.0, math.pi)])
def test_any_pose_moves_a_blob_where_the_geometry_says(pose: tuple[float, float, float]) -> None:
    grid = BevGrid(S, H)
    centres = torch.as_tensor(grid.cell_centres(), dtype=torch.float32)  # [H, H, 2]
    src_xy = torch.tensor([5.0, 3.0])  # blob position in the sender frame
    blob = torch.exp(-((centres - src_xy) ** 2).sum(-1) / (2 * 1.5**2))[None, None]
    w, _ = warp_to_ego(blob, torch.tensor([pose]), S)
    exp_xy = transform_points(src_xy[None], torch.tensor(pose))[0]
    exp_rc = grid.xy_to_rc(exp_xy.numpy()) - 0.5  # continuous index of the cell centre
    m = w[0, 0].numpy()
    rr, cc = np.meshgrid(np.arange(H), np.arange(H), indexing="ij")
    got = np.array([(m * rr).sum(), (m * cc).sum()]) / m.sum()
    assert np.abs(got - exp_rc).max() < 0.2


def test_batched_shapes_and_identity_for_the_ego() -> None:
    f = torch.randn(2, 3, 4, 16, 16)
    poses = torch.zeros(2, 3, 3)
    poses[:, 1:] = torch.tensor([2.0, -1.0, 0.3])
    w, mask = warp_to_ego(f, poses, 50.0)
    assert w.shape == f.shape and mask.shape == (2, 3, 16, 16)
    torch.testing.assert_close(w[:, 0], f[:, 0], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match=re.escape("rel_poses (2, 2, 3) does not match features (2, 3, 4, 16, 16)")):
        warp_to_ego(f, torch.zeros(2, 2, 3), 50.0)


def test_transform_boxes_adds_yaw() -> None:
    b = torch.tensor([[1.0, 0.0, 4.5, 1.9, 0.2, 0.9]])
    out = transform_boxes(b, torch.tensor([10.0, 0.0, math.pi / 2]))
    torch.testing.assert_close(out, torch.tensor([[10.0, 1.0, 4.5, 1.9, 0.2 + math.pi / 2, 0.9]]))
