"""Validation of a stage's models on dataset samples through the one prediction path: each sample as the
ego's FusionInputs off the wire, scored by v2vsim.evaluation.fuse_and_score."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from models.compression import ChannelCompressor
from v2vsim.data.torch_dataset import CooperativeDataset, collate
from v2vsim.evaluation.fuse_and_score import box_iou, fuse_and_score
from v2vsim.evaluation.metrics import ApAccumulator, MethodScore
from v2vsim.perception.encode import encode_points, late_outputs
from v2vsim.perception.fuse import FusionInputs
from v2vsim.training.cache import FeatureCache
from v2vsim.training.extrapolate import extrapolate_batch
from v2vsim.training.stages import COMPRESS, EXTRAPOLATE, StageSpec


def validate(spec: StageSpec, model: nn.Module, single: nn.Module, ds: CooperativeDataset,
             cache: FeatureCache | None, n: int, wire: ChannelCompressor | None = None) -> dict[str, dict]:
    """Metrics of the stage's methods on `n` validation samples (spread over the split), on the CPU: the
    run's own prediction path (numpy in, numpy out), features through the `wire` compressor (the `compress`
    stage: its own, scoring `none` on the ego's compressed map). The models are moved back to their device."""
    dev = next(model.parameters()).device
    model.cpu().eval()
    single.cpu().eval()
    models = {m: model for m in spec.methods} if spec.methods else {"none": model, "late": model}
    if spec.name == COMPRESS:  # `none` on the ego's own map sent through this ratio's compressor: what it costs
        models, wire = {"none": model}, model.compressor
    wire = None if wire is None else wire.cpu().eval()
    idx = np.linspace(0, len(ds) - 1, min(n, len(ds))).round().astype(int)
    try:
        if spec.name == EXTRAPOLATE:
            return evaluate_extrapolation(model, spec.methods[0], ds, [int(i) for i in idx], cache, wire)
        return evaluate_samples(models, single, ds, [int(i) for i in idx], cache, wire,
                                own_compressed=spec.name == COMPRESS)
    finally:
        model.to(dev)


@torch.no_grad()
def sample_fusion_inputs(s: dict, single: nn.Module, cache: FeatureCache | None = None, late: bool = True,
                         wire: ChannelCompressor | None = None, own_compressed: bool = False) -> FusionInputs:
    """A dataset sample as the ego's FusionInputs, as they arrive off the wire: features float16 (from
    `single`'s encoder, or the cache; the neighbours' through the `wire` compressor where the zoo has one, the
    ego's own too only with `own_compressed`: the `compress` stage's scoring), late outputs
    computed by each CAV from its float32 features with `single`'s heads and shipped as float16 maps +
    float32 boxes, points float32."""
    inp = FusionInputs(senders=list(s["agents"]), rel_poses=s["rel_poses"].numpy())
    for j, (c, k) in enumerate(zip(s["agents"], s["agent_frames"], strict=True)):
        if cache is not None:
            feats = cache.get(s["key"].run, k, c).astype(np.float32)
        elif s["images"]:  # [M, 3, h, w] uint8 -> the encoder's [1, M, 3, h, w] in [0, 1]
            feats = single.encoder(s["images"][j][None].float().div(255.0), s["intrinsics"][j][None],
                                   s["extrinsics"][j][None])[0].float().numpy()
        else:
            feats = encode_points(single.encoder, s["points"][j].numpy())
        if wire is None or (j == 0 and not own_compressed):  # slot 0: the ego's own map, never on the air
            inp.features[c] = feats.astype(np.float16).astype(np.float32)
        else:
            inp.features[c] = wire.over_the_wire(torch.from_numpy(feats.astype(np.float32))).numpy()
        if s["points"]:
            inp.points[c] = s["points"][j].numpy()
        if late:
            maps, boxes = late_outputs(single, feats)
            inp.outputs[c] = (maps.astype(np.float16).astype(np.float32), boxes)
    return inp


@torch.no_grad()
def evaluate_samples(models: dict[str, nn.Module], single: nn.Module, ds: CooperativeDataset, idx: list[int],
                     cache: FeatureCache | None = None, wire: ChannelCompressor | None = None,
                     own_compressed: bool = False) -> dict[str, dict]:
    """metrics.json-style scores of `models` on dataset samples, through the ego's own scoring
    (v2vsim.evaluation.fuse_and_score.fuse_and_score) on `sample_fusion_inputs`."""
    scores = {m: MethodScore(boxes=ApAccumulator()) for m in models}
    for i in idx:
        s = ds[i]
        inp = sample_fusion_inputs(s, single, cache, late="late" in models, wire=wire, own_compressed=own_compressed)
        gt = {"dynamic": s["dynamic"].numpy(), "visible": s["vehicle"].numpy(), "road": s["road"].numpy(),
              "lane": s["lane"].numpy()}
        fuse_and_score(models, inp, gt["road"].shape[0], gt, s["boxes"].numpy(), scores)
    return {m: sc.to_json(box_iou) for m, sc in scores.items()}


@torch.no_grad()
def evaluate_extrapolation(model: nn.Module, method: str, ds: CooperativeDataset, idx: list[int],
                           cache: FeatureCache, wire: ChannelCompressor | None = None) -> dict[str, dict]:
    """Scores of `method` (a model with an `.extrapolation` module) on with_previous samples of late
    neighbours, as they arrive ("<method>") and with every late message extrapolated first
    ("<method>_extrapolated"); both through the ego's own scoring on the same samples."""
    plain, extra = f"{method}", f"{method}_extrapolated"
    scores = {m: MethodScore(boxes=ApAccumulator()) for m in (plain, extra)}
    for i in idx:
        s = ds[i]
        inp = sample_fusion_inputs(s, model, cache, late=False, wire=wire)
        gt = {"dynamic": s["dynamic"].numpy(), "visible": s["vehicle"].numpy(), "road": s["road"].numpy(),
              "lane": s["lane"].numpy()}
        cells, boxes = gt["road"].shape[0], s["boxes"].numpy()
        fuse_and_score({method: model}, inp, cells, gt, boxes, {method: scores[plain]})
        feats = torch.from_numpy(np.stack([inp.features[c] for c in s["agents"]]))[None]  # [1, L, C, F, F]
        moved = extrapolate_batch(model.extrapolation, feats, collate([s]), cache, model.bev_size_m, wire)[0]
        compensated = FusionInputs(senders=inp.senders, rel_poses=inp.rel_poses,
                                   features={c: moved[j].numpy() for j, c in enumerate(s["agents"])})
        fuse_and_score({method: model}, compensated, cells, gt, boxes, {method: scores[extra]})
    return {m: sc.to_json(box_iou) for m, sc in scores.items()}
