"""A mixed fleet's models (cavs.fleet; v2vsim.perception.fleet): the feature space a scenario's fusion models were
trained on and the label each CAV's feature messages carry, and each CAV's encoder: the base's, or its type's
encoder backward-aligned into the base's space (models.aligner, the `align` training stage), verified against the
base it was aligned to."""

from __future__ import annotations

from torch import nn

from models import zoo
from models.aligner import AlignedEncoder
from models.aligner import build_aligned_encoder as build_aligned
from models.build import build_encoder
from models.presets import get_preset
from models.zoo import Aligned
from v2vsim.config import ConfigError
from v2vsim.perception.build import _seed, build_agent_encoder, load_part, verified
from v2vsim.perception.plan import ModelPlan, _sha


def feature_space(plan: ModelPlan) -> str:
    """The name of the feature space the scenario's fusion models were trained on: its zoo and the sha256 (12
    hex digits) of the encoder checkpoint that defines it, e.g. "pointpillars_tiny:f487cbd52552"; with random
    weights the seed instead ("pointpillars_tiny:random-seed0")."""
    name = zoo.zoo_name(plan.encoder, plan.preset)
    if plan.zoo is None:
        return f"{name}:random-seed{plan.seed}"
    return f"{name}:{(_sha(plan.zoo.encoder_file) or 'none')[:12]}"


def space_label(plan: ModelPlan, cav: str) -> str:
    """What CAV `cav`'s feature messages name as their origin (Message.space): "<encoder>@<feature space>" in a
    mixed fleet, "" (nothing on the wire, the bytes of a single-encoder run) otherwise."""
    return f"{plan.agent_type(cav).encoder}@{feature_space(plan)}" if plan.mixed else ""


def build_cav_encoder(plan: ModelPlan, cav: str) -> nn.Module:
    """The encoder CAV `cav` runs: the base's (build_agent_encoder), or its type's aligned encoder."""
    t = plan.agent_type(cav)
    return build_agent_encoder(plan) if t == plan.base else build_aligned_encoder(plan, t.encoder)


def aligned_state(plan: ModelPlan, encoder: str) -> tuple[Aligned, dict, str]:
    """The plan zoo's `encoder` aligned into its feature space: its record, its verified state_dict and the
    command that re-aligns it. ConfigError (one line) when the zoo has none, or when it was aligned to other base
    checkpoints than the zoo's current ones (its manifest record names their sha256): fused with this base its
    features would land off the space the fusion models were trained on."""
    z = plan.zoo
    base = zoo.zoo_name(plan.encoder, plan.preset)
    train = (f"v2vsim train --data CAMERA_DATA --stage align --encoder {encoder} --out "
             f"{zoo.WEIGHTS_DIR if z is None else z.root} --work WORK (docs/training.md)")
    if z is None:
        raise ConfigError(f"{plan.source}: cavs.fleet: {encoder} CAVs need the {base} zoo's aligned {encoder} "
                          f"encoder, and perception.weights is {plan.weights!r} (random weights have no aligned "
                          "encoder); allowed: 'auto' or a zoo folder")
    if encoder not in plan.aligned:
        raise ValueError(f"encoder {encoder!r} is no agent type of this plan's fleet (planned: "
                         f"{', '.join(plan.aligned) or 'none'})")
    aligned = plan.aligned[encoder]
    if aligned is None:
        raise ConfigError(f"{plan.source}: cavs.fleet: the {base} zoo at {z.root} has no {encoder} encoder aligned to "
                          f"it; train one with: {train}")
    path = aligned.checkpoint.path
    state = verified(aligned.checkpoint)
    for file, sha in aligned.checkpoint.trained_on.items():
        have = _sha(z.files.get(file))
        if have != sha:
            raise ConfigError(f"{path}: aligned to {base}/{file} sha256 {sha[:12]}…, but the base zoo at {z.root} has "
                              f"{base}/{file} {'sha256 ' + have[:12] + '…' if have else 'missing'}: a stale pairing; "
                              f"re-align with: {train}")
    return aligned, state, train


def aligned_module(plan: ModelPlan, encoder: str, aligned: Aligned) -> AlignedEncoder:
    """The AlignedEncoder `aligned` was saved from, its weights as initialised (seeded)."""
    assert plan.zoo is not None  # aligned_state refuses random weights
    _seed(plan, f"aligned:{encoder}")  # every weight is loaded below, as in every process: the same module anyway
    camera = build_encoder(encoder, plan.preset, bev_size_m=plan.bev_size_m, image_backbone=aligned.image_backbone)
    return build_aligned(camera, get_preset(plan.preset).channels, plan.zoo.cells, aligned.blocks)


def build_aligned_encoder(plan: ModelPlan, encoder: str) -> AlignedEncoder:
    """The plan zoo's `encoder` backward-aligned into its feature space (the `align` stage: models.aligner),
    verified like every checkpoint; ConfigError (one line) where aligned_state refuses it or it does not fit."""
    aligned, state, train = aligned_state(plan, encoder)
    module = aligned_module(plan, encoder, aligned)
    load_part(module, state, "encoder.", aligned.checkpoint.path, f"the aligned {encoder} encoder",
              f"re-align with: {train}")
    return module.eval()
