"""The ego side of perception: what reached the ego for one frame, fused and decoded with one method
(warp with each sender's capture pose, fuse, heads) into BEV probabilities and boxes on the ego grid. The models
run on the device their weights sit on (v2vsim.perception.device); late fusion merges decoded outputs on the
host; a Prediction is numpy on the host."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor, nn

from models.fusion.early import merge_points_to_ego
from models.fusion.late import late_fuse_boxes, late_fuse_probabilities
from models.heads import decode_detections, resize_logits, segmentation_probabilities
from models.registry import is_intermediate
from v2vsim.perception.device import model_device, to_host
from v2vsim.perception.encode import heads_float
from v2vsim.perception.precision import Precision, autocast


@dataclass
class FusionInputs:
    """What reached the ego for one frame, per sender (ego first), all in the sender's own frame."""

    senders: list[str]
    rel_poses: np.ndarray  # [L, 3] (dx, dy, dyaw) of each sender's capture pose in the ego's body frame
    # The same per message kind ("features", "points", "outputs"), where a sender's messages of different kinds
    # come from different frames (a late kind is older): each method warps with the poses of the kind it fuses.
    poses_by_kind: dict[str, np.ndarray] = field(default_factory=dict)
    features: dict[str, np.ndarray] = field(default_factory=dict)  # sender -> [C, F, F]
    # The ego's own map as its encoder made it (float16 [C, F, F]) when the wire compresses feature messages: the
    # ego never radios its map to itself, so it fuses this instead of its own compressed message.
    own: np.ndarray | None = None
    points: dict[str, np.ndarray] = field(default_factory=dict)  # sender -> [P, 4] body frame
    outputs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # sender -> (maps, boxes)
    # defence.evidence: what each LiDAR sender's rays established, sender -> [F, F] uint8 UNKNOWN / FREE / OCCUPIED
    # in its own frame (v2vsim.perception.evidence), from its feature message, else its outputs message
    evidence: dict[str, np.ndarray] = field(default_factory=dict)
    # Learned latency compensation (comm.compensation, v2vsim.perception.extrapolate): per neighbour whose
    # features are late, the age (s) of its message at the fused frame's instant and its message before
    # (features, that capture's (dx, dy, dyaw) in the newer capture's frame, seconds between the two) ...
    feature_ages: dict[str, float] = field(default_factory=dict)
    previous_features: dict[str, tuple[np.ndarray, np.ndarray, float]] = field(default_factory=dict)
    # ... and, per method with a trained extrapolation, its features extrapolated to that instant, which that
    # method fuses instead: method -> sender -> [C, F, F]
    extrapolated: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


@dataclass(frozen=True)
class Prediction:
    probs: dict[str, np.ndarray]  # vehicle / road / lane [cells, cells] in the ego grid
    boxes: np.ndarray | None  # [K, 6] (x, y, l, w, yaw, score) in the ego frame (LiDAR)
    ms: float  # wall time of fusion + decoding
    decode_ms: float = 0.0  # of which the decoder + heads (BEV maps and boxes from the fused features)


def _poses(inp: FusionInputs, names: list[str], kind: str) -> Tensor:
    idx = [inp.senders.index(s) for s in names]
    return torch.from_numpy(inp.poses_by_kind.get(kind, inp.rel_poses)[idx]).float()


def fused_inputs(method: str, inp: FusionInputs) -> tuple[dict, str]:
    """What `method` fuses: sender -> its payload (late: (maps, boxes); early: points; intermediate: features, or
    their extrapolation for this method; none: the ego's own features only), and the message kind whose poses warp
    them ("" for none: nothing is warped). predict() and fusion_key() both read through this."""
    ego = inp.senders[0]
    if method == "late":
        return inp.outputs, "outputs"
    if method == "early":
        return inp.points, "points"
    if method == "none" or not is_intermediate(method):
        return ({ego: inp.features[ego]} if ego in inp.features else {}), ""
    return {**inp.features, **inp.extrapolated.get(method, {})}, "features"


def fusion_key(method: str, inp: FusionInputs, digests: dict[int, bytes] | None = None) -> bytes:
    """A digest of exactly what predict(method, ...) reads of `inp` (the same selection, in the same order):
    two FusionInputs with the same key give that method the same prediction from the same model. Replays of one
    recording in one process share predictions by it (agents.ego_replay.ReplayShare). `digests`: each array's
    own digest by id(), kept by the caller across the methods of one frame (the arrays must stay alive)."""
    h = hashlib.sha1(method.encode())
    ego = inp.senders[0]
    known = {} if digests is None else digests

    def add(name: str, *arrays: np.ndarray, held: bool = True) -> None:
        """`held`: arrays `inp` holds (their id() stays theirs while it lives), not temporaries."""
        h.update(name.encode())
        for a in arrays:
            d = known.get(id(a)) if held else None
            if d is None:
                c = np.ascontiguousarray(a)
                one = hashlib.sha1(f"{c.dtype}{c.shape}".encode())
                one.update(c.data)
                d = one.digest()
                if held:
                    known[id(a)] = d
            h.update(d)

    def poses(names: list[str], kind: str) -> np.ndarray:
        return inp.poses_by_kind.get(kind, inp.rel_poses)[[inp.senders.index(s) for s in names]]

    table, kind = fused_inputs(method, inp)
    if ego not in table:
        return h.digest() + b"-"  # no input: predict returns None
    names = [s for s in inp.senders if s in table]
    for s in names:
        v = table[s]
        add(s, *(v if isinstance(v, tuple) else (v,)))
    if kind:
        add("poses", poses(names, kind), held=False)
    return h.digest()


@torch.no_grad()
def predict(method: str, model: nn.Module, inp: FusionInputs, cells: int,
            precision: Precision = "fp32") -> Prediction | None:
    """Fuse and decode what reached the ego with one method; None when the method has no input
    (e.g. the ego's own message is missing). `precision`: the models' forward passes (v2vsim.perception.precision)."""
    ego = inp.senders[0]
    t0 = time.perf_counter()
    table, kind = fused_inputs(method, inp)
    if ego not in table:
        return None
    names = [s for s in inp.senders if s in table]
    if method == "late":
        maps = torch.from_numpy(np.stack([table[s][0] for s in names]))  # [L, 3, S, S]
        poses = _poses(inp, names, kind)
        valid = torch.ones(len(names), dtype=torch.bool)
        merged = late_fuse_probabilities(maps, poses, valid, model.bev_size_m)  # [3, S, S]
        merged = resize_logits(merged[None], cells)[0]
        probs = {k: merged[i].numpy() for i, k in enumerate(("vehicle", "road", "lane"))}
        boxes = None
        if model.heads.detection is not None:
            per = [torch.from_numpy(table[s][1]) for s in names]
            boxes = late_fuse_boxes(per, poses, valid, extent_m=model.bev_size_m).numpy()
        return Prediction(probs, boxes, (time.perf_counter() - t0) * 1000)
    device = model_device(model)
    if method == "early":  # the clouds are merged on the host, the merged one encoded on the device
        clouds = [torch.from_numpy(table[s]) for s in names]
        merged = merge_points_to_ego(clouds, _poses(inp, names, kind)).to(device)
        with autocast(precision, device.type):
            fused = model.encoder([merged])
    elif not kind:  # none: the ego's own map
        fused = torch.from_numpy(table[ego])[None].to(device)
    else:
        feats = torch.from_numpy(np.stack([table[s] for s in names])).to(device)  # [L, C, F, F]
        valid = torch.ones(1, len(names), dtype=torch.bool, device=device)
        with autocast(precision, device.type):
            fused = model.fuse(feats[None], _poses(inp, names, kind)[None].to(device), valid)
    t_fused = time.perf_counter()
    out = heads_float(model, fused, precision)
    dyn, stat = resize_logits(out["dynamic"], cells), resize_logits(out["static"], cells)
    probs = {k: to_host(v[0]) for k, v in segmentation_probabilities(dyn, stat).items()}
    boxes = None
    if "det_cls" in out:
        boxes = to_host(decode_detections(out["det_cls"], out["det_reg"], model.anchors)[0])
    t_end = time.perf_counter()
    return Prediction(probs, boxes, (t_end - t0) * 1000, (t_end - t_fused) * 1000)
