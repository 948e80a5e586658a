"""The scenario schema's `sensors`, `bev`, `perception` and `evaluation` sections (DESIGN.md "Scenario YAML"): what
each CAV senses, the BEV grid, the encoder and fusion methods that run on it and how they are scored; and the
constants these sections are checked against."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Literal

from models.registry import BUILTIN_METHODS, METHODS  # (imports no torch)
from v2vsim.config.schema_fields import _f, _nonneg, _pos, _prob

ENCODERS_BY_MODALITY = {"lidar": ("pointpillars",), "camera": ("sinbevt", "lara")}
DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")  # perception.device (v2vsim.perception.device resolves it)


class _Methods:
    """What perception.methods allows, spelled when an error needs it: the registry's methods (models.registry:
    the built-ins and every installed fusion plugin, whose entry points are read only then)."""

    def __str__(self) -> str:
        return f"a non-empty list of {', '.join(METHODS)}"


@dataclass(frozen=True)
class LidarConfig:
    channels: int = _f(32, ">= 1", _pos)
    points_per_channel: int = _f(1024, ">= 1", _pos)
    range_m: float = _f(100.0, "> 0", _pos)
    vertical_fov_deg: tuple[float, float] = _f((-25.0, 5.0), "[lo, hi] with -90 <= lo < hi <= 90",
                                               lambda v: -90 <= v[0] < v[1] <= 90)
    height_m: float = _f(1.9, "> 0", _pos)
    noise_std_m: float = _f(0.02, ">= 0", _nonneg)
    dropout: float = _f(0.0, "0..1", _prob)


@dataclass(frozen=True)
class CamerasConfig:
    count: int = _f(4, "4 (front, right, left, back)", lambda v: v == 4)
    fov_deg: float = _f(110.0, "0 < fov < 180", lambda v: 0 < v < 180)
    width: int = _f(800, ">= 16", lambda v: v >= 16)
    height: int = _f(600, ">= 16", lambda v: v >= 16)
    render_scale: float = _f(0.25, "0 < scale <= 1", lambda v: 0 < v <= 1)
    height_m: float = _f(1.6, "> 0 (mount height)", _pos)


@dataclass(frozen=True)
class SensorsConfig:
    lidar: LidarConfig = field(default_factory=LidarConfig)
    cameras: CamerasConfig = field(default_factory=CamerasConfig)


@dataclass(frozen=True)
class BevConfig:
    size_m: float = _f(100.0, "> 0", _pos)
    cells: int = _f(256, ">= 8", lambda v: v >= 8)


@dataclass(frozen=True)
class PerceptionConfig:
    modality: Literal["lidar", "camera"] = "lidar"
    encoder: Literal["pointpillars", "sinbevt", "lara"] = "pointpillars"
    preset: Literal["tiny", "paper"] = "tiny"
    # default: the built-in methods; a fusion plugin (models.registry) runs when named here or in --methods
    methods: tuple[str, ...] = _f(BUILTIN_METHODS, _Methods(), lambda v: len(v) > 0 and all(m in METHODS for m in v))
    weights: str = _f("auto", "'auto', 'none' or a checkpoint path")
    # the models' forward passes (v2vsim.perception.precision): auto = bf16 autocast where the CPU has native
    # bfloat16 (AMX, AVX-512 BF16), fp32 elsewhere; metrics.json says which ran
    precision: Literal["auto", "fp32", "bf16"] = "fp32"
    # where each process's models run (v2vsim.perception.device): auto = the GPU where torch sees one, else the CPU
    # (so a CPU host runs exactly as before); whether the host has the device is checked before any process starts
    # (the loader imports no torch); metrics.json "device" says what ran
    device: str = _f("auto", "auto, cpu, cuda or cuda:N", lambda v: DEVICE_PATTERN.fullmatch(v) is not None)
    # how many methods the ego fuses at once, each on its own thread (every prediction bit-identical to one at a
    # time; v2vsim.perception.threads): 0 = auto
    fusion_threads: int = _f(0, "0 (auto) or a positive integer", lambda v: v >= 0)


@dataclass(frozen=True)
class EvaluationConfig:
    # How AP ranks detections: 'global' sorts every detection of the run by score (OpenCOOD's
    # --global_sort_detections, the DESIGN.md default); 'per_frame' keeps frame order and sorts
    # only within each frame (OpenCOOD's default, which most published AP tables use).
    ap_sort: Literal["global", "per_frame"] = "global"
