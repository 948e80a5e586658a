"""`v2vsim models`: every encoder, fusion method (plugins too) and the decoder heads of a preset, built from the
registry (models.registry) and run once on example inputs: parameters and per-stage output shapes, as rows
(`describe_models`) and as a plain-text table (`format_models_table`); a fusion plugin that cannot be used is a row
saying why."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from models.build import build_encoder, build_fusion, build_heads
from models.registration import BRACKETS, BUILTIN, PluginError
from models.registry import MODALITY, fusion_names, name_clashes, registration

if TYPE_CHECKING:
    from torch import nn


def _params(m: nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def _row(name: str, kind: str, module: nn.Module, stages: list[tuple[str, tuple]], output: tuple | None,
         **extra: Any) -> dict:
    return {
        "name": name,
        "kind": kind,
        "params": _params(module),
        "stages": [{"stage": s, "shape": list(shape)} for s, shape in stages],
        "output": list(output) if output is not None else None,
        "origin": BUILTIN,
        **extra,
    }


def _with_output(module: nn.Module, run: Callable[[], list[tuple[str, tuple]]]) -> tuple[list, tuple | None]:
    """Run `run` (which calls module's forward) with a hook on the module itself; (its result, output shape)."""
    import torch

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
    """Every encoder, fusion method (plugins too) and the heads of `preset`: name, kind, origin (where it comes
    from: "built-in", "plugin NAME VERSION" (its distribution), "registered"), params, per-stage output shapes.

    Runs one forward pass per model on example inputs (encoders: their `example_inputs()`; fusion:
    `agents` random C x F x F maps; heads: the fused map) with forward hooks. A plugin that cannot be used is
    a row with "error" (its PluginError message) and no shapes: the listing shows it rather than fail.
    """
    import torch

    from models.presets import get_preset
    from models.resnet import record_stage_shapes

    p = get_preset(preset)
    rows: list[dict] = []
    for name, modality in MODALITY.items():
        enc = build_encoder(name, preset).eval()
        stages, out = _with_output(enc, enc.stage_shapes)
        rows.append(_row(name, f"encoder ({modality})", enc, stages, out))
    feats = torch.randn(1, agents, p.channels, p.cells, p.cells)
    valid = torch.ones(1, agents, dtype=torch.bool)
    for name in fusion_names():
        reg = registration(name)
        try:
            fus = build_fusion(name, preset).eval()
        except PluginError as e:
            rows.append({"name": name, "kind": "fusion", "params": None, "stages": [], "output": None,
                         "origin": reg.source(), "error": str(e)})
            continue
        names = list(getattr(fus, "stage_names", [n for n, _ in fus.named_children()]))

        def run(fus: nn.Module = fus, names: list[str] = names) -> list[tuple[str, tuple]]:
            return record_stage_shapes(fus, names, lambda: fus(feats, valid), skip_missing=True)

        stages, out = _with_output(fus, run)
        rows.append(_row(name, "fusion", fus, stages, out, agents=agents, origin=reg.source()))
    for r in name_clashes():  # installed plugins that claim a name already taken
        rows.append({"name": r.name, "kind": "fusion", "params": None, "stages": [], "output": None,
                     "origin": r.source(), "error": r.error})
    for modality in ("camera", "lidar"):
        heads = build_heads(modality, preset).eval()
        names = ["decoder.stages.0", "decoder.stages.1", "decoder.stages.2", "dynamic", "static"]
        if heads.detection is not None:
            names += ["detection.cls", "detection.reg"]
        x = torch.randn(1, p.channels, heads.in_cells, heads.in_cells)  # the fused map of that modality's grid
        stages = record_stage_shapes(heads, names, lambda heads=heads, x=x: heads(x), skip_missing=True)
        rows.append(_row(f"heads-{modality}", "decoder+heads", heads, stages, dict(stages)["dynamic"]))
    for name in BRACKETS:  # the brackets: no module of their own
        rows.append({"name": name, "kind": "bracket", "params": 0, "stages": [], "output": None, "origin": BUILTIN})
    return rows


def format_models_table(rows: list[dict]) -> str:
    """Plain-text table of describe_models rows: name, kind, where it comes from, parameters, stage=shape ... ->
    output shape; a broken plugin's row says BROKEN and why."""

    def dims(shape: list[int]) -> str:
        return "x".join(str(d) for d in shape)

    notes = {"early": "raw points merged in the ego frame -> encoder -> heads",
             "late": "per-CAV outputs merged in the ego frame (max / rotated NMS)"}
    width = max([8, *(len(r.get("origin", BUILTIN)) for r in rows)])
    lines = [f"{'name':<14} {'kind':<18} {'from':<{width}} {'params':>12}  stages -> output"]
    for r in rows:
        parts = [f"{s['stage']}={dims(s['shape'])}" for s in r["stages"]]
        text = ", ".join(parts)
        if r.get("output") is not None:
            text = f"{text} -> {dims(r['output'])}" if text else f"-> {dims(r['output'])}"
        if r.get("error"):
            text = f"BROKEN: {r['error']}"
        params = "-" if r["params"] is None else f"{r['params']:,}"
        lines.append(f"{r['name']:<14} {r['kind']:<18} {r.get('origin', BUILTIN):<{width}} {params:>12}  "
                     f"{text or notes.get(r['name'], '-')}")
    return "\n".join(lines)
