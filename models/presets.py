"""Model sizes per preset.

"paper": CoBEVT supplementary Table A2 / Sec. 3.3 (C = 128, F = 32, decoder 128/64/32,
FuseBEVT 3 blocks, window 8, 4 heads, MLP 256) with PointPillars as in Lang et al. 2019
(64-channel PFN, backbone 64/128/256 with 4/6/6 layers, three 128-channel upsamplings).
"tiny": CPU preset (C = 64, F = 64: 1.56 m cells over 100 m), narrow and shallow PointPillars; a zoo
trained before the grid was chosen (manifest "cells": 32) keeps its own grid.
The fusion methods' sizes per preset are declared in each method's own file (models/fusion/*.py, METHOD's
preset_kwargs; models.declared).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PointPillarsConfig:
    """PointPillars encoder sizes (pillar grid + PFN + 2D backbone + shrink header)."""

    voxel_m: float = 0.4  # pillar size in x and y (Sec. 3.3: 0.4 x 0.4 x 4 m)
    z_range: tuple[float, float] = (-1.0, 3.0)  # body-frame z kept (4 m pillar height)
    max_points: int = 32  # points kept per pillar
    pfn_channels: int = 64
    stage_channels: tuple[int, int, int] = (64, 128, 256)
    stage_layers: tuple[int, int, int] = (4, 6, 6)  # conv layers per stage, the first one strided
    stage_strides: tuple[int, int, int] = (2, 2, 2)
    up_channels: tuple[int, int, int] = (128, 128, 128)
    shrink_channels: int = 256  # first stride-2 conv of the shrink header; the rest use C


@dataclass(frozen=True)
class ModelPreset:
    """All sizes of one preset; C x F x F is the shared fusion feature map.

    `cells` is the LiDAR (PointPillars) fusion grid F over the 100 m BEV square; a zoo records the grid it
    was trained at (models.zoo), so the preset's value is the default of a newly trained zoo. The camera
    encoders' grid is their own (SinBEVT's output, Table A2: 32 x 32), `camera_cells` here.
    """

    name: str
    channels: int  # C
    cells: int  # F of the LiDAR track
    pointpillars: PointPillarsConfig
    decoder_channels: tuple[int, int, int]  # Table A2 decoder, after each x2 upsampling
    camera_cells: int = 32
    seg_cells: int = 256  # final segmentation grid (Table A2: 256 x 256)
    anchor_size: tuple[float, float] = (4.5, 1.9)  # (l, w) of the detection anchors
    anchor_yaws: tuple[float, ...] = (0.0, 1.5707963267948966)


PRESETS: dict[str, ModelPreset] = {
    "paper": ModelPreset(
        name="paper",
        channels=128,
        cells=32,
        pointpillars=PointPillarsConfig(),
        decoder_channels=(128, 64, 32),
    ),
    "tiny": ModelPreset(
        name="tiny",
        channels=64,
        cells=64,  # 1.56 m cells (docs/results.md, "Choosing the LiDAR grid")
        pointpillars=PointPillarsConfig(
            pfn_channels=16,
            stage_channels=(16, 32, 64),
            stage_layers=(2, 3, 3),
            stage_strides=(2, 2, 2),
            up_channels=(16, 16, 32),
            shrink_channels=64,
        ),
        decoder_channels=(32, 16, 16),
    ),
}


def get_preset(name: str) -> ModelPreset:
    """The preset called `name`; ValueError listing the known ones otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; allowed: {', '.join(sorted(PRESETS))}") from None
