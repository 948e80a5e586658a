"""Training stages: what each stage trains and with which defaults (StageSpec, SPECS), the arguments of a
training run (TrainArgs), and each stage's model: built from the `single` stage, frozen where it runs on cached
features, saved and loaded as a checkpoint under --work.

A fusion plugin (models.registry: an installed "v2vsim.fusion" entry point) is a stage of its own name, trained like
the built-in `attfuse` / `fcooper` stages (stage_spec: fusion module + heads, the heads from `single`, on the cached
features of the same frozen encoder and wire); it is not part of `all`, the shipped zoo's recipe."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from models import zoo
from models.build import build_cooperative, preset_image_backbone
from models.compression import ChannelCompressor
from models.cooperative import CooperativePerception
from models.extrapolation import FeatureExtrapolation
from models.presets import get_preset
from models.registry import BUILTIN_METHODS, MODALITY, check_methods, is_intermediate, is_plugin
from v2vsim.data.layout import DatasetError

# Every built-in intermediate method is a stage of its own (models.registry: as their files declare them).
FUSION_STAGES = tuple(m for m in BUILTIN_METHODS if is_intermediate(m))
# `compress`: the wire's channel compressors (one per ratio), trained after the cache and before every stage
# that reads features off the wire (none, the fusion methods), which then train on the zoo's wire ratio.
COMPRESS = "compress"
STAGE_ORDER = ("single", "cache", COMPRESS, "none", "early", *FUSION_STAGES)
# The ratios `--stage compress` trains by default (CoBEVT Table 4's), and the zoo's default wire ratio among
# them: 64 channels -> 8 at 64 x 64 cells = 64 KiB float16 per message, 5.2 Mbps at 10 Hz on a 27 Mbps link.
COMPRESS_RATIOS = (8, 16, 32, 64)
WIRE_RATIO = 8
# Receiver-side latency compensation (models.extrapolation) on top of a method already in the zoo (--out):
# an add-on, run on its own (`--stage extrapolate`), not part of `all`.
EXTRAPOLATE = "extrapolate"
EXTRA_STAGES = (EXTRAPOLATE,)
# A pretrained image backbone (models.image_backbone) fine-tunes at this fraction of the stage's learning rate,
# so that the first steps of the randomly initialised BEV layers above it do not wash out its ImageNet features.
PRETRAINED_LR_SCALE = 0.1


@dataclass(frozen=True)
class StageSpec:
    """What one stage trains and with which defaults (every field can be overridden by a flag)."""

    name: str
    methods: tuple[str, ...]  # zoo methods this stage's checkpoint serves
    inputs: str  # "points" (encoder runs) | "cache" (frozen encoder features)
    target: str  # "self" (own sensors' vehicles) | "coop" (vehicles any CAV saw)
    epochs: int
    samples_per_epoch: int
    batch: int
    lr: float
    max_agents: int
    delays: tuple[int, ...]
    stride: int = 1  # use every stride-th frame (cache stages: the frames the feature cache holds)
    val_samples: int = 120
    distill_weight: float = 0.0
    # Cross-entropy weight of the lane class: markings are ~2 cells wide and rare; unweighted they never
    # reached p >= 0.5 in the single-agent stage (lane IoU 0), so every fine-tuning stage weights them.
    lane_weight: float = 3.0
    # Camera `single` stage: turn each sample's agent frame by U(-d, d) degrees (v2vsim.training.augment).
    yaw_jitter_deg: float = 0.0
    ratio: int = 1  # `compress` stage: the channel compression ratio it trains
    wire_ratio: int | None = None  # a fusion stage trained on this wire instead of the zoo's (--wire-ratio)
    recon_weight: float = 0.0  # `compress` stage: weight of the feature reconstruction loss


SPECS: dict[str, StageSpec] = {
    "single": StageSpec("single", (), "points", "self", 3, 1400, 4, 2e-3, 1, (0,), lane_weight=1.0),
    # `none` (and `late`, whose CAVs run the same heads) get the fine-tuning every fusion method gets,
    # on the same cached features, so that no method wins by training its heads longer.
    "none": StageSpec("none", ("none", "late"), "cache", "self", 3, 1200, 4, 2e-3, 1, (0,)),
    # Early fusion re-trains the encoder on merged clouds (~4x the points): the costliest stage per sample,
    # but it sees as many samples as every other fine-tuning stage (3 x 1200).
    "early": StageSpec("early", ("early",), "points", "coop", 3, 1200, 2, 1e-3, 5, (0, 1, 2)),
    # Neighbours 0 or 1 frame old: a 27 Mbps link delivers feature messages one frame (100 ms) late.
    **{m: StageSpec(m, (m,), "cache", "coop", 3, 1200, 4, 2e-3, 5, (0, 1)) for m in FUSION_STAGES},
}
# KL per cell starts near 0.1 here; weight 10 puts distillation on the scale of the perception losses
# (1e3 made it ~100x them).
SPECS["disconet"] = dataclasses.replace(SPECS["disconet"], distill_weight=10.0)
# FeatureExtrapolation for the zoo's CoBEVT (frozen fusion + heads, the same frozen feature cache): neighbours
# 1-5 frames old (up to comm.max_age_ms 500 at 10 Hz), each with the message before it; only the
# extrapolation module trains. `methods`: the method whose checkpoint it extends (it replaces none).
SPECS[EXTRAPOLATE] = StageSpec(EXTRAPOLATE, ("cobevt",), "cache", "coop", 3, 1200, 4, 1e-3, 5, (1, 2, 3, 4, 5))
# A channel compressor (models.compression) between the frozen encoder's cached features and the frozen `single`
# heads, one CAV's own map: the task loss through the heads plus the features' reconstruction error (relative
# to their mean square), so that the decompressed map serves every fusion method, not only these heads.
SPECS[COMPRESS] = StageSpec(COMPRESS, (), "cache", "self", 3, 1200, 4, 5e-3, 1, (0,), recon_weight=4.0)
# A fusion plugin's stage: the built-in fusion stages' defaults (FUSION_STAGES), under the plugin's name.
PLUGIN_SPEC = SPECS["attfuse"]


def stage_spec(name: str) -> StageSpec:
    """The defaults of stage `name`: SPECS, or for a fusion plugin (models.registry) those of every fusion stage
    (PLUGIN_SPEC) under its name; ValueError (a PluginError for a plugin that cannot be used) otherwise."""
    if name in SPECS:
        return SPECS[name]
    stages_for(name)
    return dataclasses.replace(PLUGIN_SPEC, name=name, methods=(name,))


@dataclass(frozen=True)
class TrainArgs:
    data: Path
    stage: str
    out: Path  # zoo root (manifest.json + <encoder>_<preset>/)
    work: Path  # checkpoints, feature cache
    encoder: str = "pointpillars"
    preset: str = "tiny"
    device: str = "cpu"
    threads: int = 2
    seed: int = 0
    resume: bool = False
    val_every: int = 1  # validate every N epochs and after the last
    workers: int = 0  # DataLoader processes (0: load in the training process)
    overrides: tuple[tuple[str, object], ...] = ()  # StageSpec fields from flags
    command: str = ""
    cells: int | None = None  # LiDAR fusion grid (default: the --out zoo's, else the preset's)
    ratios: tuple[int, ...] = COMPRESS_RATIOS  # `compress` stage
    bf16: bool = False  # bfloat16 autocast in the forward pass (CPU with AMX, or CUDA)
    wire_ratio: int | None = None  # fusion stages: read the neighbours through this ratio's wire (1: uncompressed)
    image_backbone: str | None = None  # camera encoders (default: the --out zoo's, else the preset's)


# ---- models per stage ----------------------------------------------------------------------------


def _prefixed(state: dict, prefix: str) -> dict:
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def train_cells(args: TrainArgs) -> int | None:
    """The LiDAR fusion grid of this training: --cells, else the --out zoo's (a stage joins that zoo), else the
    preset's; None for a camera encoder."""
    if MODALITY[args.encoder] != "lidar":
        return None
    z = zoo.find(args.encoder, args.preset, args.out)
    return args.cells or (get_preset(args.preset).cells if z is None else z.cells)


def train_image_backbone(args: TrainArgs) -> str | None:
    """A camera encoder's image backbone in this training: --image-backbone, else the --out zoo's (a stage joins
    that zoo), else the preset's; None for a LiDAR encoder."""
    if MODALITY[args.encoder] != "camera":
        if args.image_backbone is not None:
            raise ValueError(f"--image-backbone {args.image_backbone}: {args.encoder} is a LiDAR encoder")
        return None
    z = zoo.find(args.encoder, args.preset, args.out)
    return (args.image_backbone or (None if z is None else z.image_backbone)
            or preset_image_backbone(args.encoder, args.preset))


def build_training_model(args: TrainArgs, method: str) -> CooperativePerception:
    """`method`'s model at this training's grid and image backbone, seeded."""
    torch.manual_seed(args.seed)
    return build_cooperative(args.encoder, method, args.preset, cells=train_cells(args),
                             image_backbone=train_image_backbone(args))


def check_zoo_grid(args: TrainArgs) -> None:
    """Before training: a --cells that differs from the --out zoo's grid would be refused at export."""
    z = zoo.find(args.encoder, args.preset, args.out)
    if z is None or not z.files:
        return
    if MODALITY[args.encoder] == "camera":
        have_bb = z.image_backbone
        if args.image_backbone and args.image_backbone != have_bb:
            name = zoo.zoo_name(args.encoder, args.preset)
            raise DatasetError(f"--image-backbone {args.image_backbone}: the zoo at {args.out} ({name}) was trained "
                               f"with the {have_bb} backbone; train a {args.image_backbone} zoo into another --out")
        return
    have = z.cells
    if args.cells and args.cells != have:
        name = zoo.zoo_name(args.encoder, args.preset)
        raise DatasetError(f"--cells {args.cells}: the zoo at {args.out} ({name}) was trained at {have} x {have}; "
                           f"train a {args.cells} x {args.cells} zoo into another --out")


def wire_compressor(args: TrainArgs) -> ChannelCompressor | None:
    """The --out zoo's compressor of its wire ratio (or of --wire-ratio), frozen, through which every stage
    after `compress` reads the neighbours' cached features, as the ego reads them off the wire; None when that
    wire is uncompressed."""
    z = zoo.find(args.encoder, args.preset, args.out)
    ratio = args.wire_ratio or (1 if z is None else z.wire_ratio)
    if ratio == 1:
        return None
    ckpt = None if z is None else z.compressors.get(ratio)
    if ckpt is None:
        raise DatasetError(f"--wire-ratio {ratio}: the zoo at {args.out} has no ratio-{ratio} compressor; train it "
                           f"first (`v2vsim train --stage compress --ratios {ratio} --out {args.out}`)")
    try:
        state = ckpt.load()
    except zoo.ZooError as e:
        raise DatasetError(str(e)) from None
    comp = ChannelCompressor(get_preset(args.preset).channels, ratio)
    comp.load_state_dict(_prefixed(state, "compressor."))
    for p in comp.parameters():
        p.requires_grad_(False)
    return comp.eval()


def stage_dir(spec: StageSpec) -> str:
    """The stage's folder under --work: its name, and for `compress` its ratio too (compress_r8, ...), for a
    fusion stage on another wire than the zoo's that wire's (cobevt_wire16, ...)."""
    if spec.wire_ratio is not None:
        return f"{spec.name}_wire{spec.wire_ratio}"
    return f"{spec.name}_r{spec.ratio}" if spec.name == COMPRESS else spec.name


def stage_file(args: TrainArgs, stage: str) -> Path:
    return args.work / stage / "final.pt"


def load_stage_state(args: TrainArgs, stage: str) -> dict:
    """A finished stage's weights: its final.pt under --work, or where --work has none (a zoo trained over
    several sessions, its work folder lost) the stage's verified checkpoint in the --out zoo."""
    p = stage_file(args, stage)
    if p.is_file():
        return torch.load(p, map_location="cpu", weights_only=True)["state_dict"]
    z = zoo.find(args.encoder, args.preset, args.out)
    name = "single.pt" if stage == "single" else f"{stage}.pt"
    if z is not None and name in z.files:
        try:
            return z.files[name].load()
        except zoo.ZooError as e:
            raise DatasetError(str(e)) from None
    raise DatasetError(f"{p}: stage {stage!r} has not finished; run `v2vsim train --stage {stage}` first")


def zoo_state(args: TrainArgs, method: str) -> dict:
    """The verified state_dict of `method`'s checkpoint ("encoder": the CAVs' encoder) in the zoo at --out."""
    z = zoo.find(args.encoder, args.preset, args.out)
    ckpt = None if z is None else z.method(method)
    if ckpt is None:
        stage = "single" if method == "encoder" else method
        raise DatasetError(f"{args.out / zoo.MANIFEST}: no {method} checkpoint of "
                           f"{zoo.zoo_name(args.encoder, args.preset)}; train it into this --out first "
                           f"(`v2vsim train --stage {stage} --out {args.out}`)")
    try:
        return ckpt.load()
    except zoo.ZooError as e:
        raise DatasetError(str(e)) from None


def build_extrapolation_model(args: TrainArgs, spec: StageSpec) -> nn.Module:
    """The zoo's (--out) model of spec.methods[0] with a fresh FeatureExtrapolation as `.extrapolation`; its
    encoder keeps its seeded initial weights (the stage reads the feature cache, never runs it)."""
    (method,) = spec.methods
    model = build_training_model(args, method)
    state = zoo_state(args, method)
    model.fusion.load_state_dict(_prefixed(state, "fusion."))
    model.heads.load_state_dict(_prefixed(state, "heads."))
    model.extrapolation = FeatureExtrapolation(model.encoder.out_channels)
    return model


def build_stage_model(args: TrainArgs, spec: StageSpec) -> nn.Module:
    if spec.name == EXTRAPOLATE:
        return build_extrapolation_model(args, spec)
    method = "none" if spec.name in ("single", COMPRESS) else spec.name
    model = build_training_model(args, method)
    backbone = getattr(model.encoder, "image_backbone", None)
    if spec.name == "single" and backbone is not None and backbone.pretrained:
        backbone.load_pretrained()  # the single-agent stage fine-tunes it (a resumed run's last.pt replaces it)
    if spec.name != "single":
        single = load_stage_state(args, "single")
        model.encoder.load_state_dict(_prefixed(single, "encoder."))
        model.heads.load_state_dict(_prefixed(single, "heads."))
    if spec.name == COMPRESS:  # a fresh compressor between the frozen encoder and the frozen heads
        model.compressor = ChannelCompressor(model.encoder.out_channels, spec.ratio)
    return model


def param_groups(model: nn.Module, spec: StageSpec) -> list[dict]:
    """AdamW parameter groups with their peak learning rates: a pretrained image backbone fine-tunes at
    PRETRAINED_LR_SCALE x the stage's rate (the rest of a camera encoder and the heads start from scratch)."""
    params = trainable(model, spec)
    backbone = getattr(model.encoder, "image_backbone", None)
    if backbone is None or not backbone.pretrained or spec.inputs == "cache":
        return [{"params": params, "lr": spec.lr}]
    mine = {id(p) for p in backbone.parameters()}
    return [{"params": [p for p in params if id(p) in mine], "lr": spec.lr * PRETRAINED_LR_SCALE},
            {"params": [p for p in params if id(p) not in mine], "lr": spec.lr}]


def trainable(model: nn.Module, spec: StageSpec) -> list[nn.Parameter]:
    if spec.name in (EXTRAPOLATE, COMPRESS):  # the model stays frozen; gradients only flow through it
        add_on = model.extrapolation if spec.name == EXTRAPOLATE else model.compressor
        for p in model.parameters():
            p.requires_grad_(False)
        params = list(add_on.parameters())
        for p in params:
            p.requires_grad_(True)
        return params
    if spec.inputs == "cache":
        for p in model.encoder.parameters():
            p.requires_grad_(False)
        return [*model.fusion.parameters(), *model.heads.parameters()]
    return list(model.parameters())


def state_to_save(model: nn.Module, spec: StageSpec) -> dict:
    if spec.name == EXTRAPOLATE:
        return {f"extrapolation.{k}": v for k, v in model.extrapolation.state_dict().items()}
    if spec.name == COMPRESS:
        return {f"compressor.{k}": v for k, v in model.compressor.state_dict().items()}
    parts = {"fusion": model.fusion, "heads": model.heads}
    if spec.name in ("single", "early"):
        parts["encoder"] = model.encoder
    return {f"{p}.{k}": v for p, m in parts.items() for k, v in m.state_dict().items()}


def stages_for(name: str, encoder: str = "pointpillars") -> list[str]:
    """The stages `--stage name` runs: `all` = the shipped zoo's recipe (STAGE_ORDER; not the plugins), else the
    named stage, a fusion plugin's too (imported and checked against the fusion contract: PluginError if broken)."""
    if name == "all":  # a camera zoo: no early fusion (LiDAR points), and its 32 x 32 message fits uncompressed
        return [s for s in STAGE_ORDER if MODALITY[encoder] == "lidar" or s not in ("early", COMPRESS)]
    if name in STAGE_ORDER + EXTRA_STAGES:
        return [name]
    if is_plugin(name):
        check_methods([name])
        return [name]
    from models.registry import fusion_names

    plugins = [m for m in fusion_names() if is_plugin(m)]
    raise ValueError(f"--stage {name!r}: allowed: all, {', '.join(STAGE_ORDER + EXTRA_STAGES)}"
                     + (f", or a fusion plugin's name: {', '.join(plugins)}" if plugins else
                        " (or an installed fusion plugin's name: none is installed)"))
