"""Which models a scenario runs, with which weights: the encoder every CAV shares and one
CooperativePerception per fusion method, built by name from the scenario's ModelPlan (v2vsim.perception.plan:
its `perception` section and zoo, resolved once per process by plan_models; every builder here takes the plan).

Weights: `perception.weights: auto` loads the zoo's checkpoints (models.zoo: models/weights/
<encoder>_<preset>/, verified against manifest.json when loaded); where none ship, every process builds the same
randomly initialised models from the scenario seed (so CAV encoders and the ego agree), and the report says the
weights are untrained. Which checkpoint each method loads (a fusion plugin's may come from the plugin's own zoo)
is the plan's (v2vsim.perception.plan).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models import zoo
from models.build import build_cooperative, build_encoder
from models.compression import ChannelCompressor
from models.extrapolation import FeatureExtrapolation
from models.presets import get_preset
from models.zoo import Checkpoint
from v2vsim.config import ConfigError
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.plan import ModelPlan, _sha

Loaded = tuple[Checkpoint, dict]  # a verified checkpoint and its state_dict


def method_checkpoints(plan: ModelPlan, methods: tuple[str, ...]) -> dict[str, str | None]:
    """Checkpoint file each method loads (relative to the zoo root; a plugin's own zoo's file: its absolute path),
    None where weights are random."""
    z = plan.zoo
    if z is None:
        return dict.fromkeys(methods)
    files = {m: plan.checkpoint(m) for m in methods}
    return {m: None if c is None else str(c.path.relative_to(z.root) if c.path.parent.parent == z.root else c.path)
            for m, c in files.items()}


def verified(ckpt: Checkpoint) -> dict:
    """The checkpoint's verified state_dict; ConfigError naming the file and its rebuild command otherwise."""
    try:
        return ckpt.load()
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None


def _states(plan: ModelPlan, methods: tuple[str, ...]) -> dict[str, Loaded | None]:
    """The verified checkpoint of each method ("encoder": the CAVs' encoder; None: random weights), every file
    read and hashed once; ConfigError naming the file when one is broken."""
    files = {m: plan.checkpoint(m) for m in methods}
    states = {p: verified(c) for p, c in {c.path: c for c in files.values() if c is not None}.items()}
    return {m: None if c is None else (c, states[c.path]) for m, c in files.items()}


def _seed(plan: ModelPlan, what: str) -> None:
    torch.manual_seed(plan.seed * 1_000_003 + zlib.crc32(what.encode()))


def misfit(path: Path, what: str, reason: str, remedy: str) -> ConfigError:
    """The one-line error of a checkpoint part made for another version of the model: `what` ("the cobevt
    checkpoint's fusion weights do not fit", ...), the loader's `reason` (missing, unknown or resized weights)."""
    reason = " ".join(reason.split())
    return ConfigError(f"{path}: {what} this version of the model ({reason[:300]}); {remedy}")


def method_part(loaded: Loaded | None, prefix: str) -> dict:
    """The `prefix` part of a method's verified checkpoint, the prefix stripped ({}: random weights, or none)."""
    return {} if loaded is None else {k[len(prefix):]: v for k, v in loaded[1].items() if k.startswith(prefix)}


def method_misfit(ckpt: Checkpoint, prefix: str, method: str, reason: str) -> ConfigError:
    """misfit for the `prefix` part of `method`'s checkpoint."""
    return misfit(ckpt.path, f"the {method} checkpoint's {prefix.rstrip('.')} weights do not fit", reason,
                  f"rebuild it with: {ckpt.rebuild_command}")


def _load(module: nn.Module, loaded: Loaded | None, prefix: str, method: str) -> None:
    """Load the `prefix` part of `method`'s checkpoint into `module` (nothing where it has none); ConfigError naming
    the file and its rebuild command when it was made for another version of the model (missing, unknown or
    resized weights)."""
    sub = method_part(loaded, prefix)
    if not sub:
        return
    try:
        module.load_state_dict(sub)
    except RuntimeError as e:
        raise method_misfit(loaded[0], prefix, method, str(e)) from None  # type: ignore[index]


def build_agent_encoder(plan: ModelPlan) -> nn.Module:
    """The encoder every CAV runs; identical in every process for a given scenario."""
    _seed(plan, "encoder")
    enc = build_encoder(plan.encoder, plan.preset, bev_size_m=plan.bev_size_m, cells=plan.cells,
                        image_backbone=plan.image_backbone)
    _load(enc, _states(plan, ("encoder",))["encoder"], "encoder.", "encoder")
    return enc.eval()


def build_compressor(plan: ModelPlan, channels: int) -> ChannelCompressor | None:
    """The channel compression pair of the plan's wire ratio (None when it is 1): the zoo's trained one
    (`compress` stage), verified like every checkpoint. A ratio the zoo has no compressor for is a ConfigError
    naming the ratio and the command that trains it (ModelPlan.wire_compressor). Only a run whose weights are all
    random (perception.weights: none; its report says so) builds a seeded random one."""
    ratio = plan.wire_ratio
    if ratio == 1:
        return None
    if plan.zoo is None:
        _seed(plan, "compressor")
        return ChannelCompressor(channels, ratio).eval()
    ckpt = plan.wire_compressor()
    assert ckpt is not None  # a zoo and a ratio > 1: its compressor, or wire_compressor raised
    state = verified(ckpt)
    comp = ChannelCompressor(channels, ratio)
    load_part(comp, state, "compressor.", ckpt.path, f"the ratio-{ratio} compressor",
              f"rebuild it with: {ckpt.rebuild_command}")
    return comp.eval()


def load_part(module: nn.Module, state: dict, prefix: str, path: Path, what: str, remedy: str) -> None:
    """Load the `prefix` part of a verified checkpoint's `state` (read from `path`) into `module`; ConfigError naming
    the file, `what` does not fit and the `remedy` when it was made for another version of the model (missing,
    unknown or resized weights)."""
    try:
        module.load_state_dict({k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)})
    except RuntimeError as e:
        raise misfit(path, f"{what} does not fit", str(e), remedy) from None


@torch.no_grad()
def compress(comp: ChannelCompressor | None, features: np.ndarray) -> np.ndarray:
    """Sender side: [C, F, F] -> [C/r, F, F] (unchanged without compression), on the compressor's device, back on
    the host for the wire."""
    if comp is None:
        return features
    return to_host(comp.compress(torch.from_numpy(features)[None].to(model_device(comp)))[0])


@torch.no_grad()
def decompress(comp: ChannelCompressor | None, payload: np.ndarray) -> np.ndarray:
    """Receiver side: [C/r, F, F] -> [C, F, F] float32, on the compressor's device, back on the host."""
    x = payload.astype(np.float32)
    return x if comp is None else to_host(comp.decompress(torch.from_numpy(x)[None].to(model_device(comp)))[0])


def method_model(plan: ModelPlan, method: str) -> nn.Module:
    """`method`'s CooperativePerception as the plan builds it, its weights as initialised (seeded from the
    scenario seed and the method's name)."""
    _seed(plan, f"method:{method}")
    return build_cooperative(plan.encoder, method, plan.preset, bev_size_m=plan.bev_size_m, cells=plan.cells,
                             image_backbone=plan.image_backbone)


def build_method_models(plan: ModelPlan, encoder: nn.Module, methods: tuple[str, ...]) -> dict[str, nn.Module]:
    """One CooperativePerception per method, all sharing `encoder` (every method fuses the same messages)."""
    states = _states(plan, methods)
    out = {}
    for m in methods:
        model = method_model(plan, m)
        if m == "early":  # early fusion's encoder runs at the ego on merged clouds: its own weights
            _load(model.encoder, states[m], "encoder.", m)
        else:
            model.encoder = encoder
        _load(model.fusion, states[m], "fusion.", m)
        _load(model.heads, states[m], "heads.", m)
        model.heads.for_inference()
        out[m] = model.eval()
    return out


def extrapolation_state(plan: ModelPlan, method: str) -> tuple[Checkpoint, dict] | None:
    """The zoo's verified latency compensation for `method` (its checkpoint and its "extrapolation." part, the
    prefix stripped); None when the plan runs random weights or its zoo has none for `method`. ConfigError naming
    the file when it is broken or was trained on another checkpoint of `method` than the zoo's current one."""
    ckpt = None if plan.zoo is None else plan.extrapolation.get(method)
    if ckpt is None:
        return None
    state = verified(ckpt)
    current = _sha(plan.checkpoint(method))  # the one this run's wire ratio loads
    for file, sha in ckpt.trained_on.items():
        if current != sha:
            raise ConfigError(f"{ckpt.path}: trained on top of {file} (sha256 {sha[:12]}…), not on the zoo's current "
                              f"{method} checkpoint; rebuild it with: {ckpt.rebuild_command}")
    return ckpt, {k[len("extrapolation."):]: v for k, v in state.items() if k.startswith("extrapolation.")}


def extrapolation_module(plan: ModelPlan, ckpt: Checkpoint, sub: dict, method: str,
                         load: bool = True) -> FeatureExtrapolation:
    """The FeatureExtrapolation `sub` (extrapolation_state) was saved from, with its weights where `load` (else
    as initialised: v2vsim.perception.checks compares their shapes); ConfigError naming the file when it does not
    fit this version of the model."""
    channels = get_preset(plan.preset).channels
    first = sub.get("net.0.weight")  # [H, 2C, 3, 3]
    try:
        if first is None or first.shape[1] != 2 * channels:
            raise RuntimeError(f"expected a first convolution over 2 x {channels} channels, got "
                               f"{None if first is None else tuple(first.shape)}")
        module = FeatureExtrapolation(channels, first.shape[0])
        if load:
            module.load_state_dict(sub)
    except RuntimeError as e:
        raise misfit(ckpt.path, f"the {method} extrapolation weights do not fit", str(e),
                     f"rebuild it with: {ckpt.rebuild_command}") from None
    return module


def build_extrapolation(plan: ModelPlan, method: str = "cobevt") -> FeatureExtrapolation | None:
    """The zoo's receiver-side latency compensation for `method` (models.extrapolation, trained by the
    `extrapolate` stage on top of that method's checkpoint), verified like every checkpoint; None when the
    scenario runs random weights or its zoo has none for `method` (never a randomly initialised one).
    ConfigError naming the file when it is broken, does not fit, or was trained on another checkpoint of
    `method` than the zoo's current one."""
    found = extrapolation_state(plan, method)
    if found is None:
        return None
    return extrapolation_module(plan, *found, method).eval()
