"""models.registry: build every name, reject unknown ones, describe the models, compose the pipeline."""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import pytest
import torch

from models.build import build_cooperative, build_encoder, build_fusion, build_heads
from models.describe import describe_models, format_models_table
from models.fusion.base import FusionModule
from models.presets import PRESETS, get_preset
from models.registry import ENCODERS, FUSION, METHODS, intermediate_methods, is_intermediate


def test_tables() -> None:
    assert set(ENCODERS) == {"pointpillars", "sinbevt", "lara"}
    assert set(FUSION) == {"none", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt"}
    assert METHODS == ["none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt"]
    assert intermediate_methods() == ["attfuse", "fcooper", "v2vnet", "disconet", "cobevt"]
    assert not is_intermediate("late") and not is_intermediate("none") and is_intermediate("cobevt")


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_builds_every_fusion_and_heads(preset: str) -> None:
    c = get_preset(preset).channels
    for name in FUSION:
        m = build_fusion(name, preset)
        assert isinstance(m, torch.nn.Module)
        if name != "cobevt":
            assert isinstance(m, FusionModule) and m.channels == c
    for modality in ("lidar", "camera"):
        assert build_heads(modality, preset).decoder.channels == get_preset(preset).decoder_channels


@pytest.mark.parametrize("name", sorted(ENCODERS))
def test_builds_every_encoder(name: str) -> None:
    enc = build_encoder(name, "tiny")
    assert (enc.out_channels, enc.out_cells) == (64, 64 if name == "pointpillars" else 32)
    paper = build_encoder(name, "paper")
    assert (paper.out_channels, paper.out_cells) == (128, 32)


@pytest.mark.parametrize(
    "call",
    [
        lambda: build_encoder("pointnet", "tiny"),
        lambda: build_fusion("where2comm", "tiny"),
        lambda: build_fusion("late", "tiny"),
        lambda: build_encoder("pointpillars", "huge"),
        lambda: build_cooperative("pointpillars", "magic", "tiny"),
        lambda: is_intermediate("magic"),
    ],
)
def test_unknown_names_are_rejected_with_the_allowed_list(call: Callable[[], object]) -> None:
    with pytest.raises(ValueError, match="allowed"):
        call()


def test_error_lists_the_names() -> None:
    with pytest.raises(ValueError) as e:
        build_fusion("nope", "tiny")
    for n in FUSION:
        assert n in str(e.value)


def _lidar_batch(b: int = 1, l: int = 3) -> tuple[list, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    clouds = [
        [torch.rand(3000, 4, generator=g) * torch.tensor([60.0, 60.0, 2.0, 1.0]) - torch.tensor([30.0, 30.0, 0.5, 0.0])
         for _ in range(l)]
        for _ in range(b)
    ]  # fmt: skip
    poses = torch.zeros(b, l, 3)
    poses[:, 1:] = torch.tensor([8.0, -3.0, math.pi / 2])
    valid = torch.ones(b, l, dtype=torch.bool)
    valid[:, -1] = False
    return clouds, poses, valid


@pytest.mark.parametrize("method", METHODS)
def test_cooperative_forward_and_predict_every_method(method: str) -> None:
    torch.manual_seed(0)
    model = build_cooperative("pointpillars", method, "tiny").eval()
    clouds, poses, valid = _lidar_batch()
    with torch.no_grad():
        out = model(clouds, poses, valid)
        # an absent agent's data does not matter
        clouds[0][-1] = torch.full((100, 4), 7.0)
        out2 = model(clouds, poses, valid)
    assert out["dynamic"].shape == (1, 2, 256, 256) and out["static"].shape == (1, 3, 256, 256)
    assert out["det_cls"].shape == (1, 2, 128, 128) and out["fused"].shape == (1, 64, 64, 64)
    assert torch.equal(out["dynamic"], out2["dynamic"])


@pytest.mark.parametrize("cells", [32, 64, 128])
def test_every_lidar_grid_decodes_to_the_same_maps(cells: int) -> None:
    """The tiny preset's LiDAR grid is 64 x 64 (1.56 m cells); 32 and 128 build too (the grid study). Whatever
    the grid: features C x F x F, the same 256 x 256 segmentation and 128 x 128 anchors, the decoder's three
    stages with the first upsamplings skipped on a finer grid."""
    model = build_cooperative("pointpillars", "cobevt", "tiny", cells=cells).eval()
    clouds, poses, valid = _lidar_batch()
    with torch.no_grad():
        out = model(clouds, poses, valid)
    assert out["features"].shape[2:] == (64, cells, cells) and out["fused"].shape == (1, 64, cells, cells)
    assert out["dynamic"].shape == (1, 2, 256, 256) and out["det_cls"].shape == (1, 2, 128, 128)
    assert model.anchors.shape == (128 * 128 * 2, 5)
    assert model.heads.decoder.scales == {32: (2, 2, 2), 64: (1, 2, 2), 128: (1, 1, 2)}[cells]
    assert build_cooperative("pointpillars", "none", "tiny").encoder.out_cells == get_preset("tiny").cells == 64
    assert build_cooperative("sinbevt", "none", "tiny").heads.in_cells == 32  # the camera grid is its own
    with pytest.raises(ValueError, match="cannot be decoded"):
        build_heads("lidar", "tiny", 48)


def test_camera_pipeline_rejects_early() -> None:
    with pytest.raises(ValueError, match="LiDAR"):
        build_cooperative("sinbevt", "early", "tiny")


def test_describe_models_tiny() -> None:
    rows = describe_models("tiny")
    names = [r["name"] for r in rows]
    for n in [*ENCODERS, *FUSION, "late", "early", "heads-lidar", "heads-camera"]:
        assert n in names
    by = {r["name"]: r for r in rows}
    assert by["pointpillars"]["output"] == [1, 64, 64, 64]
    assert by["sinbevt"]["output"] == [1, 64, 32, 32]
    assert by["fcooper"]["output"] == [1, 64, 64, 64]
    assert by["heads-lidar"]["stages"][0]["shape"] == [1, 32, 64, 64]  # no upsampling before the first conv
    assert by["heads-lidar"]["stages"][2]["shape"] == [1, 16, 256, 256]
    assert by["heads-camera"]["stages"][0]["shape"] == [1, 32, 64, 64]
    assert by["heads-camera"]["stages"][2]["shape"] == [1, 16, 256, 256]
    assert all(r["params"] >= 0 for r in rows)
    json.dumps(rows)
    table = format_models_table(rows)
    assert "pointpillars" in table and "cobevt" in table and "bracket" in table
    assert format_models_table([]).startswith("name")


@pytest.mark.parametrize("method", ["attfuse", "late"])
def test_camera_pipeline(method: str) -> None:
    torch.manual_seed(0)
    model = build_cooperative("lara", method, "tiny").eval()
    images, intr, extr = model.encoder.example_inputs(batch=2)  # 2 agents of one batch item
    inputs = (images[None], intr[None], extr[None])  # [1, L=2, M, ...]
    poses = torch.tensor([[[0.0, 0.0, 0.0], [5.0, 2.0, 0.4]]])
    valid = torch.tensor([[True, True]])
    with torch.no_grad():
        out = model(inputs, poses, valid)
    assert out["dynamic"].shape == (1, 2, 256, 256) and "det_cls" not in out


def test_cobevt_fuses_as_many_agents_as_a_scenario_allows() -> None:
    """cavs.count goes up to 16: the FuseBEVT bias table must cover 16 agents."""
    import torch

    from models.build import build_fusion

    fusion = build_fusion("cobevt", "tiny").eval()
    x = torch.randn(1, 16, 64, 8, 8)
    with torch.no_grad():
        assert fusion(x, torch.ones(1, 16, dtype=torch.bool)).shape == (1, 64, 8, 8)


def test_early_fusion_takes_a_padded_batch() -> None:
    """A training batch pads rel_poses / valid to its largest agent count; early fusion merges only the
    clouds each item has (regression: 'N clouds, M poses')."""
    torch.manual_seed(0)
    model = build_cooperative("pointpillars", "early", "tiny").eval()
    g = torch.Generator().manual_seed(1)
    clouds = [[torch.rand(400, 4, generator=g) * 20 for _ in range(3)], [torch.rand(400, 4, generator=g) * 20]]
    poses = torch.zeros(2, 3, 3)
    valid = torch.tensor([[True, True, True], [True, False, False]])
    with torch.no_grad():
        out = model(clouds, poses, valid)
        alone = model([clouds[1]], poses[1:, :1], valid[1:, :1])
    assert out["dynamic"].shape == (2, 2, 256, 256)
    assert torch.allclose(out["dynamic"][1], alone["dynamic"][0], atol=1e-5)
