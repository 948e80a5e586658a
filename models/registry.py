"""Build models by name: encoders, fusion methods, heads, the composed cooperative model.

Adding a fusion method = one file in models/fusion/ + one line in FUSION (+ optional sizes in
models.presets.ModelPreset.fusion_kwargs). "early" and "late" are brackets around the single-agent
model, not fusion modules: they are in METHODS but not in FUSION.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from models.cooperative import CooperativePerception
from models.fusion.attfuse import AttFusion
from models.fusion.cobevt import FuseBEVT
from models.fusion.disconet import DiscoNetFusion
from models.fusion.fcooper import FCooperFusion
from models.fusion.none import NoFusion
from models.fusion.v2vnet import V2VNetFusion
from models.heads import BevHeads, build_bev_heads
from models.lara import PRESETS as LARA_PRESETS
from models.lara import build_lara
from models.pointpillars import build_pointpillars
from models.presets import get_preset
from models.sinbevt import PRESETS as SINBEVT_PRESETS
from models.sinbevt import build_sinbevt

ENCODERS: dict[str, Callable[..., nn.Module]] = {
    "pointpillars": build_pointpillars,
    "sinbevt": build_sinbevt,
    "lara": build_lara,
}
MODALITY: dict[str, str] = {"pointpillars": "lidar", "sinbevt": "camera", "lara": "camera"}
FUSION: dict[str, Callable[..., nn.Module]] = {
    "none": NoFusion,
    "attfuse": AttFusion,
    "fcooper": FCooperFusion,
    "v2vnet": V2VNetFusion,
    "disconet": DiscoNetFusion,
    "cobevt": FuseBEVT,
}
METHODS: list[str] = ["none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt"]


def _check(kind: str, name: str, allowed: list[str] | dict[str, Any]) -> None:
    if name not in allowed:
        raise ValueError(f"unknown {kind} {name!r}; allowed: {', '.join(allowed)}")


def is_intermediate(method: str) -> bool:
    """True for methods that fuse BEV feature messages (every FUSION entry but "none")."""
    _check("method", method, METHODS)
    return method in FUSION and method != "none"


def intermediate_methods() -> list[str]:
    """METHODS that fuse intermediate BEV features, in METHODS order."""
    return [m for m in METHODS if is_intermediate(m)]


def build_encoder(name: str, preset: str, bev_size_m: float = 100.0, cells: int | None = None,
                  image_backbone: str | None = None) -> nn.Module:
    """Encoder `name` ("pointpillars" | "sinbevt" | "lara") of `preset` -> [B, C, F, F] over bev_size_m.

    `cells`: the LiDAR fusion grid F (default the preset's; a zoo records its own, models.zoo.zoo_cells).
    The camera encoders' grid is fixed by their architecture (SinBEVT's output, Table A2): for them
    `cells` must be None or their own. `image_backbone`: a camera encoder's image backbone
    (models.image_backbone; default the preset's; a zoo records its own, models.zoo.zoo_image_backbone)."""
    _check("encoder", name, ENCODERS)
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
    _check("encoder", encoder, ENCODERS)
    presets = {"sinbevt": SINBEVT_PRESETS, "lara": LARA_PRESETS}.get(encoder)
    return None if presets is None else presets[get_preset(preset).name].backbone


def build_fusion(name: str, preset: str) -> nn.Module:
    """Fusion module `name` of `preset`: forward([B, L, C, H, W], [B, L] bool) -> [B, C, H, W]."""
    _check("fusion method", name, FUSION)
    p = get_preset(preset)
    return FUSION[name](p.channels, **p.fusion_args(name))


def build_heads(modality: str, preset: str, in_cells: int | None = None) -> BevHeads:
    """Decoder + segmentation heads (+ detection head for "lidar") of `preset` for an in_cells grid (default:
    the preset's grid of that modality)."""
    p = get_preset(preset)
    return build_bev_heads(modality, preset, in_cells or (p.cells if modality == "lidar" else p.camera_cells))


def build_cooperative(encoder: str, method: str, preset: str, bev_size_m: float = 100.0,
                      cells: int | None = None, image_backbone: str | None = None) -> CooperativePerception:
    """The whole model for one encoder and one of METHODS (brackets use fusion "none"); `cells`: the LiDAR
    fusion grid, `image_backbone`: a camera encoder's (build_encoder)."""
    _check("encoder", encoder, ENCODERS)
    _check("method", method, METHODS)
    modality = MODALITY[encoder]
    fusion = build_fusion(method if is_intermediate(method) else "none", preset)
    enc = build_encoder(encoder, preset, bev_size_m, cells, image_backbone)
    return CooperativePerception(enc, fusion, build_heads(modality, preset, enc.out_cells), method, modality,
                                 bev_size_m)


def _params(m: nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def _hook_shapes(module: nn.Module, names: list[str], run: Callable[[], object]) -> list[tuple[str, tuple]]:
    """Run `run` with forward hooks on the named submodules; (name, output shape) in `names` order."""
    shapes: dict[str, tuple] = {}
    subs = dict(module.named_modules())

    def make(n: str) -> Callable[..., None]:
        def hook(_m: nn.Module, _i: object, out: object) -> None:
            t = out[0] if isinstance(out, (tuple, list)) else out
            if isinstance(out, dict):
                t = next(iter(out.values()))
            if isinstance(t, torch.Tensor):
                shapes[n] = tuple(t.shape)

        return hook

    handles = [subs[n].register_forward_hook(make(n)) for n in names]
    try:
        with torch.no_grad():
            run()
    finally:
        for h in handles:
            h.remove()
    return [(n, shapes[n]) for n in names if n in shapes]


def _row(name: str, kind: str, module: nn.Module, stages: list[tuple[str, tuple]], output: tuple | None,
         **extra: Any) -> dict:
    return {
        "name": name,
        "kind": kind,
        "params": _params(module),
        "stages": [{"stage": s, "shape": list(shape)} for s, shape in stages],
        "output": list(output) if output is not None else None,
        **extra,
    }


def _with_output(module: nn.Module, run: Callable[[], list[tuple[str, tuple]]]) -> tuple[list, tuple | None]:
    """Run `run` (which calls module's forward) with a hook on the module itself; (its result, output shape)."""
    seen: list[tuple] = []

    def hook(_m: nn.Module, _i: object, out: object) -> None:
        if isinstance(out, torch.Tensor):
            seen.append(tuple(out.shape))

    h = module.register_forward_hook(hook)
    try:
        stages = run()
    finally:
        h.remove()
    return stages, (seen[-1] if seen else None)


def describe_models(preset: str, agents: int = 4) -> list[dict]:
    """Every encoder, fusion method and the heads of `preset`: name, kind, params, per-stage output shapes.

    Runs one forward pass per model on example inputs (encoders: their `example_inputs()`; fusion:
    `agents` random C x F x F maps; heads: the fused map) with forward hooks.
    """
    p = get_preset(preset)
    rows: list[dict] = []
    for name, modality in MODALITY.items():
        enc = build_encoder(name, preset).eval()
        stages, out = _with_output(enc, enc.stage_shapes)
        rows.append(_row(name, f"encoder ({modality})", enc, stages, out))
    feats = torch.randn(1, agents, p.channels, p.cells, p.cells)
    valid = torch.ones(1, agents, dtype=torch.bool)
    for name in FUSION:
        fus = build_fusion(name, preset).eval()
        names = list(getattr(fus, "stage_names", [n for n, _ in fus.named_children()]))
        def run(fus: nn.Module = fus, names: list[str] = names) -> list[tuple[str, tuple]]:
            return _hook_shapes(fus, names, lambda: fus(feats, valid))

        stages, out = _with_output(fus, run)
        rows.append(_row(name, "fusion", fus, stages, out, agents=agents))
    for modality in ("camera", "lidar"):
        heads = build_heads(modality, preset).eval()
        names = ["decoder.stages.0", "decoder.stages.1", "decoder.stages.2", "dynamic", "static"]
        if heads.detection is not None:
            names += ["detection.cls", "detection.reg"]
        x = torch.randn(1, p.channels, heads.in_cells, heads.in_cells)  # the fused map of that modality's grid
        stages = _hook_shapes(heads, names, lambda heads=heads, x=x: heads(x))
        rows.append(_row(f"heads-{modality}", "decoder+heads", heads, stages, dict(stages)["dynamic"]))
    for name in METHODS:
        if name not in FUSION:  # the brackets: no module of their own
            rows.append({"name": name, "kind": "bracket", "params": 0, "stages": [], "output": None})
    return rows


def format_models_table(rows: list[dict]) -> str:
    """Plain-text table of describe_models rows: name, kind, parameters, stage=shape ... -> output shape."""

    def dims(shape: list[int]) -> str:
        return "x".join(str(d) for d in shape)

    notes = {"early": "raw points merged in the ego frame -> encoder -> heads",
             "late": "per-CAV outputs merged in the ego frame (max / rotated NMS)"}
    lines = [f"{'name':<14} {'kind':<18} {'params':>12}  stages -> output"]
    for r in rows:
        parts = [f"{s['stage']}={dims(s['shape'])}" for s in r["stages"]]
        text = ", ".join(parts)
        if r.get("output") is not None:
            text = f"{text} -> {dims(r['output'])}" if text else f"-> {dims(r['output'])}"
        lines.append(f"{r['name']:<14} {r['kind']:<18} {r['params']:>12,}  {text or notes.get(r['name'], '-')}")
    return "\n".join(lines)
