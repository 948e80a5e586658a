"""A scenario's model needs, resolved once (`plan_models`) into one immutable `ModelPlan`: the zoo and its grid,
image backbone and wire ratio, the methods that run, and the checkpoint of each model (with the sha256 its
manifest records, which loading verifies). Every builder (v2vsim.perception.build, .aligned) and the checks
(v2vsim.perception.checks) take the plan, so a process reads the zoo's manifest once.

`plan_models` raises only what finding the zoo raises (perception.weights: a missing zoo folder, a malformed
manifest). What a zoo cannot give one model (a fusion method without a checkpoint for the run's wire, a wire ratio
without a trained compressor, a plugin's checkpoint trained on another encoder, a mixed fleet's missing aligned
encoder) is recorded in the plan and raised by whoever needs that model, as before the plan: a process that
never builds a model never fails on it.

`perception.weights`: "auto" = models/weights/ when it ships this encoder/preset (else random), "none" = random,
or a path to a zoo folder with its own manifest.json (as `v2vsim train --out` writes).

A fusion plugin (models.registry) loads its checkpoint like a built-in, from the scenario's zoo. Where that zoo
has none and the plugin ships a zoo of its own (its entry point object's `weights` attribute: a folder with a
manifest.json), the checkpoint comes from there if it was trained on this zoo's encoder and wire (_plugin_zoo:
the manifests' sha256 of the encoder and of the wire's compressor must match); else the method runs untrained,
as every method without a checkpoint does, and the report and metrics.json say so.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

from models import zoo
from models.presets import get_preset
from models.registry import MODALITY, is_intermediate, is_plugin, plugin_weights
from models.zoo import Aligned, Checkpoint, Zoo
from v2vsim.config import ConfigError, Scenario
from v2vsim.perception.fleet import AgentType, agent_type, base_type, extra_types, is_mixed
from v2vsim.sensors.sensing import ego_ids
from v2vsim.traffic.base import cav_id

# what resolving one model's checkpoint may raise: kept in the plan, raised where that model is needed
Refusal = ConfigError | ValueError


@dataclass(frozen=True)
class ModelPlan:
    """What a scenario's models are and which weights each loads, resolved once by `plan_models`.

    `checkpoints`: per planned method and "encoder" (the CAVs' encoder), the checkpoint it loads (a plugin's own
    zoo's where that is where it comes from), None where it runs with seeded random weights; `refused`: per
    planned key whose resolution failed, the error its use raises (`checkpoint`). `compressor`: the wire ratio's
    trained compressor (None: uncompressed, or random weights), `compressor_refused` where the zoo has none.
    `aligned`: per encoder of a mixed fleet's other agent types, the base zoo's aligned encoder (None: it has
    none). Immutable: mappings are read-only views, sequences tuples."""

    source: str  # the scenario's path, for messages
    encoder: str  # perception.encoder
    preset: str  # perception.preset
    modality: str  # perception.modality
    weights: str  # perception.weights, as the scenario gives it
    bev_size_m: float
    seed: int  # the scenario seed: random weights are seeded from it and each model's name
    compensation: bool  # comm.compensation: the ego loads each method's trained extrapolation
    zoo: Zoo | None  # the parsed zoo entry; None = seeded random weights
    cells: int | None  # the LiDAR fusion grid the models are built at (None: a camera encoder's own)
    image_backbone: str | None  # a camera encoder's image backbone (None: the preset's)
    wire_ratio: int  # the channel compression ratio of the feature messages (1: uncompressed)
    methods: tuple[str, ...]  # the runnable methods of perception.methods (runnable_methods)
    checkpoints: Mapping[str, Checkpoint | None]
    refused: Mapping[str, Refusal]
    compressor: Checkpoint | None
    compressor_refused: ConfigError | None
    extrapolation: Mapping[str, Checkpoint]  # per method, the zoo's latency-compensation add-on
    aligned: Mapping[str, Aligned | None]
    base: AgentType  # the type of every CAV no fleet group names
    types: Mapping[str, AgentType]  # each CAV's type (cavs.fleet)
    mixed: bool  # cavs.fleet gives some CAVs their own sensor and encoder (v2vsim.perception.fleet.is_mixed)

    def agent_type(self, cav: str) -> AgentType:
        """The sensor and encoder of CAV `cav` (the base's for a CAV no fleet group names)."""
        return self.types.get(cav, self.base)

    def checkpoint(self, method: str) -> Checkpoint | None:
        """The checkpoint `method` ("encoder": the CAVs' encoder) loads, None for random weights; the error its
        resolution raised (ConfigError naming the file or ratio and its remedy) where it failed."""
        if method in self.refused:
            raise self.refused[method].with_traceback(None) from None
        if method not in self.checkpoints:
            raise ValueError(f"method {method!r} is not part of this model plan (planned: "
                             f"{', '.join(self.checkpoints)}); pass it to plan_models(sc, extra=...)")
        return self.checkpoints[method]

    def wire_compressor(self) -> Checkpoint | None:
        """The trained compressor of the wire ratio (None: uncompressed, or random weights); ConfigError naming
        the ratio and the command that trains it where the zoo has none."""
        if self.compressor_refused is not None:
            raise self.compressor_refused.with_traceback(None) from None
        return self.compressor


def zoo_for(sc: Scenario) -> Zoo | None:
    """The zoo of the checkpoints the scenario asks for, parsed (one read of its manifest); None = seeded random
    weights. ConfigError for a perception.weights folder without a manifest or this encoder/preset, or a
    malformed manifest."""
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


def runnable_methods(sc: Scenario) -> tuple[str, ...]:
    """perception.methods less what the modality cannot run: early fusion ships LiDAR points, so it needs a LiDAR
    base and, in a mixed fleet, egos that carry a LiDAR (a camera neighbour sends no points: the LiDAR CAVs'
    clouds are merged without it)."""
    egos = ego_ids(sc, [cav_id(i) for i in range(sc.cavs.count)])
    camera_ego = any(agent_type(sc, e).modality != "lidar" for e in egos)
    return tuple(m for m in sc.perception.methods
                 if m != "early" or (sc.perception.modality == "lidar" and not camera_ego))


def _ratio(sc: Scenario, z: Zoo | None) -> int:
    """comm.channel_compression, or where it is null the zoo's wire ratio (1 with random weights)."""
    if sc.comm.channel_compression is not None:
        return sc.comm.channel_compression
    return 1 if z is None else z.wire_ratio


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


def _sha(ckpt: Checkpoint | None) -> str | None:
    return None if ckpt is None else ckpt.sha256


def _method_file(sc: Scenario, z: Zoo, method: str, ratio: int) -> Checkpoint | None:
    """The checkpoint `method` ("encoder": the CAVs' encoder) loads from the zoo `z`. An intermediate method loads
    the one trained on the scenario's wire ratio: the zoo's own wire is its "methods" file, another ratio
    (comm.channel_compression) needs a checkpoint trained on that wire ("wire_methods"). Where there is none it
    is a ConfigError: a fusion model fed another wire's decoded features runs off the distribution it was
    trained on, and its results would say nothing about the method."""
    if method == "encoder" or not is_intermediate(method):
        return z.method(method)
    ckpt = z.method(method, ratio)
    if ckpt is None and method in z.methods:
        have = ", ".join(map(str, z.wire_ratios(method)))
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio}: the {z.name} zoo's {method} was trained "
                          f"on the ratio-{z.wire_ratio} wire and has no checkpoint for ratio {ratio} (ratios it "
                          f"has: {have}); fed another wire's features it would run off its training distribution. "
                          f"Train one with: v2vsim train --data DATA --stage {method} --wire-ratio {ratio} --out "
                          f"{z.root} --work WORK (docs/training.md), or leave {method} out of perception.methods")
    return ckpt


def _plugin_zoo(sc: Scenario, method: str, z: Zoo, ratio: int) -> Zoo | None:
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


def _checkpoint(sc: Scenario, z: Zoo, method: str, ratio: int) -> Checkpoint | None:
    """The checkpoint of `method` (None: it runs untrained): the scenario's zoo `z`'s, or for a fusion plugin that
    zoo has no checkpoint of, the one of the plugin's own zoo (_plugin_zoo) where it ships a fitting one."""
    ckpt = _method_file(sc, z, method, ratio)
    own = None if ckpt is not None or method == "encoder" or not is_plugin(method) else _plugin_zoo(sc, method, z,
                                                                                                   ratio)
    return ckpt if own is None else own.method(method, ratio)


def _compressor(sc: Scenario, z: Zoo | None, ratio: int) -> Checkpoint | None:
    """The trained compressor of the wire ratio; ConfigError naming the ratio and the command that trains it where
    the zoo has none: behind trained encoders and fusion models a randomly initialised compressor would make every
    intermediate method's result meaningless, silently (only random weights build a seeded random one)."""
    if ratio == 1 or z is None:
        return None
    ckpt = z.compressors.get(ratio)
    if ckpt is None:
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio}: the {z.name} zoo ({z.root}) has no trained "
                          f"compressor for ratio {ratio}; allowed: {', '.join(map(str, [1, *sorted(z.compressors)]))} "
                          f"(or null: the zoo's wire ratio, {z.wire_ratio}); train one with: v2vsim train --data DATA "
                          f"--stage compress --ratios {ratio} --out {z.root} --work WORK (docs/training.md)")
    return ckpt


def plan_models(sc: Scenario, extra: tuple[str, ...] = ()) -> ModelPlan:
    """The scenario's ModelPlan: its zoo read once, and the checkpoint of the encoder, of `none` (the single-agent
    model every CAV and the defence run), of every method of perception.methods and of `extra` (methods a caller
    builds beyond those: the env's). ConfigError only where finding the zoo fails (module docstring)."""
    z = zoo_for(sc)
    ratio = _ratio(sc, z)
    checkpoints: dict[str, Checkpoint | None] = {}
    refused: dict[str, Refusal] = {}
    for m in dict.fromkeys(("encoder", "none", *sc.perception.methods, *extra)):
        try:
            checkpoints[m] = None if z is None else _checkpoint(sc, z, m, ratio)
        except (ConfigError, ValueError) as e:  # raised where the method is built (ModelPlan.checkpoint)
            refused[m] = e
    compressor, compressor_refused = None, None
    try:
        compressor = _compressor(sc, z, ratio)
    except ConfigError as e:  # raised where the compressor is built or checked (ModelPlan.wire_compressor)
        compressor_refused = e
    cavs = [cav_id(i) for i in range(sc.cavs.count)] + [c for g in sc.cavs.fleet for c in g.cavs]
    return ModelPlan(
        source=sc.source, encoder=sc.perception.encoder, preset=sc.perception.preset,
        modality=sc.perception.modality, weights=sc.perception.weights, bev_size_m=sc.bev.size_m, seed=sc.seed,
        compensation=sc.comm.compensation, zoo=z, cells=_cells(sc, z), image_backbone=_image_backbone(sc, z),
        wire_ratio=ratio, methods=runnable_methods(sc), checkpoints=MappingProxyType(checkpoints),
        refused=MappingProxyType(refused), compressor=compressor, compressor_refused=compressor_refused,
        extrapolation=MappingProxyType({} if z is None else dict(z.extrapolation)),
        aligned=MappingProxyType({t.encoder: None if z is None else z.aligned.get(t.encoder) for t in extra_types(sc)}),
        base=base_type(sc), types=MappingProxyType({c: agent_type(sc, c) for c in dict.fromkeys(cavs)}),
        mixed=is_mixed(sc))
