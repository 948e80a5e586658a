"""Which models a scenario runs, with which weights: the encoder every CAV shares and one
CooperativePerception per fusion method, built by name from the scenario's `perception` section.

Weights: `perception.weights: auto` loads the zoo's checkpoints (models.zoo: models/weights/
<encoder>_<preset>/, verified against manifest.json); where none ship, every process builds the same
randomly initialised models from the scenario seed (so CAV encoders and the ego agree), and the
report says the weights are untrained. Each build function resolves the scenario's zoo once (zoo_for: a
models.zoo.Zoo, or None for random weights) and works from that object; the helpers below take it.

A fusion plugin (models.registry) loads its checkpoint like a built-in, from the scenario's zoo (`perception.weights:
PATH`, a folder `v2vsim train --stage NAME --out PATH` wrote it into). Where that zoo has none and the plugin ships
a zoo of its own (its entry point object's `weights` attribute: a folder with a manifest.json), the checkpoint comes
from there if it was trained on this zoo's encoder and wire (_plugin_zoo: the manifests' sha256 of the encoder and
of the wire's compressor must match); else the method runs untrained, as every method without a checkpoint does,
and the report and metrics.json say so.
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
from models.registry import MODALITY, is_intermediate, is_plugin, plugin_weights
from models.zoo import Checkpoint, Zoo
from v2vsim.config import ConfigError, Scenario
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.fleet import agent_type
from v2vsim.sensors.sensing import ego_ids
from v2vsim.traffic.base import cav_id

Loaded = tuple[Checkpoint, dict]  # a verified checkpoint and its state_dict


def zoo_for(sc: Scenario) -> Zoo | None:
    """The zoo of the checkpoints the scenario asks for, parsed; None = seeded random weights.

    `perception.weights`: "auto" = models/weights/ when it ships this encoder/preset (else random),
    "none" = random, or a path to a zoo folder with its own manifest.json (as `v2vsim train --out` writes).
    """
    spec = sc.perception.weights
    if spec == "none":
        return None
    root = zoo.WEIGHTS_DIR
    if spec != "auto":
        root = Path(spec)
        relative = not root.is_absolute()
        if relative:
            root = Path(sc.source).parent / root
        if not (root / "manifest.json").is_file():
            how = (f" ({spec!r} is relative, so it is resolved against the scenario's folder "
                   f"{Path(sc.source).parent}, not the working directory; give an absolute path)" if relative else "")
            raise ConfigError(f"{sc.source}: perception.weights: no zoo manifest at {root / 'manifest.json'}{how}; "
                              "allowed: 'auto', 'none' or a folder written by `v2vsim train --out`")
    try:
        z = zoo.find(sc.perception.encoder, sc.perception.preset, root)
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None
    if z is None and spec != "auto":
        raise ConfigError(f"{sc.source}: perception.weights: {root} has no "
                          f"{zoo.zoo_name(sc.perception.encoder, sc.perception.preset)} checkpoints")
    return z


def _ratio(sc: Scenario, z: Zoo | None) -> int:
    """comm.channel_compression, or where it is null the zoo's wire ratio (1 with random weights)."""
    if sc.comm.channel_compression is not None:
        return sc.comm.channel_compression
    return 1 if z is None else z.wire_ratio


def _method_file(sc: Scenario, z: Zoo, method: str) -> Checkpoint | None:
    """The checkpoint `method` ("encoder": the CAVs' encoder) loads from the zoo `z`. An intermediate method loads
    the one trained on the scenario's wire ratio: the zoo's own wire is its "methods" file, another ratio
    (comm.channel_compression) needs a checkpoint trained on that wire ("wire_methods"). Where there is none it
    is a ConfigError: a fusion model fed another wire's decoded features runs off the distribution it was
    trained on, and its results would say nothing about the method."""
    if method == "encoder" or not is_intermediate(method):
        return z.method(method)
    ratio = _ratio(sc, z)
    ckpt = z.method(method, ratio)
    if ckpt is None and method in z.methods:
        have = ", ".join(map(str, z.wire_ratios(method)))
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio}: the {z.name} zoo's {method} was trained "
                          f"on the ratio-{z.wire_ratio} wire and has no checkpoint for ratio {ratio} (ratios it "
                          f"has: {have}); fed another wire's features it would run off its training distribution. "
                          f"Train one with: v2vsim train --data DATA --stage {method} --wire-ratio {ratio} --out "
                          f"{z.root} --work WORK (docs/training.md), or leave {method} out of perception.methods")
    return ckpt


def _sha(ckpt: Checkpoint | None) -> str | None:
    return None if ckpt is None else ckpt.sha256


def _plugin_zoo(sc: Scenario, method: str, z: Zoo) -> Zoo | None:
    """The zoo a fusion plugin ships (models.registry.plugin_weights) when it holds `method`'s checkpoint for this
    encoder/preset and wire, trained on the encoder and wire compressor of the scenario's zoo `z` (the sha256 its
    manifest records for them equal z's); None when the plugin ships no zoo or none for this encoder/preset.
    ConfigError when it does but was trained on another encoder or wire: fused from other features its results
    would say nothing about the method."""
    folder = plugin_weights(method)
    if folder is None:
        return None
    try:
        own = zoo.find(z.encoder, z.preset, folder)
    except zoo.ZooError as e:
        raise ConfigError(f"fusion plugin {method!r}: its weights {folder}: {e}") from None
    ratio = _ratio(sc, z)
    if own is None or own.method(method, ratio) is None:
        return None
    why = []
    if _sha(own.encoder_file) != _sha(z.encoder_file):
        why.append("its encoder")
    if own.cells != z.cells or own.image_backbone != z.image_backbone:
        why.append("its grid or image backbone")
    if ratio > 1 and _sha(own.compressors.get(ratio)) != _sha(z.compressors.get(ratio)):
        why.append(f"its ratio-{ratio} wire compressor")
    if why:
        raise ConfigError(f"{sc.source}: perception.methods: fusion plugin {method!r}: the checkpoint it ships "
                          f"({folder / z.name}) was trained on another model than the {z.name} zoo at {z.root} "
                          f"({' and '.join(why)} differ: manifest sha256); train {method} on this zoo (v2vsim train "
                          f"--data DATA --stage {method} --out COPY_OF_ZOO --work WORK, docs/training.md) and run "
                          "with perception.weights: COPY_OF_ZOO")
    return own


def _checkpoints(sc: Scenario, z: Zoo, methods: tuple[str, ...]) -> dict[str, Checkpoint | None]:
    """The checkpoint of each method (None: it runs untrained): the scenario's zoo `z`'s, or for a fusion plugin
    that zoo has no checkpoint of, the one of the plugin's own zoo (_plugin_zoo) where it ships a fitting one."""
    out = {}
    for m in methods:
        ckpt = _method_file(sc, z, m)
        own = None if ckpt is not None or m == "encoder" or not is_plugin(m) else _plugin_zoo(sc, m, z)
        out[m] = ckpt if own is None else own.method(m, _ratio(sc, z))
    return out


def method_checkpoints(sc: Scenario, methods: tuple[str, ...], *, z: Zoo | None = None) -> dict[str, str | None]:
    """Checkpoint file each method loads (relative to the zoo root; a plugin's own zoo's file: its absolute path),
    None where weights are random; `z`: the scenario's zoo where the caller already holds it (zoo_for)."""
    z = zoo_for(sc) if z is None else z
    if z is None:
        return dict.fromkeys(methods)
    return {m: None if c is None else str(c.path.relative_to(z.root) if c.path.parent.parent == z.root else c.path)
            for m, c in _checkpoints(sc, z, methods).items()}


def verified(ckpt: Checkpoint) -> dict:
    """The checkpoint's verified state_dict; ConfigError naming the file and its rebuild command otherwise."""
    try:
        return ckpt.load()
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None


def _states(sc: Scenario, z: Zoo | None, methods: tuple[str, ...]) -> dict[str, Loaded | None]:
    """The verified checkpoint of each method ("encoder": the CAVs' encoder; None: random weights), every file
    read and hashed once; ConfigError naming the file when one is broken."""
    if z is None:
        return dict.fromkeys(methods)
    files = _checkpoints(sc, z, methods)
    states = {p: verified(c) for p, c in {c.path: c for c in files.values() if c is not None}.items()}
    return {m: None if c is None else (c, states[c.path]) for m, c in files.items()}


def _seed(sc: Scenario, what: str) -> None:
    torch.manual_seed(sc.seed * 1_000_003 + zlib.crc32(what.encode()))


def _load(module: nn.Module, loaded: Loaded | None, prefix: str, method: str) -> None:
    """Load the `prefix` part of `method`'s checkpoint into `module`; ConfigError naming the file and its rebuild
    command when it was made for another version of the model (missing, unknown or resized weights)."""
    if loaded is None:
        return
    ckpt, state = loaded
    sub = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    if not sub:
        return
    try:
        module.load_state_dict(sub)
    except RuntimeError as e:
        reason = " ".join(str(e).split())
        raise ConfigError(f"{ckpt.path}: the {method} checkpoint's {prefix.rstrip('.')} weights do not fit this "
                          f"version of the model ({reason[:300]}); rebuild it with: {ckpt.rebuild_command}") from None


def _cells(sc: Scenario, z: Zoo | None) -> int | None:
    """The LiDAR fusion grid the scenario's models are built at: its zoo's (models.zoo.Zoo.cells), the preset's
    with random weights; None for a camera encoder (its grid is its own)."""
    if MODALITY[sc.perception.encoder] != "lidar":
        return None
    return get_preset(sc.perception.preset).cells if z is None else z.cells


def _image_backbone(sc: Scenario, z: Zoo | None) -> str | None:
    """A camera encoder's image backbone: its zoo's (models.zoo.Zoo.image_backbone; the first camera zoo's is
    "resnet"), the preset's (None) with random weights or for a LiDAR encoder."""
    return None if MODALITY[sc.perception.encoder] != "camera" or z is None else z.image_backbone


def fusion_cells(sc: Scenario) -> int | None:
    """The LiDAR fusion grid of the scenario's models (_cells)."""
    return _cells(sc, zoo_for(sc))


def wire_ratio(sc: Scenario) -> int:
    """The channel compression ratio r of the feature messages: comm.channel_compression, or where it is
    null the zoo's wire ratio (models.zoo.Zoo.wire_ratio; 1 with random weights or a zoo without compressors)."""
    return _ratio(sc, None if sc.comm.channel_compression is not None else zoo_for(sc))


def build_agent_encoder(sc: Scenario) -> nn.Module:
    """The encoder every CAV runs; identical in every process for a given scenario."""
    z = zoo_for(sc)
    _seed(sc, "encoder")
    enc = build_encoder(sc.perception.encoder, sc.perception.preset, bev_size_m=sc.bev.size_m, cells=_cells(sc, z),
                        image_backbone=_image_backbone(sc, z))
    _load(enc, _states(sc, z, ("encoder",))["encoder"], "encoder.", "encoder")
    return enc.eval()


def runnable_methods(sc: Scenario) -> tuple[str, ...]:
    """perception.methods less what the modality cannot run: early fusion ships LiDAR points, so it needs a LiDAR
    base and, in a mixed fleet, egos that carry a LiDAR (a camera neighbour sends no points: the LiDAR CAVs'
    clouds are merged without it)."""
    egos = ego_ids(sc, [cav_id(i) for i in range(sc.cavs.count)])
    camera_ego = any(agent_type(sc, e).modality != "lidar" for e in egos)
    return tuple(m for m in sc.perception.methods
                 if m != "early" or (sc.perception.modality == "lidar" and not camera_ego))


def build_compressor(sc: Scenario, channels: int) -> ChannelCompressor | None:
    """The channel compression pair of the scenario's wire ratio (None when it is 1): the zoo's trained one
    (`compress` stage), verified like every checkpoint. A ratio the zoo has no compressor for is a ConfigError
    naming the ratio and the command that trains it: behind trained encoders and fusion models a randomly
    initialised compressor would make every intermediate method's result meaningless, silently. Only a run
    whose weights are all random (perception.weights: none; its report says so) builds a seeded random one."""
    if sc.comm.channel_compression == 1:  # uncompressed whatever the zoo
        return None
    z = zoo_for(sc)
    ratio = _ratio(sc, z)
    if ratio == 1:
        return None
    if z is None:
        _seed(sc, "compressor")
        return ChannelCompressor(channels, ratio).eval()
    ckpt = z.compressors.get(ratio)
    if ckpt is None:
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio}: the {z.name} zoo ({z.root}) has no trained "
                          f"compressor for ratio {ratio}; allowed: {', '.join(map(str, [1, *sorted(z.compressors)]))} "
                          f"(or null: the zoo's wire ratio, {z.wire_ratio}); train one with: v2vsim train --data DATA "
                          f"--stage compress --ratios {ratio} --out {z.root} --work WORK (docs/training.md)")
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
        reason = " ".join(str(e).split())
        raise ConfigError(f"{path}: {what} does not fit this version of the model ({reason[:300]}); {remedy}") from None


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


def build_method_models(sc: Scenario, encoder: nn.Module, methods: tuple[str, ...]) -> dict[str, nn.Module]:
    """One CooperativePerception per method, all sharing `encoder` (every method fuses the same messages)."""
    z = zoo_for(sc)
    states, cells, backbone = _states(sc, z, methods), _cells(sc, z), _image_backbone(sc, z)
    out = {}
    for m in methods:
        _seed(sc, f"method:{m}")
        model = build_cooperative(sc.perception.encoder, m, sc.perception.preset, bev_size_m=sc.bev.size_m,
                                  cells=cells, image_backbone=backbone)
        if m == "early":  # early fusion's encoder runs at the ego on merged clouds: its own weights
            _load(model.encoder, states[m], "encoder.", m)
        else:
            model.encoder = encoder
        _load(model.fusion, states[m], "fusion.", m)
        _load(model.heads, states[m], "heads.", m)
        model.heads.for_inference()
        out[m] = model.eval()
    return out


def build_extrapolation(sc: Scenario, method: str = "cobevt") -> FeatureExtrapolation | None:
    """The zoo's receiver-side latency compensation for `method` (models.extrapolation, trained by the
    `extrapolate` stage on top of that method's checkpoint), verified like every checkpoint; None when the
    scenario runs random weights or its zoo has none for `method` (never a randomly initialised one).
    ConfigError naming the file when it is broken, does not fit, or was trained on another checkpoint of
    `method` than the zoo's current one."""
    z = zoo_for(sc)
    ckpt = None if z is None else z.extrapolation.get(method)
    if z is None or ckpt is None:
        return None
    state = verified(ckpt)
    current = _sha(_method_file(sc, z, method))  # the one this run's wire ratio loads
    for file, sha in ckpt.trained_on.items():
        if current != sha:
            raise ConfigError(f"{ckpt.path}: trained on top of {file} (sha256 {sha[:12]}…), not on the zoo's current "
                              f"{method} checkpoint; rebuild it with: {ckpt.rebuild_command}")
    sub = {k[len("extrapolation."):]: v for k, v in state.items() if k.startswith("extrapolation.")}
    channels = get_preset(z.preset).channels
    first = sub.get("net.0.weight")  # [H, 2C, 3, 3]
    try:
        if first is None or first.shape[1] != 2 * channels:
            raise RuntimeError(f"expected a first convolution over 2 x {channels} channels, got "
                               f"{None if first is None else tuple(first.shape)}")
        module = FeatureExtrapolation(channels, first.shape[0])
        module.load_state_dict(sub)
    except RuntimeError as e:
        reason = " ".join(str(e).split())
        raise ConfigError(f"{ckpt.path}: the {method} extrapolation weights do not fit this version of the model "
                          f"({reason[:300]}); rebuild it with: {ckpt.rebuild_command}") from None
    return module.eval()
