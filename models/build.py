"""Models built by name from the registry (models.registry): an encoder, a fusion method (plugins too), the
decoder heads, and the whole cooperative model of one encoder and one method, each in a model preset
(models.presets). Torch is imported when a model is built, not with this module."""

from __future__ import annotations

from typing import TYPE_CHECKING

from models.registry import ENCODERS, FUSION, METHODS, MODALITY, check_name, fusion_kwargs, is_intermediate

if TYPE_CHECKING:
    from torch import nn

    from models.cooperative import CooperativePerception
    from models.heads import BevHeads


def build_encoder(name: str, preset: str, bev_size_m: float = 100.0, cells: int | None = None,
                  image_backbone: str | None = None) -> nn.Module:
    """Encoder `name` ("pointpillars" | "sinbevt" | "lara") of `preset` -> [B, C, F, F] over bev_size_m.

    `cells`: the LiDAR fusion grid F (default the preset's; a zoo records its own, models.zoo.Zoo.cells).
    The camera encoders' grid is fixed by their architecture (SinBEVT's output, Table A2): for them
    `cells` must be None or their own. `image_backbone`: a camera encoder's image backbone
    (models.image_backbone; default the preset's; a zoo records its own, models.zoo.Zoo.image_backbone)."""
    from models.presets import get_preset

    check_name("encoder", name, ENCODERS)
    p = get_preset(preset)
    if MODALITY[name] == "lidar":
        if image_backbone is not None:
            raise ValueError(f"{name}: a LiDAR encoder has no image backbone (got {image_backbone!r})")
        return ENCODERS[name](preset, bev_size_m=bev_size_m, cells=cells)
    if cells not in (None, p.camera_cells):
        raise ValueError(f"{name}: a camera encoder's grid is {p.camera_cells} x {p.camera_cells}, not {cells}")
    extra = {} if image_backbone is None else {"backbone": image_backbone}
    return ENCODERS[name](preset, bev_size_m=bev_size_m, **extra)


def preset_image_backbone(encoder: str, preset: str) -> str | None:
    """The image backbone (models.image_backbone) of a camera encoder's `preset`; None for a LiDAR encoder."""
    from models.lara import PRESETS as LARA_PRESETS
    from models.presets import get_preset
    from models.sinbevt import PRESETS as SINBEVT_PRESETS

    check_name("encoder", encoder, ENCODERS)
    presets = {"sinbevt": SINBEVT_PRESETS, "lara": LARA_PRESETS}.get(encoder)
    return None if presets is None else presets[get_preset(preset).name].backbone


def build_fusion(name: str, preset: str) -> nn.Module:
    """Fusion module `name` of `preset`: forward([B, L, C, H, W], [B, L] bool) -> [B, C, H, W]."""
    from models.presets import get_preset

    check_name("fusion method", name, FUSION)
    return FUSION[name](get_preset(preset).channels, **fusion_kwargs(name, preset))


def build_heads(modality: str, preset: str, in_cells: int | None = None) -> BevHeads:
    """Decoder + segmentation heads (+ detection head for "lidar") of `preset` for an in_cells grid (default:
    the preset's grid of that modality)."""
    from models.heads import build_bev_heads
    from models.presets import get_preset

    p = get_preset(preset)
    return build_bev_heads(modality, preset, in_cells or (p.cells if modality == "lidar" else p.camera_cells))


def build_cooperative(encoder: str, method: str, preset: str, bev_size_m: float = 100.0,
                      cells: int | None = None, image_backbone: str | None = None) -> CooperativePerception:
    """The whole model for one encoder and one of METHODS (brackets use fusion "none"); `cells`: the LiDAR
    fusion grid, `image_backbone`: a camera encoder's (build_encoder)."""
    from models.cooperative import CooperativePerception

    check_name("encoder", encoder, ENCODERS)
    check_name("method", method, METHODS)
    modality = MODALITY[encoder]
    fusion = build_fusion(method if is_intermediate(method) else "none", preset)
    enc = build_encoder(encoder, preset, bev_size_m, cells, image_backbone)
    return CooperativePerception(enc, fusion, build_heads(modality, preset, enc.out_cells), method, modality,
                                 bev_size_m)
