"""LaRa camera encoder (LaRa supp. Eq. 8-12)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from models.lara import BevLatentCrossAttention, build_lara, fourier_encode
from models.sinbevt import default_camera_rig
from v2vsim.world.geometry import BevGrid

SMALL = dict(  # the architecture at test size, on the small from-scratch ResNet
    backbone="resnet",
    image_size=(64, 64),
    resnet_width=0.25,
    resnet_blocks=(1, 1, 1, 1),
    feat_dim=32,
    ray_dim=16,
    num_latents=32,
    latent_dim=64,
    latent_layers=1,
    cross_heads=2,
    latent_heads=2,
    query_dim=32,
    out_channels=32,
    out_cells=16,
    fourier_bands=8,
)


def test_paper_preset_shapes() -> None:
    torch.manual_seed(0)
    m = build_lara("paper").eval()
    assert (m.out_channels, m.out_cells) == (128, 32)
    intr, extr = default_camera_rig(1, 4, 512, 512)
    shapes = dict(m.stage_shapes((torch.rand(1, 4, 3, 512, 512), intr, extr)))
    assert shapes["resnet.layer1"] == (1, 4, 128, 64, 64)
    assert shapes["neck"] == (1, 4, 128, 64, 64)  # one stride-8 map, c = 128 as in LaRa
    assert shapes["encode"] == shapes["process"] == (1, 512, 256)
    assert shapes["decode"] == (1, 32 * 32, 128)
    assert shapes["head"] == (1, 32 * 32, 128)


def test_tiny_preset_output_matches_sinbevt_tiny() -> None:
    torch.manual_seed(0)
    m = build_lara("tiny").eval()
    images, intr, extr = m.example_inputs(batch=2)
    with torch.no_grad():
        y = m(images, intr, extr)
    assert y.shape == (2, 64, 32, 32) and torch.isfinite(y).all()
    with pytest.raises(ValueError, match=r"unknown LaRa preset 'huge'"):
        build_lara("huge")


def test_fourier_encoding_eq11() -> None:
    z = torch.tensor([0.5, -0.25])
    out = fourier_encode(z, bands=3, max_freq=4.0)  # f = 1, 2.5, 4
    assert out.shape == (2, 7)
    f = torch.tensor([1.0, 2.5, 4.0])
    expect = torch.cat([z[:, None], torch.sin(f * math.pi * z[:, None]), torch.cos(f * math.pi * z[:, None])], 1)
    torch.testing.assert_close(out, expect)


def test_bev_query_grid_and_variants() -> None:
    m = build_lara("tiny", **{**SMALL, "bev_query": "coords", "ray_encoding": "plucker"}).eval()
    coords = m.query.coords.numpy() * 50.0  # normalised by half of 100 m
    np.testing.assert_allclose(coords, BevGrid(100.0, 16).cell_centres(), atol=1e-4)
    intr, extr = default_camera_rig(1, 2, 48, 64)
    with torch.no_grad():
        y = m(torch.rand(1, 2, 3, 48, 64), intr, extr)
    assert y.shape == (1, 32, 16, 16)


def test_ray_embedding() -> None:
    m = build_lara("tiny", **SMALL)
    intr, extr = default_camera_rig(1, 4, 64, 64)
    extr[..., :3, 3] = torch.tensor([1.0, 2.0, 1.5])
    rays = m.ray_embedding(intr, extr, (4, 4))  # [1, 4, 4, 4, 6] = (origin / 50, unit direction)
    torch.testing.assert_close(rays[..., :3], torch.tensor([1.0, 2.0, 1.5]).expand(1, 4, 4, 4, 3) / 50)
    torch.testing.assert_close(rays[..., 3:].norm(dim=-1), torch.ones(1, 4, 4, 4))
    assert (rays[0, 0, :, :, 3] > 0).all()  # front camera looks along +x
    plucker = build_lara("tiny", **{**SMALL, "ray_encoding": "plucker"}).ray_embedding(intr, extr, (4, 4))
    d, moment = plucker[..., :3], plucker[..., 3:]
    torch.testing.assert_close((d * moment).sum(-1), torch.zeros(1, 4, 4, 4), atol=1e-6, rtol=0)


def test_bev_latent_cross_attention_is_not_residual() -> None:
    """Eq. 10: the query is not added back; with the attention output zeroed the result is query-independent."""
    torch.manual_seed(0)
    dec = BevLatentCrossAttention(query_dim=8, latent_dim=16, heads=2, mlp_ratio=2)
    with torch.no_grad():
        dec.attn.proj.weight.zero_()
        dec.attn.proj.bias.zero_()
    latents = torch.randn(1, 5, 16)
    a = dec(torch.randn(1, 3, 8), latents)
    b = dec(torch.randn(1, 3, 8), latents)
    torch.testing.assert_close(a, b)



def test_overfits_one_batch() -> None:
    """Gradients flow end to end: two samples with different images and BEV masks are fitted (the BEV
    queries are shared, so only the image path can tell them apart); loss falls >= 10x below
    min(initial, ln 2)."""
    torch.manual_seed(0)
    m = build_lara("tiny", **SMALL)
    head = nn.Conv2d(m.out_channels, 1, 1)
    images = torch.rand(2, 2, 3, 64, 64)
    images[1] *= 0.3
    intr, extr = default_camera_rig(2, 2, 64, 64)
    target = torch.zeros(2, 1, m.out_cells, m.out_cells)
    target[0, :, 2:6, 3:9] = 1
    target[1, :, 8:14, 5:8] = 1
    opt = torch.optim.Adam([*m.parameters(), *head.parameters()], lr=1e-3)
    loss_fn = nn.BCEWithLogitsLoss()
    first = None
    for _ in range(400):
        loss = loss_fn(head(m(images, intr, extr)), target)
        opt.zero_grad()
        loss.backward()
        if first is None:
            first = loss.item()
            for name in ("resnet.stem.0.weight", "ray_mlp.fc1.weight", "latents", "query.mlp.fc1.weight"):
                g = dict(m.named_parameters())[name].grad
                assert g is not None and g.abs().sum() > 0, name
        opt.step()
        if loss.item() < min(first, math.log(2)) / 10:
            break
    assert loss.item() < min(first, math.log(2)) / 10, (first, loss.item())
