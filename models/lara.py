"""LaRa camera encoder (LaRa supp. Sec. A, Eq. 5-12): images -> latent array -> BEV map.

    images [B, M, 3, h, w] -> resize -> image backbone at strides 8/16/32 (models/image_backbone.py: ImageNet
    EfficientNet-Lite0, LaRa's family, or a from-scratch ResNet) -> ``neck``: FPN-lite sum at stride 8
    (LaRa uses one stride-8 map with c = 128)                      -> [B*M, c, h/8, w/8]
    camera-ray embedding per feature pixel: MLP_ray(origin, unit direction) (or Plücker (d, o x d)),
    concatenated to the features                                   -> input tokens [B, M*h*w, c + c_ray]
    ``encode``  latent-input cross-attention (Eq. 8), residual     -> latents [B, L, D]
    ``process`` latent self-attention stack (Eq. 9)                -> latents [B, L, D]
    ``query``   BEV queries: Fourier (Eq. 11-12) or raw coordinates of the F x F BEV cells, MLP_bev
    ``decode``  BEV-query-to-latent cross-attention, NOT residual (Eq. 10) -> [B, F*F, Dq]
    ``head``    Linear Dq -> C, reshaped                            -> [B, C, F, F]

Stage submodules (forward-hook names): the backbone's three maps (e.g. ``efficientnet.net._blocks.4``),
``neck``, ``encode``, ``process``, ``decode``, ``head``; ``stage_shapes()`` reports them. The output has
SinBEVT's shape for the preset (paper [B, 128, 32, 32], tiny [B, 64, 32, 32]) on the same BevGrid
convention (row 0 front, col 0 left).
Latent count/width and layer counts are our choices (the supplement defers them to the code).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from models.fax import Mlp
from models.image_backbone import build_image_backbone
from models.sinbevt import (
    CameraEncoderIntrospection,
    bev_cell_xy,
    camera_centres,
    feature_rays,
    l2_normalize,
    resize_images,
)


@dataclass(frozen=True)
class LaRaConfig:
    """Sizes of a LaRa build (see PRESETS)."""

    image_size: tuple[int, int]  # (h, w) images are resized to inside the model
    raw_image_size: tuple[int, int]  # simulator camera size (example inputs only)
    resnet_width: float
    resnet_blocks: tuple[int, int, int, int]
    feat_dim: int  # c: image feature channels at stride 8
    ray_dim: int  # MLP_ray output, concatenated to the features
    num_latents: int  # L
    latent_dim: int  # D
    latent_layers: int  # Eq. 9 repeats
    cross_heads: int  # heads of Eq. 8 and Eq. 10
    latent_heads: int  # heads of Eq. 9
    query_dim: int  # MLP_bev output Dq
    out_channels: int  # C
    out_cells: int  # F
    bev_query: str = "fourier"  # "fourier" (Eq. 11-12) | "coords"
    fourier_bands: int = 16  # B; f_B = Nyquist of the F-cell grid (F / 2)
    ray_encoding: str = "origin_dir"  # "origin_dir" (o, d) | "plucker" (d, o x d)
    mlp_ratio: int = 2
    cameras: int = 4
    fov_deg: float = 110.0
    backbone: str = "resnet"  # image backbone (models.image_backbone): "resnet" | "efficientnet_lite0"


PRESETS: dict[str, LaRaConfig] = {
    # Same image encoder and input size as SinBEVT "paper" (ResNet-34 on 512x512, stride-8 c = 128 as in
    # LaRa), 512 latents of width 256, 4 self-attention layers; output 32x32x128 like SinBEVT.
    "paper": LaRaConfig(
        image_size=(512, 512),
        raw_image_size=(600, 800),
        resnet_width=1.0,
        resnet_blocks=(3, 4, 6, 3),
        feat_dim=128,
        ray_dim=128,
        num_latents=512,
        latent_dim=256,
        latent_layers=4,
        cross_heads=1,
        latent_heads=8,
        query_dim=128,
        out_channels=128,
        out_cells=32,
    ),
    # CPU size: SinBEVT "tiny" image encoder (128x128, ImageNet EfficientNet-Lite0; backbone="resnet": the
    # from-scratch half-width ResNet of the first camera zoo), 128 latents of width 128, 2 layers.
    "tiny": LaRaConfig(
        image_size=(128, 128),
        raw_image_size=(150, 200),
        resnet_width=0.5,
        resnet_blocks=(2, 2, 2, 2),
        feat_dim=64,
        ray_dim=32,
        num_latents=128,
        latent_dim=128,
        latent_layers=2,
        cross_heads=1,
        latent_heads=4,
        query_dim=64,
        out_channels=64,
        out_cells=32,
        backbone="efficientnet_lite0",
    ),
}


def fourier_encode(z: Tensor, bands: int, max_freq: float) -> Tensor:
    """Eq. 11: z [...] -> [..., 1 + 2B] = (z, sin(f_b pi z), cos(f_b pi z)), f_b = linspace(1, f_B, B)."""
    freqs = torch.linspace(1.0, max_freq, bands, device=z.device, dtype=z.dtype)
    arg = z[..., None] * freqs * torch.pi
    return torch.cat([z[..., None], arg.sin(), arg.cos()], dim=-1)


class MultiheadAttention(nn.Module):
    """LaRa supp. Eq. 6-7: multi-head attention with separate query and key/value widths."""

    def __init__(self, q_dim: int, kv_dim: int, heads: int, inner_dim: int | None = None) -> None:
        super().__init__()
        inner = inner_dim or q_dim
        if inner % heads:
            raise ValueError(f"attention width {inner} not divisible by heads {heads}")
        self.heads = heads
        self.to_q = nn.Linear(q_dim, inner)
        self.to_k = nn.Linear(kv_dim, inner)
        self.to_v = nn.Linear(kv_dim, inner)
        self.proj = nn.Linear(inner, q_dim)

    def forward(self, q: Tensor, kv: Tensor) -> Tensor:
        """q [B, Tq, q_dim], kv [B, Tk, kv_dim] -> [B, Tq, q_dim]."""
        b, tq, _ = q.shape
        h = self.heads
        q = self.to_q(q).unflatten(-1, (h, -1)).transpose(1, 2)  # [B, h, Tq, d]
        k = self.to_k(kv).unflatten(-1, (h, -1)).transpose(1, 2)
        v = self.to_v(kv).unflatten(-1, (h, -1)).transpose(1, 2)
        out = F.scaled_dot_product_attention(q, k, v)  # softmax(QK^T / sqrt(d)) V, Eq. 6
        return self.proj(out.transpose(1, 2).reshape(b, tq, -1))


class LatentInputCrossAttention(nn.Module):
    """Eq. 8: latents <- MHA(LN(latents), LN(input)) + latents; latents <- MLP(LN(latents)) + latents."""

    def __init__(self, latent_dim: int, input_dim: int, heads: int, mlp_ratio: int) -> None:
        super().__init__()
        self.norm_q = nn.LayerNorm(latent_dim)
        self.norm_kv = nn.LayerNorm(input_dim)
        self.attn = MultiheadAttention(latent_dim, input_dim, heads)
        self.norm_mlp = nn.LayerNorm(latent_dim)
        self.mlp = Mlp(latent_dim, mlp_ratio * latent_dim)

    def forward(self, latents: Tensor, inputs: Tensor) -> Tensor:  # [B, L, D], [B, T, Din] -> [B, L, D]
        latents = self.attn(self.norm_q(latents), self.norm_kv(inputs)) + latents
        return self.mlp(self.norm_mlp(latents)) + latents


class LatentSelfAttention(nn.Module):
    """Eq. 9: latents <- MHA(LN(latents), LN(latents)) + latents; latents <- MLP(LN(latents)) + latents."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.attn = MultiheadAttention(dim, dim, heads)
        self.norm_mlp = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, mlp_ratio * dim)

    def forward(self, latents: Tensor) -> Tensor:  # [B, L, D] -> same
        z = self.norm(latents)
        latents = self.attn(z, z) + latents
        return self.mlp(self.norm_mlp(latents)) + latents


class BevLatentCrossAttention(nn.Module):
    """Eq. 10 (not residual): out <- MHA(LN(query), LN(latents)); out <- MLP(LN(out)) + out."""

    def __init__(self, query_dim: int, latent_dim: int, heads: int, mlp_ratio: int) -> None:
        super().__init__()
        self.norm_q = nn.LayerNorm(query_dim)
        self.norm_kv = nn.LayerNorm(latent_dim)
        self.attn = MultiheadAttention(query_dim, latent_dim, heads)
        self.norm_mlp = nn.LayerNorm(query_dim)
        self.mlp = Mlp(query_dim, mlp_ratio * query_dim)

    def forward(self, query: Tensor, latents: Tensor) -> Tensor:  # [B, Q, Dq], [B, L, D] -> [B, Q, Dq]
        out = self.attn(self.norm_q(query), self.norm_kv(latents))
        return self.mlp(self.norm_mlp(out)) + out


class BevQuery(nn.Module):
    """BEV query embedding: Fourier features of normalised cell coordinates (Eq. 11-12) or the raw
    coordinates, then MLP_bev (2-layer GELU MLP, Eq. 5)."""

    def __init__(self, cells: int, size_m: float, dim: int, kind: str, bands: int) -> None:
        super().__init__()
        if kind not in ("fourier", "coords"):
            raise ValueError(f"bev_query must be 'fourier' or 'coords', got {kind!r}")
        self.kind, self.bands, self.max_freq = kind, bands, cells / 2  # Nyquist of the cell grid
        self.register_buffer("coords", bev_cell_xy(cells, size_m) / (size_m / 2), persistent=False)  # [F,F,2]
        in_dim = 2 * (1 + 2 * bands) if kind == "fourier" else 2
        self.mlp = Mlp(in_dim, dim, dim)

    def forward(self, batch: int) -> Tensor:  # -> [B, F*F, Dq], row-major over (row, col)
        c = self.coords.flatten(0, 1)  # [F*F, 2]
        if self.kind == "fourier":
            c = torch.cat([fourier_encode(c[:, 0], self.bands, self.max_freq),
                           fourier_encode(c[:, 1], self.bands, self.max_freq)], dim=-1)  # Eq. 12
        return self.mlp(c)[None].expand(batch, -1, -1)


class FeatureNeck(nn.Module):
    """Sum of 1x1-projected ResNet layer1..3 maps upsampled to stride 8 (one LaRa-style stride-8 map)."""

    def __init__(self, in_channels: Sequence[int], out_dim: int) -> None:
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_dim, 1) for c in in_channels)
        self.out = nn.Sequential(
            nn.BatchNorm2d(out_dim), nn.ReLU(inplace=True), nn.Conv2d(out_dim, out_dim, 3, padding=1)
        )

    def forward(self, feats: list[Tensor]) -> Tensor:  # 3 x [B*M, Ci, hi, wi] -> [B*M, c, h1, w1]
        size = feats[0].shape[-2:]
        x = sum(F.interpolate(lat(f), size=size, mode="bilinear", align_corners=False) if i else lat(f)
                for i, (lat, f) in enumerate(zip(self.lateral, feats, strict=True)))
        return self.out(x)


class LatentStack(nn.Module):
    """Eq. 9 repeated ``layers`` times."""

    def __init__(self, dim: int, heads: int, layers: int, mlp_ratio: int) -> None:
        super().__init__()
        self.layers = nn.ModuleList(LatentSelfAttention(dim, heads, mlp_ratio) for _ in range(layers))

    def forward(self, latents: Tensor) -> Tensor:
        for layer in self.layers:
            latents = layer(latents)
        return latents


class LaRa(CameraEncoderIntrospection, nn.Module):
    """LaRa camera encoder: forward(images, intrinsics, extrinsics) -> [B, C, F, F] BEV features."""

    per_camera_extra = ("neck",)
    head_stage_names: tuple[str, ...] = ("neck", "encode", "process", "decode", "head")  # after the backbone's

    def __init__(self, config: LaRaConfig, bev_size_m: float = 100.0) -> None:
        super().__init__()
        cfg = config
        if cfg.ray_encoding not in ("origin_dir", "plucker"):
            raise ValueError(f"ray_encoding must be 'origin_dir' or 'plucker', got {cfg.ray_encoding!r}")
        self.config = cfg
        self.bev_size_m = bev_size_m
        self.out_channels: int = cfg.out_channels
        self.out_cells: int = cfg.out_cells
        self.backbone_attr, backbone = build_image_backbone(cfg.backbone, cfg.resnet_width, cfg.resnet_blocks)
        self.add_module(self.backbone_attr, backbone)
        self.neck = FeatureNeck(backbone.out_channels, cfg.feat_dim)
        self.ray_mlp = Mlp(6, cfg.ray_dim, cfg.ray_dim)  # MLP_ray
        self.latents = nn.Parameter(torch.randn(cfg.num_latents, cfg.latent_dim) * 0.02)
        in_dim = cfg.feat_dim + cfg.ray_dim
        self.encode = LatentInputCrossAttention(cfg.latent_dim, in_dim, cfg.cross_heads, cfg.mlp_ratio)
        self.process = LatentStack(cfg.latent_dim, cfg.latent_heads, cfg.latent_layers, cfg.mlp_ratio)
        self.query = BevQuery(cfg.out_cells, bev_size_m, cfg.query_dim, cfg.bev_query, cfg.fourier_bands)
        self.decode = BevLatentCrossAttention(cfg.query_dim, cfg.latent_dim, cfg.cross_heads, cfg.mlp_ratio)
        self.head = nn.Linear(cfg.query_dim, cfg.out_channels)
        # Linear layers keep PyTorch's default init: with the small widths here the ViT-style
        # trunc_normal(0.02) init starts Eq. 10 with near-uniform attention and trains much slower.

    def ray_embedding(self, intrinsics: Tensor, extrinsics: Tensor, feat_hw: tuple[int, int]) -> Tensor:
        """Per feature pixel camera ray in the agent frame -> [B, M, h, w, 6] before MLP_ray.

        "origin_dir": (o / (S/2), d) with d the unit direction; "plucker": (d, o x d / (S/2)).
        """
        d = l2_normalize(feature_rays(intrinsics, extrinsics, self.config.image_size, feat_hw))  # [B,M,h,w,3]
        o = (camera_centres(extrinsics) / (self.bev_size_m / 2))[:, :, None, None].expand_as(d)
        if self.config.ray_encoding == "plucker":
            return torch.cat([d, torch.linalg.cross(o, d)], dim=-1)
        return torch.cat([o, d], dim=-1)

    def forward(self, images: Tensor, intrinsics: Tensor, extrinsics: Tensor) -> Tensor:
        """images [B, M, 3, h, w] in [0, 1], intrinsics [B, M, 3, 3] (pixels), extrinsics [B, M, 4, 4]
        camera-to-agent -> [B, C, F, F] (row 0 = front, column 0 = left)."""
        b, m = images.shape[:2]
        intrinsics, extrinsics = intrinsics.to(images.dtype), extrinsics.to(images.dtype)
        images, intrinsics = resize_images(images, intrinsics, self.config.image_size)
        x = self.image_backbone.normalise(images.flatten(0, 1))  # [B*M, 3, H, W]
        feat = self.neck(self.image_backbone(x))  # [B*M, c, h, w]
        h, w = feat.shape[-2:]
        feat = feat.unflatten(0, (b, m)).permute(0, 1, 3, 4, 2)  # [B, M, h, w, c]
        rays = self.ray_mlp(self.ray_embedding(intrinsics, extrinsics, (h, w)))  # [B, M, h, w, c_ray]
        tokens = torch.cat([feat, rays], dim=-1).reshape(b, m * h * w, -1)  # [B, T, c + c_ray]
        latents = self.encode(self.latents[None].expand(b, -1, -1), tokens)  # Eq. 8
        latents = self.process(latents)  # Eq. 9
        out = self.decode(self.query(b), latents)  # Eq. 10, [B, F*F, Dq]
        out = self.head(out)  # [B, F*F, C]
        f = self.config.out_cells
        return out.transpose(1, 2).reshape(b, -1, f, f)



def build_lara(preset: str, bev_size_m: float = 100.0, **overrides: object) -> LaRa:
    """LaRa for ``preset`` in PRESETS ("tiny", "paper"); ``overrides`` replace LaRaConfig fields."""
    if preset not in PRESETS:
        raise ValueError(f"unknown LaRa preset {preset!r}; choose from {sorted(PRESETS)}")
    return LaRa(replace(PRESETS[preset], **overrides), bev_size_m=bev_size_m)
