"""Fusion methods (models/fusion): masking contract, neighbour-order invariance, brackets."""

from __future__ import annotations

import math

import pytest
import torch

from models.build import build_fusion
from models.fusion.attfuse import AttFusion
from models.fusion.early import merge_points_to_ego
from models.fusion.late import late_fuse_boxes, late_fuse_probabilities
from models.fusion.none import NoFusion
from models.registry import FUSION

C, HW = 64, 16  # tiny channels; 16 cells keep every window size valid and the test fast
SYMMETRIC = ["fcooper", "attfuse", "v2vnet", "disconet"]


def _inputs(b: int = 2, l: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    feats = torch.randn(b, l, C, HW, HW, generator=g).relu()
    valid = torch.tensor([[True, True, False, True, False], [True, False, False, False, True]])[:b, :l]
    return feats, valid


@pytest.fixture(scope="module", params=sorted(FUSION))
def method(request: pytest.FixtureRequest) -> tuple[str, torch.nn.Module]:
    torch.manual_seed(0)
    return request.param, build_fusion(request.param, "tiny").eval()


@pytest.mark.parametrize("garbage", ["random", "huge", "nan", "inf"])
def test_masked_agents_change_nothing(method: tuple[str, torch.nn.Module], garbage: str) -> None:
    name, fus = method
    feats, valid = _inputs()
    with torch.no_grad():
        ref = fus(feats, valid)
        other = feats.clone()
        fill = {"random": torch.randn_like(feats) * 5, "huge": torch.full_like(feats, 1e30),
                "nan": torch.full_like(feats, float("nan")), "inf": torch.full_like(feats, float("inf"))}[garbage]
        other[~valid] = fill[~valid]
        out = fus(other, valid)
    assert out.shape == (2, C, HW, HW)
    assert torch.isfinite(ref).all()
    assert torch.equal(out, ref), f"{name}: absent agents leak into the output"


@pytest.mark.parametrize("name", SYMMETRIC)
def test_invariant_to_neighbour_order(name: str) -> None:
    torch.manual_seed(0)
    fus = build_fusion(name, "tiny").eval()
    feats, valid = _inputs()
    perm = torch.tensor([0, 3, 1, 4, 2])  # ego stays in slot 0
    with torch.no_grad():
        a = fus(feats, valid)
        b = fus(feats[:, perm], valid[:, perm])
    torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("l", [1, 2, 4])
def test_shapes_and_ego_only(method: tuple[str, torch.nn.Module], l: int) -> None:
    name, fus = method
    feats = torch.randn(1, l, C, HW, HW).relu()
    valid = torch.zeros(1, l, dtype=torch.bool)
    valid[:, 0] = True
    with torch.no_grad():
        out = fus(feats, valid)
    assert out.shape == (1, C, HW, HW)
    if name in ("none", "fcooper", "attfuse", "disconet"):  # pure selections: only the ego remains
        torch.testing.assert_close(out, feats[:, 0], atol=1e-6, rtol=0)


def test_fcooper_is_elementwise_max_and_none_is_ego() -> None:
    feats, valid = _inputs()
    out = build_fusion("fcooper", "tiny")(feats, valid)
    torch.testing.assert_close(out[0], feats[0, [0, 1, 3]].amax(0))
    torch.testing.assert_close(NoFusion(C)(feats, valid), feats[:, 0])


def test_attfuse_weights_follow_similarity() -> None:
    ego = torch.zeros(1, 1, 4, 1, 1)
    ego[0, 0, 0] = 3.0
    same, other = ego.clone(), torch.zeros_like(ego)
    other[0, 0, 1] = 3.0
    feats = torch.cat([ego, same, other], dim=1)
    out = AttFusion(4)(feats, torch.ones(1, 3, dtype=torch.bool))
    w_other = 1 / (2 * math.exp(9 / 2) + 1)  # logits 9/2, 9/2, 0
    assert out[0, 1, 0, 0].item() == pytest.approx(3 * w_other, rel=1e-5)


def test_learnable_methods_get_gradients() -> None:
    for name in ("v2vnet", "disconet"):
        fus = build_fusion(name, "tiny")
        feats, valid = _inputs()
        fus(feats, valid).square().mean().backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in fus.parameters())


def test_early_merges_valid_clouds_in_the_ego_frame() -> None:
    ego = torch.tensor([[1.0, 0.0, 0.5, 0.1]])
    nb = torch.tensor([[1.0, 0.0, 0.7, 0.2]])
    absent = torch.tensor([[9.0, 9.0, 9.0, 9.0]])
    poses = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, math.pi / 2], [5.0, 5.0, 0.0]])
    out = merge_points_to_ego([ego, nb, absent], poses, torch.tensor([True, True, False]))
    torch.testing.assert_close(out, torch.tensor([[1.0, 0.0, 0.5, 0.1], [10.0, 1.0, 0.7, 0.2]]))


def test_late_probabilities_max_over_valid_agents() -> None:
    s, cells = 32.0, 32
    probs = torch.zeros(3, 1, cells, cells)
    probs[0, 0, 10, 10] = 0.4
    probs[1, 0, 10, 10] = 0.9  # same place, neighbour at the ego's pose
    probs[2] = 1.0  # absent agent: must be ignored
    poses = torch.zeros(3, 3)
    out = late_fuse_probabilities(probs, poses, torch.tensor([True, True, False]), s)
    assert out.shape == (1, cells, cells)
    assert out[0, 10, 10].item() == pytest.approx(0.9)
    assert out.sum().item() == pytest.approx(0.9)


def test_late_boxes_transform_and_deduplicate() -> None:
    ego = torch.tensor([[10.0, 1.0, 4.5, 1.9, 0.0, 0.8]])
    nb = torch.tensor([[1.0, 0.0, 4.5, 1.9, -math.pi / 2, 0.9], [0.0, -20.0, 4.5, 1.9, 0.0, 0.5]])
    poses = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, math.pi / 2]])
    out = late_fuse_boxes([ego, nb], poses, iou_threshold=0.3)
    assert out.shape == (2, 6)
    torch.testing.assert_close(out[0], torch.tensor([10.0, 1.0, 4.5, 1.9, 0.0, 0.9]), atol=1e-5, rtol=0)
    torch.testing.assert_close(out[1, :2], torch.tensor([30.0, 0.0]), atol=1e-5, rtol=0)


def test_late_boxes_beyond_the_ego_grid_are_dropped() -> None:
    """A neighbour 40 m ahead sees a car 30 m further on: 70 m from the ego, off its 100 m grid, where
    ground truth has no box for it (v2vsim.evaluation.gt.gt_boxes) and it could only count as a false positive."""
    ego = torch.tensor([[10.0, 1.0, 4.5, 1.9, 0.0, 0.8]])
    nb = torch.tensor([[30.0, 0.0, 4.5, 1.9, 0.0, 0.9], [5.0, 0.0, 4.5, 1.9, 0.0, 0.7]])
    poses = torch.tensor([[0.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    out = late_fuse_boxes([ego, nb], poses, extent_m=100.0)
    assert sorted(out[:, 0].tolist()) == pytest.approx([10.0, 45.0])
    assert len(late_fuse_boxes([ego, nb], poses)) == 3  # without an extent, everything is kept
