"""models.nms: rotated IoU and rotated NMS."""

from __future__ import annotations

import math

import pytest
import torch
from shapely.geometry import Polygon

from models.nms import box_corners, rotated_iou_matrices, rotated_iou_matrix, rotated_iou_pairs, rotated_nms


def test_known_ious() -> None:
    a = torch.tensor([[1.0, 2.0, 4.5, 1.9, 0.4]])
    assert rotated_iou_matrix(a, a).item() == pytest.approx(1.0, abs=1e-6)
    far = torch.tensor([[20.0, 2.0, 4.5, 1.9, 0.4]])
    assert rotated_iou_matrix(a, far).item() == 0.0
    touching = torch.tensor([[1.0 + 4.5 * math.cos(0.4), 2.0 + 4.5 * math.sin(0.4), 4.5, 1.9, 0.4]])
    assert rotated_iou_matrix(a, touching).item() == pytest.approx(0.0, abs=1e-6)
    # the same box rotated 90 deg about its centre: w x w square overlap -> w / (2 l - w)
    rot = a.clone()
    rot[0, 4] += math.pi / 2
    assert rotated_iou_matrix(a, rot).item() == pytest.approx(1.9 / (2 * 4.5 - 1.9), abs=1e-6)
    # half overlap along the length: (lw/2) / (2lw - lw/2) = 1/3, at any heading
    yaw = 0.4
    half = torch.tensor([[1.0 + 2.25 * math.cos(yaw), 2.0 + 2.25 * math.sin(yaw), 4.5, 1.9, yaw]])
    assert rotated_iou_matrix(a, half).item() == pytest.approx(1 / 3, abs=1e-6)
    # heading is modulo pi for a box
    flip = a.clone()
    flip[0, 4] += math.pi
    assert rotated_iou_matrix(a, flip).item() == pytest.approx(1.0, abs=1e-6)


def test_matches_shapely_on_random_boxes() -> None:
    g = torch.Generator().manual_seed(0)
    boxes = torch.rand(60, 5, generator=g) * torch.tensor([8.0, 8.0, 4.0, 2.0, 6.28]) + torch.tensor(
        [0, 0, 1.0, 0.5, -3.14]
    )
    iou = rotated_iou_matrix(boxes, boxes)
    polys = [Polygon(c) for c in box_corners(boxes.double()).numpy()]
    for i in range(0, 60, 5):
        for j in range(60):
            ref = polys[i].intersection(polys[j]).area / polys[i].union(polys[j]).area
            assert iou[i, j].item() == pytest.approx(ref, abs=1e-5)
    torch.testing.assert_close(iou, iou.T, atol=1e-6, rtol=0)
    torch.testing.assert_close(rotated_iou_pairs(boxes[:10], boxes[10:20]), iou[torch.arange(10), torch.arange(10, 20)])


def test_empty_inputs() -> None:
    assert rotated_iou_matrix(torch.zeros(0, 5), torch.zeros(3, 5)).shape == (0, 3)
    assert rotated_nms(torch.zeros(0, 5), torch.zeros(0), 0.5).numel() == 0


def test_nms_suppresses_duplicates_and_keeps_separate_boxes() -> None:
    boxes = torch.tensor(
        [
            [0.0, 0.0, 4.5, 1.9, 0.0],
            [0.2, 0.1, 4.5, 1.9, 0.05],  # duplicate of 0, lower score
            [10.0, 0.0, 4.5, 1.9, 1.0],
            [10.1, 0.0, 4.4, 1.9, 1.0],  # duplicate of 2, higher score
            [0.0, 5.0, 4.5, 1.9, 0.0],
        ]
    )
    scores = torch.tensor([0.9, 0.8, 0.5, 0.7, 0.3])
    keep = rotated_nms(boxes, scores, iou_threshold=0.3)
    assert keep.tolist() == [0, 3, 4]
    assert rotated_nms(boxes, scores, 0.3, max_out=2).tolist() == [0, 3]


def test_many_matrices_at_once_equal_each_alone() -> None:
    """rotated_iou_matrices (a run's AP: every frame's candidate pairs in one pass) against rotated_iou_matrix per
    frame, with empty frames and frames without overlaps among them."""
    g = torch.Generator().manual_seed(5)

    def boxes(n: int, spread: float) -> torch.Tensor:
        xy = torch.rand(n, 2, generator=g) * spread
        lw = torch.rand(n, 2, generator=g) * 3 + 1
        return torch.cat([xy, lw, torch.rand(n, 1, generator=g) * 6.3], dim=1)

    pairs = [(boxes(n, s), boxes(m, s)) for n, m, s in ((7, 5, 10.0), (0, 3, 10.0), (4, 0, 10.0), (6, 6, 400.0),
                                                         (30, 12, 20.0), (1, 1, 1.0))]
    many = rotated_iou_matrices(pairs, chunk=16)  # several chunks
    assert [tuple(m.shape) for m in many] == [(a.shape[0], b.shape[0]) for a, b in pairs]
    for (a, b), m in zip(pairs, many, strict=True):
        assert torch.allclose(m, rotated_iou_matrix(a, b), atol=1e-6)
    assert many[4].max() > 0 and rotated_iou_matrices([]) == []
