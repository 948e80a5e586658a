"""Models as the running simulator uses them: the CAV side (encode, late outputs) and the ego side
(warp + fuse + decode with every method), built by name from the scenario's `perception` section.

Weights: `perception.weights: auto` loads the zoo's checkpoints (models.zoo: models/weights/
<encoder>_<preset>/, verified against manifest.json); where none ship, every process builds the same
randomly initialised models from the scenario seed (so CAV encoders and the ego agree), and the
report says the weights are untrained.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from models import zoo
from models.compression import ChannelCompressor
from models.fusion.early import merge_points_to_ego
from models.fusion.late import late_fuse_boxes, late_fuse_probabilities
from models.heads import decode_detections, resize_logits, segmentation_probabilities
from models.presets import get_preset
from models.registry import build_cooperative, build_encoder, is_intermediate
from v2vsim.config import ConfigError, Scenario
from v2vsim.sensing import SensorFrame


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
        if not root.is_absolute():
            root = Path(sc.source).parent / root
        if not (root / "manifest.json").is_file():
            raise ConfigError(f"{sc.source}: perception.weights: no zoo manifest at {root / 'manifest.json'}; "
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


def method_checkpoints(sc: Scenario, methods: tuple[str, ...]) -> dict[str, str | None]:
    """Checkpoint file each method loads (relative to the zoo root), None where weights are random."""
    z = zoo_for(sc)
    out: dict[str, str | None] = {}
    for m in methods:
        f = None if z is None else zoo.method_file(z[1], m, z[0], sc.perception.encoder, sc.perception.preset)
        out[m] = None if f is None else str(f.relative_to(z[0]))
    return out


def _states(sc: Scenario, methods: tuple[str, ...]) -> dict[str, dict | None]:
    """Verified state_dict of each method's checkpoint ("encoder": the CAVs' encoder; None: random
    weights), every file read and hashed once; ConfigError naming the file when one is broken."""
    z = zoo_for(sc)
    if z is None:
        return dict.fromkeys(methods)
    files = {m: zoo.method_file(z[1], m, z[0], sc.perception.encoder, sc.perception.preset) for m in methods}
    loaded: dict[Path, dict] = {}
    try:
        for f in {f for f in files.values() if f is not None}:
            loaded[f] = zoo.load_checkpoint(f, z[1])
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
        root, entry = zoo_for(sc)  # type: ignore[misc]  # a state was loaded, so there is a zoo
        path = zoo.method_file(entry, method, root, sc.perception.encoder, sc.perception.preset)
        reason = " ".join(str(e).split())
        raise ConfigError(f"{path}: the {method} checkpoint's {prefix.rstrip('.')} weights do not fit this "
                          f"version of the model ({reason[:300]}); rebuild it with: "
                          f"{zoo.rebuild_command(path, entry)}") from None


def build_agent_encoder(sc: Scenario) -> nn.Module:
    """The encoder every CAV runs; identical in every process for a given scenario."""
    _seed(sc, "encoder")
    enc = build_encoder(sc.perception.encoder, sc.perception.preset, bev_size_m=sc.bev.size_m)
    _load(enc, _states(sc, ("encoder",))["encoder"], "encoder.", sc, "encoder")
    return enc.eval()


def runnable_methods(sc: Scenario) -> tuple[str, ...]:
    """perception.methods less what the modality cannot run (early fusion ships LiDAR points)."""
    return tuple(m for m in sc.perception.methods if sc.perception.modality == "lidar" or m != "early")


def check_scenario(sc: Scenario) -> None:
    """Model-dependent checks the schema cannot make; ConfigError before any process starts."""
    channels = get_preset(sc.perception.preset).channels
    ratio = sc.comm.channel_compression
    if channels % ratio:
        raise ConfigError(f"{sc.source}: comm.channel_compression: {ratio} does not divide the {channels} feature "
                          f"channels of preset {sc.perception.preset!r}; allowed: a divisor of {channels}")
    if not runnable_methods(sc):
        raise ConfigError(f"{sc.source}: perception.methods: nothing to run for modality "
                          f"{sc.perception.modality!r} (early fusion needs LiDAR)")
    # every checkpoint a process loads is verified (sha256, and that it fits its model) before any starts;
    # building the models reads each file once (~0.3 s for the tiny zoo)
    if zoo_for(sc) is not None:
        build_method_models(sc, build_agent_encoder(sc), runnable_methods(sc))


def build_compressor(sc: Scenario, channels: int) -> ChannelCompressor | None:
    """The learned channel compression pair of comm.channel_compression (None when it is 1)."""
    ratio = sc.comm.channel_compression
    if ratio == 1:
        return None
    _seed(sc, "compressor")
    comp = ChannelCompressor(channels, ratio)  # not in the zoo yet: seeded random in every process
    return comp.eval()


@torch.no_grad()
def compress(comp: ChannelCompressor | None, features: np.ndarray) -> np.ndarray:
    """Sender side: [C, F, F] -> [C/r, F, F] (unchanged without compression)."""
    return features if comp is None else comp.compress(torch.from_numpy(features)[None])[0].numpy()


@torch.no_grad()
def decompress(comp: ChannelCompressor | None, payload: np.ndarray) -> np.ndarray:
    """Receiver side: [C/r, F, F] -> [C, F, F] float32."""
    x = payload.astype(np.float32)
    return x if comp is None else comp.decompress(torch.from_numpy(x)[None])[0].numpy()


def build_method_models(sc: Scenario, encoder: nn.Module, methods: tuple[str, ...]) -> dict[str, nn.Module]:
    """One CooperativePerception per method, all sharing `encoder` (every method fuses the same messages)."""
    states = _states(sc, methods)
    out = {}
    for m in methods:
        _seed(sc, f"method:{m}")
        model = build_cooperative(sc.perception.encoder, m, sc.perception.preset, bev_size_m=sc.bev.size_m)
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


def encoder_inputs(sf: SensorFrame, sc: Scenario) -> list[Tensor] | tuple[Tensor, Tensor, Tensor]:
    """A SensorFrame as the encoder takes it: body-frame points, or (images, intrinsics, extrinsics)."""
    if sc.perception.modality == "lidar":
        return [torch.from_numpy(body_frame_points(sf, sc))]
    cams = sf.cameras
    images = torch.from_numpy(cams.images).permute(0, 3, 1, 2).float().div(255.0)[None]  # [1, M, 3, h, w]
    intr = torch.from_numpy(cams.rig.intrinsics).float()[None]
    extr = torch.from_numpy(cams.rig.extrinsics).float()[None]
    return images, intr, extr


def body_frame_points(sf: SensorFrame, sc: Scenario) -> np.ndarray:
    """LiDAR-frame points (origin at the sensor) moved to the body frame (origin on the ground)."""
    pts = sf.lidar.points.copy()
    pts[:, 2] += sc.sensors.lidar.height_m
    return pts


@torch.no_grad()
def encode(encoder: nn.Module, sf: SensorFrame, sc: Scenario) -> np.ndarray:
    """[C, F, F] float32 BEV features of one CAV in its own frame."""
    if sc.perception.modality == "lidar":
        return encode_points(encoder, body_frame_points(sf, sc))
    return encoder(*encoder_inputs(sf, sc))[0].float().numpy()


@torch.no_grad()
def encode_points(encoder: nn.Module, points: np.ndarray) -> np.ndarray:
    """A LiDAR encoder on one body-frame cloud [P, 4] -> [C, F, F] float32 features."""
    return encoder([torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))])[0].float().numpy()


@torch.no_grad()
def late_outputs(model: nn.Module, features: np.ndarray, boxes: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A CAV's own decoded outputs for late fusion: probabilities [3, S, S] (vehicle, road, lane) and
    boxes [K, 6] (x, y, l, w, yaw, score) in its body frame (none decoded with `boxes=False`: [0, 6])."""
    out = model.heads(torch.from_numpy(np.ascontiguousarray(features, dtype=np.float32))[None])
    probs = segmentation_probabilities(out["dynamic"], out["static"])
    maps = np.stack([probs[k][0].numpy() for k in ("vehicle", "road", "lane")])
    found = np.zeros((0, 6), np.float32)
    if boxes and "det_cls" in out:
        found = decode_detections(out["det_cls"], out["det_reg"], model.anchors)[0].numpy()
    return maps.astype(np.float32), found.astype(np.float32)


def pooled_confidence(p_vehicle: np.ndarray, cells: int) -> np.ndarray:
    """A vehicle probability map [S, S] max-pooled to the feature grid [cells, cells]: what a CAV ranks its
    feature cells by under comm.share topk (Where2comm's spatial confidence map, Eq. 2)."""
    return torch.nn.functional.adaptive_max_pool2d(torch.from_numpy(p_vehicle)[None, None], cells)[0, 0].numpy()


def vehicle_confidence(model: nn.Module, features: np.ndarray) -> np.ndarray:
    """The single-agent heads' vehicle probability on features [C, F, F], pooled to [F, F] (pooled_confidence)."""
    maps, _ = late_outputs(model, features, boxes=False)
    return pooled_confidence(maps[0], features.shape[-1])


@dataclass
class FusionInputs:
    """What reached the ego for one frame, per sender (ego first), all in the sender's own frame."""

    senders: list[str]
    rel_poses: np.ndarray  # [L, 3] (dx, dy, dyaw) of each sender's capture pose in the ego's body frame
    features: dict[str, np.ndarray] = field(default_factory=dict)  # sender -> [C, F, F]
    points: dict[str, np.ndarray] = field(default_factory=dict)  # sender -> [P, 4] body frame
    outputs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # sender -> (maps, boxes)


@dataclass(frozen=True)
class Prediction:
    probs: dict[str, np.ndarray]  # vehicle / road / lane [cells, cells] in the ego grid
    boxes: np.ndarray | None  # [K, 6] (x, y, l, w, yaw, score) in the ego frame (LiDAR)
    ms: float  # wall time of fusion + decoding
    decode_ms: float = 0.0  # of which the decoder + heads (BEV maps and boxes from the fused features)


def _stack(inp: FusionInputs, table: dict[str, np.ndarray]) -> tuple[list[str], Tensor]:
    names = [s for s in inp.senders if s in table]
    return names, torch.from_numpy(np.stack([table[s] for s in names]))


def _poses(inp: FusionInputs, names: list[str]) -> Tensor:
    idx = [inp.senders.index(s) for s in names]
    return torch.from_numpy(inp.rel_poses[idx]).float()


@torch.no_grad()
def predict(method: str, model: nn.Module, inp: FusionInputs, cells: int) -> Prediction | None:
    """Fuse and decode what reached the ego with one method; None when the method has no input
    (e.g. the ego's own message is missing)."""
    ego = inp.senders[0]
    t0 = time.perf_counter()
    if method == "late":
        if ego not in inp.outputs:
            return None
        names = [s for s in inp.senders if s in inp.outputs]
        maps = torch.from_numpy(np.stack([inp.outputs[s][0] for s in names]))  # [L, 3, S, S]
        poses = _poses(inp, names)
        valid = torch.ones(len(names), dtype=torch.bool)
        merged = late_fuse_probabilities(maps, poses, valid, model.bev_size_m)  # [3, S, S]
        merged = resize_logits(merged[None], cells)[0]
        probs = {k: merged[i].numpy() for i, k in enumerate(("vehicle", "road", "lane"))}
        boxes = None
        if model.heads.detection is not None:
            per = [torch.from_numpy(inp.outputs[s][1]) for s in names]
            boxes = late_fuse_boxes(per, poses, valid, extent_m=model.bev_size_m).numpy()
        return Prediction(probs, boxes, (time.perf_counter() - t0) * 1000)
    if method == "early":
        if ego not in inp.points:
            return None
        names = [s for s in inp.senders if s in inp.points]
        clouds = [torch.from_numpy(inp.points[s]) for s in names]
        merged = merge_points_to_ego(clouds, _poses(inp, names))
        fused = model.encoder([merged])
    else:
        if ego not in inp.features:
            return None
        if method == "none" or not is_intermediate(method):
            fused = torch.from_numpy(inp.features[ego])[None]
        else:
            names, feats = _stack(inp, inp.features)  # [L, C, F, F]
            valid = torch.ones(1, len(names), dtype=torch.bool)
            fused = model.fuse(feats[None], _poses(inp, names)[None], valid)
    t_fused = time.perf_counter()
    out = model.heads(fused)
    dyn, stat = resize_logits(out["dynamic"], cells), resize_logits(out["static"], cells)
    probs = {k: v[0].numpy() for k, v in segmentation_probabilities(dyn, stat).items()}
    boxes = None
    if "det_cls" in out:
        boxes = decode_detections(out["det_cls"], out["det_reg"], model.anchors)[0].numpy()
    t_end = time.perf_counter()
    return Prediction(probs, boxes, (t_end - t0) * 1000, (t_end - t_fused) * 1000)
