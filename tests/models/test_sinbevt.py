"""SinBEVT (CoBEVT Table A2) and its ResNet-34 / camera geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from models.resnet import ResNet
from models.sinbevt import (
    PRESETS,
    bev_cell_xy,
    build_sinbevt,
    default_camera_rig,
    feature_rays,
    resize_images,
)
from v2vsim.world.geometry import BevGrid

# a SinBEVT small enough to train in a test: 64x64 images, features 8/4/2, BEV 32 -> 16 -> 16
SMALL = dict(  # the architecture at test size, on the small from-scratch ResNet
    backbone="resnet",
    image_size=(64, 64),
    resnet_width=0.25,
    resnet_blocks=(1, 1, 1, 1),
    dim=32,
    heads=2,
    mlp_dim=64,
    bev_sizes=(32, 16, 16),
    bev_windows=(8, 8, 16),
    feat_windows=(2, 2, 2),
    bottlenecks=1,
)


def test_paper_preset_table_a2_shapes() -> None:
    torch.manual_seed(0)
    m = build_sinbevt("paper").eval()
    assert (m.out_channels, m.out_cells) == (128, 32)
    intr, extr = default_camera_rig(1, 4, 512, 512)
    shapes = m.stage_shapes((torch.rand(1, 4, 3, 512, 512), intr, extr))
    assert shapes == [
        ("resnet.layer1", (1, 4, 128, 64, 64)),  # N x M x 64 x 64 x 128
        ("resnet.layer2", (1, 4, 256, 32, 32)),  # N x M x 32 x 32 x 256
        ("resnet.layer3", (1, 4, 512, 16, 16)),  # N x M x 16 x 16 x 512
        ("stages.0", (1, 128, 128, 128)),  # N x 128 x 128 x 128
        ("stages.1", (1, 128, 64, 64)),  # N x 64 x 64 x 128
        ("stages.2", (1, 128, 32, 32)),  # N x 32 x 32 x 128
    ]
    cfg = PRESETS["paper"]
    assert (cfg.dim, cfg.heads, cfg.mlp_dim) == (128, 4, 256)
    assert cfg.bev_windows == (16, 16, 32) and cfg.feat_windows == (8, 8, 16)


def test_resnet34_block_counts() -> None:
    r = ResNet()
    counts = [len(getattr(r, f"layer{i}")) for i in range(4)]
    assert counts == [3, 4, 6, 3]  # ResNet-34
    assert r.out_channels == (128, 256, 512)


def test_tiny_preset_from_raw_camera_size() -> None:
    torch.manual_seed(0)
    m = build_sinbevt("tiny").eval()
    images, intr, extr = m.example_inputs(batch=2)  # 200x150 renders, resized inside to 128x128
    assert images.shape == (2, 4, 3, 150, 200)
    with torch.no_grad():
        y = m(images, intr, extr)
    assert y.shape == (2, m.out_channels, m.out_cells, m.out_cells) == (2, 64, 32, 32)
    assert torch.isfinite(y).all()
    shapes = m.stage_shapes()  # ImageNet EfficientNet-Lite0 at strides 8/16/32 (models/image_backbone.py)
    assert shapes[:3] == [("efficientnet.net._blocks.4", (1, 4, 40, 16, 16)),
                          ("efficientnet.net._blocks.10", (1, 4, 112, 8, 8)),
                          ("efficientnet.net._blocks.15", (1, 4, 320, 4, 4))]
    assert [n for n, _ in shapes[3:]] == ["stages.0", "stages.1", "stages.2"]
    legacy = build_sinbevt("tiny", backbone="resnet")  # the first camera zoo's from-scratch encoder
    assert [n for n, _ in legacy.stage_shapes()][:3] == ["resnet.layer1", "resnet.layer2", "resnet.layer3"]


def test_samples_independent_and_geometry_used() -> None:
    torch.manual_seed(0)
    m = build_sinbevt("tiny", **SMALL).eval()
    images = torch.rand(2, 2, 3, 48, 64)
    intr, extr = default_camera_rig(2, 2, 48, 64)
    with torch.no_grad():
        y = m(images, intr, extr)
        images2 = images.clone()
        images2[1] = torch.rand_like(images2[1])
        assert torch.allclose(m(images2, intr, extr)[0], y[0], atol=1e-6)
        extr2 = extr.clone()
        extr2[:, :, :3, 3] += torch.tensor([5.0, 0.0, 0.0])  # move the cameras 5 m forward
        assert (m(images, intr, extr2) - y).abs().max() > 1e-5  # float noise is ~1e-7
        extr2 = extr[:, [1, 0]]  # swap the two cameras' poses
        assert (m(images, intr, extr2) - y).abs().max() > 1e-5


def test_build_errors() -> None:
    with pytest.raises(ValueError, match=r"unknown SinBEVT preset 'huge'"):
        build_sinbevt("huge")
    # stage 0: BEV 32 / window 16 = 2x2 BEV windows vs features 8 / window 2 = 4x4 feature windows
    with pytest.raises(ValueError, match=r"stage 0: 4 BEV windows != 16 feature windows"):
        build_sinbevt("tiny", **{**SMALL, "bev_windows": (16, 8, 16)})


def test_bev_cells_follow_bevgrid() -> None:
    ours = bev_cell_xy(32, 100.0).numpy()
    ref = BevGrid(size_m=100.0, cells=32).cell_centres()
    np.testing.assert_allclose(ours, ref, atol=1e-5)
    assert ours[0, 0, 0] > 0 and ours[0, 0, 1] > 0  # row 0 front, column 0 left


def test_feature_rays_in_agent_frame() -> None:
    intr, extr = default_camera_rig(1, 4, 60, 80, fov_deg=90.0)  # front, right, left, back
    rays = feature_rays(intr, extr, (60, 80), (3, 4))  # [1, 4, 3, 4, 3]
    # the central ray of each camera (between feature pixels (1, 1) and (1, 2))
    centre = (rays[0, :, 1, 1] + rays[0, :, 1, 2]) / 2
    expect = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 1.0, 0], [-1.0, 0, 0]])
    torch.testing.assert_close(centre, expect, atol=1e-5, rtol=0)
    front = rays[0, 0]
    assert front[1, 0, 1] > 0 > front[1, 3, 1]  # left image column looks to +y (left)
    assert front[0, 1, 2] > 0 > front[2, 1, 2]  # top image row looks up (+z)


def test_resize_scales_intrinsics() -> None:
    intr, _ = default_camera_rig(1, 1, 150, 200)
    images = torch.rand(1, 1, 3, 150, 200)
    out, k2 = resize_images(images, intr, (128, 128))
    assert out.shape == (1, 1, 3, 128, 128)
    point = torch.tensor([1.5, -0.7, 10.0])  # camera frame
    uv1 = intr[0, 0] @ point
    uv2 = k2[0, 0] @ point
    u1, v1 = (uv1[:2] / uv1[2]).tolist()
    u2, v2 = (uv2[:2] / uv2[2]).tolist()
    assert math.isclose(u2, u1 * 128 / 200, rel_tol=1e-6) and math.isclose(v2, v1 * 128 / 150, rel_tol=1e-6)



def test_overfits_one_batch() -> None:
    """Gradients flow end to end: two samples with different images and BEV masks are fitted (the shared
    learnable BEV query alone cannot do that), loss falls >= 10x below min(initial, ln 2)."""
    torch.manual_seed(0)
    m = build_sinbevt("tiny", **SMALL)
    head = nn.Conv2d(m.out_channels, 1, 1)
    images = torch.rand(2, 2, 3, 64, 64)
    images[1] *= 0.3
    intr, extr = default_camera_rig(2, 2, 64, 64)
    target = torch.zeros(2, 1, m.out_cells, m.out_cells)
    target[0, :, 2:6, 3:9] = 1
    target[1, :, 8:14, 5:8] = 1
    opt = torch.optim.Adam([*m.parameters(), *head.parameters()], lr=3e-3)
    loss_fn = nn.BCEWithLogitsLoss()
    first = None
    for _ in range(150):
        loss = loss_fn(head(m(images, intr, extr)), target)
        opt.zero_grad()
        loss.backward()
        if first is None:
            first = loss.item()
            for name in ("resnet.stem.0.weight", "stages.0.cross.local_attn.to_k.weight", "bev_query"):
                g = dict(m.named_parameters())[name].grad
                assert g is not None and g.abs().sum() > 0, name
        opt.step()
        if loss.item() < min(first, math.log(2)) / 10:
            break
    assert loss.item() < min(first, math.log(2)) / 10, (first, loss.item())
