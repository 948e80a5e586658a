"""SinBEVT camera encoder (CoBEVT supp. Sec. 3.1, Table A2): multi-camera images -> one agent's BEV map.

    images [B, M, 3, h, w] -> resize to the preset size -> image backbone at strides 8/16/32
        (models/image_backbone.py: ResNet-34 layer1..3 as in Table A2, or ImageNet EfficientNet-Lite0)
    learnable BEV query Q0 [C, H0, W0]
    stages.0: FAX-CA(Q0, layer1) + 2 residual bottlenecks                   -> [B, C, H0, W0]
    stages.1: downsample, FAX-CA(., layer2) + 2 residual bottlenecks       -> [B, C, H1, W1]
    stages.2: downsample, FAX-CA(., layer3) + 2 residual bottlenecks       -> [B, C, H2, W2]

Stage submodules (forward-hook names): the backbone's three maps, e.g. ``resnet.layer1..3`` or
``efficientnet.net._blocks.4/10/15`` (outputs [B*M, C, h, w]), and ``stages.0``, ``stages.1``, ``stages.2``
(outputs [B, C, H, W]); ``stage_shapes()`` reports them. Paper preset: 128x128x128 -> 64x64x128 ->
32x32x128 from 64x64x128, 32x32x256, 16x16x512 image features of 512x512 inputs (Table A2).

Camera-aware positional embedding (CVT style, per stage): each feature pixel's ray direction
K^-1 [u, v, 1] rotated to the agent frame is embedded and the camera-centre embedding subtracted;
each BEV cell's agent-frame (x, y) is embedded and the same camera-centre embedding subtracted; both
are L2-normalised. Keys = image embedding + projected features, values = projected features,
queries (per camera) = BEV features + BEV embedding, so q.k compares "direction from this camera to
the cell" with "direction of this pixel's ray".

Frames: camera OpenCV (x right, y down, z forward); extrinsics are camera-to-agent-body (x forward,
y left, z up). The output grid follows v2vsim.world.geometry.BevGrid: row 0 = front (+x), column 0 = left
(+y), cell (r, c) centre at x = S/2 - (r + 0.5) S/F, y = S/2 - (c + 0.5) S/F over S = ``bev_size_m``.
Intrinsics use the continuous pixel convention (the image spans [0, w] x [0, h]).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.fax import FAXCrossAttention, trunc_normal_init
from models.image_backbone import build_image_backbone
from models.resnet import record_stage_shapes


@dataclass(frozen=True)
class SinBEVTConfig:
    """Sizes of a SinBEVT build (see PRESETS)."""

    image_size: tuple[int, int]  # (h, w) the images are resized to inside the model
    raw_image_size: tuple[int, int]  # (h, w) of the simulator's camera images (example inputs only)
    resnet_width: float
    resnet_blocks: tuple[int, int, int, int]
    dim: int  # BEV channels C (= out_channels)
    heads: int
    mlp_dim: int
    bev_sizes: tuple[int, int, int]  # BEV query side per stage (output side = last)
    bev_windows: tuple[int, int, int]  # FAX-CA BEV window = grid size per stage
    feat_windows: tuple[int, int, int]  # FAX-CA image-feature window = grid size per stage
    bottlenecks: int = 2  # residual bottleneck blocks after each FAX-CA
    cameras: int = 4  # default camera count for example inputs
    fov_deg: float = 110.0  # example-input camera field of view
    backbone: str = "resnet"  # image backbone (models.image_backbone): "resnet" | "efficientnet_lite0"


PRESETS: dict[str, SinBEVTConfig] = {
    # Table A2 exactly: 512x512 images, ResNet-34, BEV 128 -> 64 -> 32, dim 128, 4 heads, MLP 256.
    "paper": SinBEVTConfig(
        image_size=(512, 512),
        raw_image_size=(600, 800),
        resnet_width=1.0,
        resnet_blocks=(3, 4, 6, 3),
        dim=128,
        heads=4,
        mlp_dim=256,
        bev_sizes=(128, 64, 32),
        bev_windows=(16, 16, 32),
        feat_windows=(8, 8, 16),
    ),
    # Same architecture, narrower and smaller for CPU: 200x150 renders (800x600 * 0.25) resized to
    # 128x128, ImageNet-pretrained EfficientNet-Lite0 with features 16x16x40, 8x8x112, 4x4x320 (the same
    # strides as Table A2's ResNet-34), BEV 64 -> 32 -> 32 (the last stage keeps 32 so the output is
    # 32x32), dim 64. backbone="resnet" is the from-scratch half-width ResNet (2 blocks per stage, features
    # 16x16x64, 8x8x128, 4x4x256) of the first camera zoo.
    "tiny": SinBEVTConfig(
        image_size=(128, 128),
        raw_image_size=(150, 200),
        resnet_width=0.5,
        resnet_blocks=(2, 2, 2, 2),
        dim=64,
        heads=4,
        mlp_dim=128,
        bev_sizes=(64, 32, 32),
        bev_windows=(16, 16, 32),
        feat_windows=(4, 4, 4),
        backbone="efficientnet_lite0",
    ),
}


# --------------------------------------------------------------------------------------------------
# Camera and BEV geometry helpers (shared with models/lara.py)
# --------------------------------------------------------------------------------------------------


def resize_images(images: Tensor, intrinsics: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Resize [B, M, 3, h, w] images to ``size`` (h', w') and scale [B, M, 3, 3] intrinsics to match."""
    b, m, _, h, w = images.shape
    if (h, w) == tuple(size):
        return images, intrinsics
    x = F.interpolate(images.flatten(0, 1), size=size, mode="bilinear", align_corners=False, antialias=True)
    scale = torch.tensor([size[1] / w, size[0] / h, 1.0], dtype=intrinsics.dtype, device=intrinsics.device)
    return x.reshape(b, m, 3, *size), intrinsics * scale[:, None]  # rows 0/1 scaled by sx/sy


def feature_rays(intrinsics: Tensor, extrinsics: Tensor, image_hw: tuple[int, int], feat_hw: tuple[int, int]) -> Tensor:
    """Agent-frame ray directions K^-1 [u, v, 1] rotated by the extrinsics at each feature-pixel centre.

    intrinsics [B, M, 3, 3] (pixels of an ``image_hw`` image), extrinsics [B, M, 4, 4] camera-to-agent
    -> [B, M, fh, fw, 3] (camera-frame z = 1, not unit length).
    """
    (h, w), (fh, fw) = image_hw, feat_hw
    dev, dt = intrinsics.device, intrinsics.dtype
    v = (torch.arange(fh, device=dev, dtype=dt) + 0.5) * (h / fh)
    u = (torch.arange(fw, device=dev, dtype=dt) + 0.5) * (w / fw)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    pix = torch.stack([uu, vv, torch.ones_like(uu)], dim=-1)  # [fh, fw, 3]
    k_inv = torch.linalg.inv(intrinsics)  # [B, M, 3, 3]
    rot = extrinsics[..., :3, :3] @ k_inv  # [B, M, 3, 3]
    return torch.einsum("bmij,hwj->bmhwi", rot, pix)


def camera_centres(extrinsics: Tensor) -> Tensor:
    """[B, M, 4, 4] camera-to-agent -> [B, M, 3] camera centres in the agent frame."""
    return extrinsics[..., :3, 3]


def bev_cell_xy(cells: int, size_m: float) -> Tensor:
    """[cells, cells, 2] agent-frame (x, y) of BEV cell centres (BevGrid convention: row 0 front, col 0 left)."""
    coord = size_m / 2 - (torch.arange(cells, dtype=torch.float32) + 0.5) * (size_m / cells)
    xs, ys = torch.meshgrid(coord, coord, indexing="ij")
    return torch.stack([xs, ys], dim=-1)


def default_camera_rig(
    batch: int, cameras: int, height: int, width: int, fov_deg: float = 110.0, mount_height: float = 1.9
) -> tuple[Tensor, Tensor]:
    """Example rig: ``cameras`` cameras evenly spaced in yaw (4: front, right, left, back as in OPV2V).

    Returns intrinsics [B, M, 3, 3] and camera-to-agent extrinsics [B, M, 4, 4].
    """
    yaws = [0.0, -math.pi / 2, math.pi / 2, math.pi] if cameras == 4 else [
        2 * math.pi * i / cameras for i in range(cameras)
    ]
    f = (width / 2) / math.tan(math.radians(fov_deg) / 2)
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    ext = []
    for yaw in yaws:
        c, s = math.cos(yaw), math.sin(yaw)
        e = torch.eye(4)
        # columns = agent-frame images of camera x (right), y (down), z (forward)
        e[:3, :3] = torch.tensor([[s, 0.0, c], [-c, 0.0, s], [0.0, -1.0, 0.0]])
        e[:3, 3] = torch.tensor([0.0, 0.0, mount_height])
        ext.append(e)
    intr = k.expand(batch, cameras, 3, 3).clone()
    extr = torch.stack(ext).expand(batch, cameras, 4, 4).clone()
    return intr, extr


def l2_normalize(x: Tensor, dim: int = -1) -> Tensor:
    return x / (x.norm(dim=dim, keepdim=True) + 1e-7)


# --------------------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------------------


class CameraAwareEmbedding(nn.Module):
    """CVT-style camera-aware positional embedding for one SinBEVT stage.

    img_pos[m, pixel] = norm(E_img(R_m K_m^-1 [u, v, 1]) - E_cam(c_m))
    bev_pos[m, cell]  = norm(E_bev(xy_cell) - E_cam(c_m))
    Positions are in units of ``pos_scale`` metres (half the BEV side).
    """

    def __init__(self, dim: int, pos_scale: float) -> None:
        super().__init__()
        self.pos_scale = pos_scale
        self.img_embed = nn.Linear(3, dim, bias=False)
        self.cam_embed = nn.Linear(3, dim, bias=False)
        self.bev_embed = nn.Linear(2, dim)

    def forward(self, rays: Tensor, centres: Tensor, bev_xy: Tensor) -> tuple[Tensor, Tensor]:
        """rays [B, M, h, w, 3], centres [B, M, 3], bev_xy [H, W, 2] (metres)
        -> img_pos [B, M, h, w, C], bev_pos [B, M, H, W, C]."""
        cam = self.cam_embed(centres / self.pos_scale)[:, :, None, None]  # [B, M, 1, 1, C]
        img_pos = l2_normalize(self.img_embed(rays) - cam)
        bev_pos = l2_normalize(self.bev_embed(bev_xy / self.pos_scale)[None, None] - cam)
        return img_pos, bev_pos


class Bottleneck(nn.Module):
    """Residual bottleneck block (1x1 reduce /4, 3x3, 1x1 expand, BN) used after each FAX-CA (Table A2)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        mid = max(dim // 4, 8)
        self.body = nn.Sequential(
            nn.Conv2d(dim, mid, 1, bias=False),
            nn.BatchNorm2d(mid),
            nn.ReLU(inplace=True),
            nn.Conv2d(mid, mid, 3, padding=1, bias=False),
            nn.BatchNorm2d(mid),
            nn.ReLU(inplace=True),
            nn.Conv2d(mid, dim, 1, bias=False),
            nn.BatchNorm2d(dim),
        )
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:  # [B, C, H, W] -> same
        return self.relu(x + self.body(x))


class SinBEVTStage(nn.Module):
    """One Table A2 SinBEVT row: [downsample] -> FAX-CA with one image-feature scale -> bottlenecks x2."""

    def __init__(
        self,
        dim: int,
        feat_dim: int,
        heads: int,
        mlp_dim: int,
        bev_window: int,
        feat_window: int,
        bev_cells: int,
        downsample: bool,
        bottlenecks: int,
        bev_size_m: float,
    ) -> None:
        super().__init__()
        self.down: nn.Module = nn.Identity()
        if downsample:
            self.down = nn.Sequential(
                nn.Conv2d(dim, dim, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(dim), nn.ReLU(inplace=True)
            )
        self.embed = CameraAwareEmbedding(dim, bev_size_m / 2)
        self.key_proj = nn.Sequential(nn.BatchNorm2d(feat_dim), nn.ReLU(), nn.Conv2d(feat_dim, dim, 1, bias=False))
        self.val_proj = nn.Sequential(nn.BatchNorm2d(feat_dim), nn.ReLU(), nn.Conv2d(feat_dim, dim, 1, bias=False))
        self.cross = FAXCrossAttention(dim, heads, bev_window, feat_window, mlp_dim)
        self.blocks = nn.Sequential(*[Bottleneck(dim) for _ in range(bottlenecks)])
        self.register_buffer("bev_xy", bev_cell_xy(bev_cells, bev_size_m), persistent=False)  # [H, W, 2]

    def forward(self, x: Tensor, feats: Tensor, rays: Tensor, centres: Tensor) -> Tensor:
        """x [B, C, H', W'] BEV, feats [B*M, Cf, h, w], rays [B, M, h, w, 3], centres [B, M, 3] -> [B, C, H, W]."""
        x = self.down(x)
        b, m = centres.shape[:2]
        img_pos, bev_pos = self.embed(rays, centres, self.bev_xy)
        key = self.key_proj(feats).unflatten(0, (b, m)).permute(0, 1, 3, 4, 2) + img_pos  # [B, M, h, w, C]
        val = self.val_proj(feats).unflatten(0, (b, m)).permute(0, 1, 3, 4, 2)
        x = self.cross(x.permute(0, 2, 3, 1), bev_pos, key, val).permute(0, 3, 1, 2)  # [B, C, H, W]
        return self.blocks(x.contiguous())


# --------------------------------------------------------------------------------------------------
# SinBEVT
# --------------------------------------------------------------------------------------------------


class CameraEncoderIntrospection:
    """`example_inputs` and `stage_shapes` shared by the camera encoders (for `v2vsim models`).

    Needs `config.cameras`, `config.raw_image_size`, `config.fov_deg`, `stage_names`, and
    `per_camera_stages`: the stage-name prefixes whose outputs are per camera ([B*M, ...]).
    """

    per_camera_extra: tuple[str, ...] = ()  # per-camera stages after the backbone

    @property
    def image_backbone(self) -> nn.Module:
        return getattr(self, self.backbone_attr)  # type: ignore[attr-defined]

    @property
    def per_camera_stages(self) -> tuple[str, ...]:
        return (f"{self.backbone_attr}.", *self.per_camera_extra)  # type: ignore[attr-defined]

    @property
    def stage_names(self) -> tuple[str, ...]:
        backbone = tuple(f"{self.backbone_attr}.{n}" for n in self.image_backbone.stage_names)  # type: ignore
        return (*backbone, *self.head_stage_names)  # type: ignore[attr-defined]

    def example_inputs(self, batch: int = 1, cameras: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Random images at the simulator's raw camera size with the default 4-camera rig."""
        m = cameras or self.config.cameras  # type: ignore[attr-defined]
        h, w = self.config.raw_image_size  # type: ignore[attr-defined]
        intr, extr = default_camera_rig(batch, m, h, w, self.config.fov_deg)  # type: ignore[attr-defined]
        return torch.rand(batch, m, 3, h, w), intr, extr

    def stage_shapes(self, inputs: Sequence[Tensor] | None = None) -> list[tuple[str, tuple[int, ...]]]:
        """(stage name, output shape) for `stage_names`; per-camera outputs shown as (B, M, C, h, w)."""
        images, intr, extr = inputs if inputs is not None else self.example_inputs()
        b, m = images.shape[:2]
        shapes = record_stage_shapes(self, self.stage_names, lambda: self(images, intr, extr))  # type: ignore
        return [(n, (b, m, *s[1:]) if n.startswith(self.per_camera_stages) else s) for n, s in shapes]


class SinBEVT(CameraEncoderIntrospection, nn.Module):
    """SinBEVT (CoBEVT Table A2): forward(images, intrinsics, extrinsics) -> [B, C, F, F] BEV features."""

    def __init__(self, config: SinBEVTConfig, bev_size_m: float = 100.0) -> None:
        super().__init__()
        cfg = config
        self.config = cfg
        self.bev_size_m = bev_size_m
        self.backbone_attr, backbone = build_image_backbone(cfg.backbone, cfg.resnet_width, cfg.resnet_blocks)
        self.add_module(self.backbone_attr, backbone)
        self.out_channels: int = cfg.dim
        self.out_cells: int = cfg.bev_sizes[-1]
        h0 = cfg.bev_sizes[0]
        self.bev_query = nn.Parameter(torch.randn(cfg.dim, h0, h0))  # learnable Q0 [C, H0, W0]
        stages = []
        for i in range(3):
            feat_side = (-(-cfg.image_size[0] // backbone.strides[i]), -(-cfg.image_size[1] // backbone.strides[i]))
            bev = cfg.bev_sizes[i]
            bev_groups = (bev // cfg.bev_windows[i]) ** 2
            feat_groups = (feat_side[0] // cfg.feat_windows[i]) * (feat_side[1] // cfg.feat_windows[i])
            if bev % cfg.bev_windows[i] or feat_side[0] % cfg.feat_windows[i] or feat_side[1] % cfg.feat_windows[i]:
                raise ValueError(f"stage {i}: windows must divide BEV {bev} and features {feat_side}")
            if bev_groups != feat_groups:
                raise ValueError(f"stage {i}: {bev_groups} BEV windows != {feat_groups} feature windows")
            prev = cfg.bev_sizes[i - 1] if i else bev
            if prev not in (bev, 2 * bev):
                raise ValueError(f"stage {i}: BEV side {prev} -> {bev} (only /1 or /2 supported)")
            stages.append(
                SinBEVTStage(
                    cfg.dim,
                    backbone.out_channels[i],
                    cfg.heads,
                    cfg.mlp_dim,
                    cfg.bev_windows[i],
                    cfg.feat_windows[i],
                    bev,
                    downsample=prev == 2 * bev,
                    bottlenecks=cfg.bottlenecks,
                    bev_size_m=bev_size_m,
                )
            )
        self.stages = nn.ModuleList(stages)
        for s in self.stages:
            trunc_normal_init(s.cross)
            trunc_normal_init(s.embed)

    def forward(self, images: Tensor, intrinsics: Tensor, extrinsics: Tensor) -> Tensor:
        """images [B, M, 3, h, w] in [0, 1], intrinsics [B, M, 3, 3] (pixels), extrinsics [B, M, 4, 4]
        camera-to-agent -> [B, C, F, F] (row 0 = front, column 0 = left)."""
        b, m = images.shape[:2]
        intrinsics, extrinsics = intrinsics.to(images.dtype), extrinsics.to(images.dtype)
        images, intrinsics = resize_images(images, intrinsics, self.config.image_size)
        x = self.image_backbone.normalise(images.flatten(0, 1))  # [B*M, 3, H, W]
        feats = self.image_backbone(x)  # 3 x [B*M, Ci, hi, wi]
        centres = camera_centres(extrinsics)
        bev = self.bev_query[None].expand(b, -1, -1, -1)  # [B, C, H0, W0]
        for stage, f in zip(self.stages, feats, strict=True):
            rays = feature_rays(intrinsics, extrinsics, self.config.image_size, tuple(f.shape[-2:]))
            bev = stage(bev, f, rays, centres)
        return bev

    # -- introspection --------------------------------------------------------------------------

    head_stage_names: tuple[str, ...] = ("stages.0", "stages.1", "stages.2")  # after the backbone's



def build_sinbevt(preset: str, bev_size_m: float = 100.0, **overrides: object) -> SinBEVT:
    """SinBEVT for ``preset`` in PRESETS ("tiny", "paper"); ``overrides`` replace SinBEVTConfig fields."""
    if preset not in PRESETS:
        raise ValueError(f"unknown SinBEVT preset {preset!r}; choose from {sorted(PRESETS)}")
    return SinBEVT(replace(PRESETS[preset], **overrides), bev_size_m=bev_size_m)
