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
from v2vsim.config import ConfigError, Scenario
from v2vsim.perception.build import _seed, _sha, build_agent_encoder, load_part, verified, zoo_for
from v2vsim.perception.fleet import agent_type, base_type, is_mixed


def feature_space(sc: Scenario) -> str:
    """The name of the feature space the scenario's fusion models were trained on: its zoo and the sha256 (12
    hex digits) of the encoder checkpoint that defines it, e.g. "pointpillars_tiny:f487cbd52552"; with random
    weights the seed instead ("pointpillars_tiny:random-seed0")."""
    name = zoo.zoo_name(sc.perception.encoder, sc.perception.preset)
    z = zoo_for(sc)
    if z is None:
        return f"{name}:random-seed{sc.seed}"
    return f"{name}:{(_sha(z.encoder_file) or 'none')[:12]}"


def space_label(sc: Scenario, cav: str) -> str:
    """What CAV `cav`'s feature messages name as their origin (Message.space): "<encoder>@<feature space>" in a
    mixed fleet, "" (nothing on the wire, the bytes of a single-encoder run) otherwise."""
    return f"{agent_type(sc, cav).encoder}@{feature_space(sc)}" if is_mixed(sc) else ""


def build_cav_encoder(sc: Scenario, cav: str) -> nn.Module:
    """The encoder CAV `cav` runs: the base's (build_agent_encoder), or its type's aligned encoder."""
    t = agent_type(sc, cav)
    return build_agent_encoder(sc) if t == base_type(sc) else build_aligned_encoder(sc, t.encoder)


def build_aligned_encoder(sc: Scenario, encoder: str) -> AlignedEncoder:
    """The scenario zoo's `encoder` backward-aligned into its feature space (the `align` stage: models.aligner),
    verified like every checkpoint. ConfigError (one line) when the zoo has none, or when it was aligned to other
    base checkpoints than the zoo's current ones (its manifest record names their sha256): fused with this base
    its features would land off the space the fusion models were trained on."""
    z = zoo_for(sc)
    base = zoo.zoo_name(sc.perception.encoder, sc.perception.preset)
    train = (f"v2vsim train --data CAMERA_DATA --stage align --encoder {encoder} --out "
             f"{zoo.WEIGHTS_DIR if z is None else z.root} --work WORK (docs/training.md)")
    if z is None:
        raise ConfigError(f"{sc.source}: cavs.fleet: {encoder} CAVs need the {base} zoo's aligned {encoder} encoder, "
                          f"and perception.weights is {sc.perception.weights!r} (random weights have no aligned "
                          "encoder); allowed: 'auto' or a zoo folder")
    aligned = z.aligned.get(encoder)
    if aligned is None:
        raise ConfigError(f"{sc.source}: cavs.fleet: the {base} zoo at {z.root} has no {encoder} encoder aligned to "
                          f"it; train one with: {train}")
    path = aligned.checkpoint.path
    state = verified(aligned.checkpoint)
    for file, sha in aligned.checkpoint.trained_on.items():
        have = _sha(z.files.get(file))
        if have != sha:
            raise ConfigError(f"{path}: aligned to {base}/{file} sha256 {sha[:12]}…, but the base zoo at {z.root} has "
                              f"{base}/{file} {'sha256 ' + have[:12] + '…' if have else 'missing'}: a stale pairing; "
                              f"re-align with: {train}")
    _seed(sc, f"aligned:{encoder}")  # every weight is loaded below, as in every process: the same module anyway
    camera = build_encoder(encoder, sc.perception.preset, bev_size_m=sc.bev.size_m,
                           image_backbone=aligned.image_backbone)
    module = build_aligned(camera, get_preset(sc.perception.preset).channels, z.cells, aligned.blocks)
    load_part(module, state, "encoder.", path, f"the aligned {encoder} encoder", f"re-align with: {train}")
    return module.eval()
