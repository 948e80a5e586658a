"""Which models a scenario runs, with which weights: the encoder every CAV shares and one
CooperativePerception per fusion method, built by name from the scenario's `perception` section.

Weights: `perception.weights: auto` loads the zoo's checkpoints (models.zoo: models/weights/
<encoder>_<preset>/, verified against manifest.json); where none ship, every process builds the same
randomly initialised models from the scenario seed (so CAV encoders and the ego agree), and the
report says the weights are untrained.

A fusion plugin (models.registry) loads its checkpoint like a built-in, from the scenario's zoo (`perception.weights:
PATH`, a folder `v2vsim train --stage NAME --out PATH` wrote it into). Where that zoo has none and the plugin ships
a zoo of its own (its entry point object's `weights` attribute: a folder with a manifest.json), the checkpoint comes
from there if it was trained on this zoo's encoder and wire (plugin_zoo: the manifests' sha256 of the encoder and
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
from v2vsim.config import ConfigError, Scenario
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.fleet import agent_type
from v2vsim.sensors.sensing import ego_ids
from v2vsim.traffic.base import cav_id


def zoo_for(sc: Scenario) -> tuple[Path, dict] | None:
    """(zoo root, manifest entry) of the checkpoints the scenario asks for; None = seeded random weights.

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
        entry = zoo.zoo_entry(sc.perception.encoder, sc.perception.preset, root)
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None
    if entry is None:
        if spec != "auto":
            raise ConfigError(f"{sc.source}: perception.weights: {root} has no "
                              f"{zoo.zoo_name(sc.perception.encoder, sc.perception.preset)} checkpoints")
        return None
    return root, entry


def method_file(sc: Scenario, root: Path, entry: dict, method: str) -> Path | None:
    """The checkpoint `method` ("encoder": the CAVs' encoder) loads from the zoo (root, entry). An intermediate
    method loads the one trained on the scenario's wire ratio: the zoo's own wire is its "methods" file, another
    ratio (comm.channel_compression) needs a checkpoint trained on that wire ("wire_methods"). Where there is
    none it is a ConfigError: a fusion model fed another wire's decoded features runs off the distribution it
    was trained on, and its results would say nothing about the method."""
    enc, preset = sc.perception.encoder, sc.perception.preset
    if method == "encoder" or not is_intermediate(method):
        return zoo.method_file(entry, method, root, enc, preset)
    ratio = wire_ratio(sc)
    path = zoo.wire_method_file(entry, method, ratio, root, enc, preset)
    if path is None and method in entry["methods"]:
        have = ", ".join(map(str, zoo.wire_ratios_of(entry, method)))
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio}: the {zoo.zoo_name(enc, preset)} zoo's "
                          f"{method} was trained on the ratio-{zoo.wire_ratio(entry)} wire and has no checkpoint for "
                          f"ratio {ratio} (ratios it has: {have}); fed another wire's features it would run off its "
                          f"training distribution. Train one with: v2vsim train --data DATA --stage {method} "
                          f"--wire-ratio {ratio} --out {root} --work WORK (docs/training.md), or leave {method} out "
                          "of perception.methods")
    return path


def _file_sha(entry: dict, name: str | None) -> str | None:
    return None if name is None else (entry["files"].get(name) or {}).get("sha256")


def plugin_zoo(sc: Scenario, method: str, z: tuple[Path, dict]) -> tuple[Path, dict] | None:
    """(root, entry) of the zoo a fusion plugin ships (models.registry.plugin_weights) when it holds `method`'s
    checkpoint for this encoder/preset and wire, trained on the encoder and wire compressor of the scenario's zoo
    `z` (the sha256 its manifest records for them equal z's); None when the plugin ships no zoo or none for this
    encoder/preset. ConfigError when it does but was trained on another encoder or wire: fused from other
    features its results would say nothing about the method."""
    folder = plugin_weights(method)
    if folder is None:
        return None
    enc, preset = sc.perception.encoder, sc.perception.preset
    try:
        entry = zoo.zoo_entry(enc, preset, folder)
    except zoo.ZooError as e:
        raise ConfigError(f"fusion plugin {method!r}: its weights {folder}: {e}") from None
    ratio = wire_ratio(sc)
    if entry is None or zoo.wire_method_file(entry, method, ratio, folder, enc, preset) is None:
        return None
    root, mine = z
    why = []
    if _file_sha(entry, entry.get("encoder")) != _file_sha(mine, mine.get("encoder")):
        why.append("its encoder")
    if zoo.zoo_cells(entry, 0) != zoo.zoo_cells(mine, 0) or zoo.zoo_image_backbone(entry) != zoo.zoo_image_backbone(
            mine):
        why.append("its grid or image backbone")
    if ratio > 1 and _file_sha(entry, (entry.get("compressors") or {}).get(str(ratio))) != _file_sha(
            mine, (mine.get("compressors") or {}).get(str(ratio))):
        why.append(f"its ratio-{ratio} wire compressor")
    if why:
        raise ConfigError(f"{sc.source}: perception.methods: fusion plugin {method!r}: the checkpoint it ships "
                          f"({folder / zoo.zoo_name(enc, preset)}) was trained on another model than the "
                          f"{zoo.zoo_name(enc, preset)} zoo at {root} ({' and '.join(why)} differ: manifest sha256); "
                          f"train {method} on this zoo (v2vsim train --data DATA --stage {method} --out COPY_OF_ZOO "
                          "--work WORK, docs/training.md) and run with perception.weights: COPY_OF_ZOO")
    return folder, entry


def method_zoo(sc: Scenario, method: str) -> tuple[Path, dict] | None:
    """(root, entry) of the zoo `method`'s checkpoint comes from: the scenario's (zoo_for), or for a fusion plugin
    that zoo has no checkpoint of, the plugin's own (plugin_zoo) where it ships a fitting one; None: random."""
    z = zoo_for(sc)
    if z is None or method == "encoder" or not is_plugin(method) or method_file(sc, z[0], z[1], method) is not None:
        return z
    return plugin_zoo(sc, method, z) or z


def method_checkpoints(sc: Scenario, methods: tuple[str, ...]) -> dict[str, str | None]:
    """Checkpoint file each method loads (relative to the zoo root; a plugin's own zoo's file: its absolute path),
    None where weights are random."""
    z = zoo_for(sc)
    out: dict[str, str | None] = {}
    for m in methods:
        mz = method_zoo(sc, m)
        f = None if mz is None else method_file(sc, mz[0], mz[1], m)
        out[m] = None if f is None else str(f.relative_to(mz[0]) if z is not None and mz[0] == z[0] else f)
    return out


def _states(sc: Scenario, methods: tuple[str, ...]) -> dict[str, dict | None]:
    """Verified state_dict of each method's checkpoint ("encoder": the CAVs' encoder; None: random
    weights), every file read and hashed once; ConfigError naming the file when one is broken."""
    if zoo_for(sc) is None:
        return dict.fromkeys(methods)
    zoos = {m: method_zoo(sc, m) for m in methods}
    files = {m: method_file(sc, *zoos[m], m) for m in methods}  # type: ignore[misc]  # a zoo: every method has one
    loaded: dict[Path, dict] = {}
    try:
        for m, f in files.items():
            if f is not None and f not in loaded:
                loaded[f] = zoo.load_checkpoint(f, zoos[m][1])  # type: ignore[index]
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None
    return {m: None if f is None else loaded[f] for m, f in files.items()}


def _seed(sc: Scenario, what: str) -> None:
    torch.manual_seed(sc.seed * 1_000_003 + zlib.crc32(what.encode()))


def _load(module: nn.Module, state: dict | None, prefix: str, sc: Scenario, method: str) -> None:
    """Load the `prefix` part of `method`'s checkpoint state into `module`; ConfigError naming the file and
    its rebuild command when it was made for another version of the model (missing, unknown or resized
    weights)."""
    if state is None:
        return
    sub = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    if not sub:
        return
    try:
        module.load_state_dict(sub)
    except RuntimeError as e:
        root, entry = method_zoo(sc, method)  # type: ignore[misc]  # a state was loaded, so there is a zoo
        path = method_file(sc, root, entry, method)
        reason = " ".join(str(e).split())
        raise ConfigError(f"{path}: the {method} checkpoint's {prefix.rstrip('.')} weights do not fit this "
                          f"version of the model ({reason[:300]}); rebuild it with: "
                          f"{zoo.rebuild_command(path, entry)}") from None


def fusion_cells(sc: Scenario) -> int | None:
    """The LiDAR fusion grid the scenario's models are built at: its zoo's (models.zoo.zoo_cells), the
    preset's with random weights; None for a camera encoder (its grid is its own)."""
    if MODALITY[sc.perception.encoder] != "lidar":
        return None
    z = zoo_for(sc)
    return zoo.zoo_cells(None if z is None else z[1], get_preset(sc.perception.preset).cells)


def image_backbone(sc: Scenario) -> str | None:
    """A camera encoder's image backbone: its zoo's (models.zoo.zoo_image_backbone; the first camera zoo's
    is "resnet"), the preset's (None) with random weights or for a LiDAR encoder."""
    if MODALITY[sc.perception.encoder] != "camera":
        return None
    z = zoo_for(sc)
    return zoo.zoo_image_backbone(None if z is None else z[1])


def wire_ratio(sc: Scenario) -> int:
    """The channel compression ratio r of the feature messages: comm.channel_compression, or where it is
    null the zoo's wire ratio (models.zoo.wire_ratio; 1 with random weights or a zoo without compressors)."""
    if sc.comm.channel_compression is not None:
        return sc.comm.channel_compression
    z = zoo_for(sc)
    return zoo.wire_ratio(None if z is None else z[1])


def build_agent_encoder(sc: Scenario) -> nn.Module:
    """The encoder every CAV runs; identical in every process for a given scenario."""
    _seed(sc, "encoder")
    enc = build_encoder(sc.perception.encoder, sc.perception.preset, bev_size_m=sc.bev.size_m, cells=fusion_cells(sc),
                        image_backbone=image_backbone(sc))
    _load(enc, _states(sc, ("encoder",))["encoder"], "encoder.", sc, "encoder")
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
    ratio = wire_ratio(sc)
    if ratio == 1:
        return None
    z = zoo_for(sc)
    if z is None:
        _seed(sc, "compressor")
        return ChannelCompressor(channels, ratio).eval()
    root, entry = z
    enc, preset = sc.perception.encoder, sc.perception.preset
    path = zoo.compressor_file(entry, ratio, root, enc, preset)
    if path is None:
        shipped = sorted(int(r) for r in entry.get("compressors") or {})
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio}: the {zoo.zoo_name(enc, preset)} zoo "
                          f"({root}) has no trained compressor for ratio {ratio}; allowed: "
                          f"{', '.join(map(str, [1, *shipped]))} (or null: the zoo's wire ratio, "
                          f"{zoo.wire_ratio(entry)}); train one with: v2vsim train --data DATA --stage compress "
                          f"--ratios {ratio} --out {root} --work WORK (docs/training.md)")
    try:
        state = zoo.load_checkpoint(path, entry)
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None
    comp = ChannelCompressor(channels, ratio)
    load_part(comp, state, "compressor.", path, f"the ratio-{ratio} compressor",
              f"rebuild it with: {zoo.rebuild_command(path, entry)}")
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
    states, cells, backbone = _states(sc, methods), fusion_cells(sc), image_backbone(sc)
    out = {}
    for m in methods:
        _seed(sc, f"method:{m}")
        model = build_cooperative(sc.perception.encoder, m, sc.perception.preset, bev_size_m=sc.bev.size_m,
                                  cells=cells, image_backbone=backbone)
        state = states[m]
        if m == "early":  # early fusion's encoder runs at the ego on merged clouds: its own weights
            _load(model.encoder, state, "encoder.", sc, m)
        else:
            model.encoder = encoder
        _load(model.fusion, state, "fusion.", sc, m)
        _load(model.heads, state, "heads.", sc, m)
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
    if z is None:
        return None
    root, entry = z
    enc, preset = sc.perception.encoder, sc.perception.preset
    path = zoo.extrapolation_file(entry, method, root, enc, preset)
    if path is None:
        return None
    try:
        state = zoo.load_checkpoint(path, entry)
    except zoo.ZooError as e:
        raise ConfigError(str(e)) from None
    rebuild = zoo.rebuild_command(path, entry)
    base = (entry["files"].get(path.name) or {}).get("extrapolates")
    current = method_file(sc, root, entry, method)  # the one this run's wire ratio loads
    if base is not None and (current is None
                             or (entry["files"].get(current.name) or {}).get("sha256") != base["sha256"]):
        raise ConfigError(f"{path}: trained on top of {base['file']} (sha256 {base['sha256'][:12]}…), not on the "
                          f"zoo's current {method} checkpoint; rebuild it with: {rebuild}")
    sub = {k[len("extrapolation."):]: v for k, v in state.items() if k.startswith("extrapolation.")}
    channels = get_preset(preset).channels
    first = sub.get("net.0.weight")  # [H, 2C, 3, 3]
    try:
        if first is None or first.shape[1] != 2 * channels:
            raise RuntimeError(f"expected a first convolution over 2 x {channels} channels, got "
                               f"{None if first is None else tuple(first.shape)}")
        module = FeatureExtrapolation(channels, first.shape[0])
        module.load_state_dict(sub)
    except RuntimeError as e:
        reason = " ".join(str(e).split())
        raise ConfigError(f"{path}: the {method} extrapolation weights do not fit this version of the model "
                          f"({reason[:300]}); rebuild it with: {rebuild}") from None
    return module.eval()
