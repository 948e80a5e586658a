"""One prediction path: validation during training and the ego of a run score the same recorded
frames identically. Path A is `v2vsim.training.validate.evaluate_samples` on the dataset; path B does
what the CAV agents and the ego do: encode, ship through the real codec, rebuild the ego's inputs
from the decoded headers (sender pose -> relative pose), and score with the ego's function."""

from __future__ import annotations

import math

import numpy as np
import torch

from models.build import build_cooperative
from v2vsim.comm.codec import Message, decode, encode
from v2vsim.data.layout import frame_path, unpack_masks
from v2vsim.data.torch_dataset import CooperativeDataset
from v2vsim.evaluation.fuse_and_score import box_iou, fuse_and_score
from v2vsim.evaluation.metrics import ApAccumulator, MethodScore
from v2vsim.perception.build import decompress
from v2vsim.perception.encode import encode_points, late_outputs
from v2vsim.perception.fuse import FusionInputs
from v2vsim.training.validate import evaluate_samples
from v2vsim.world.geometry import Pose, relative_pose

METHODS = ("none", "late", "early", "fcooper", "cobevt")


def _models() -> tuple[dict, torch.nn.Module]:
    torch.manual_seed(3)
    single = build_cooperative("pointpillars", "none", "tiny").eval()
    models = {}
    for m in METHODS:
        torch.manual_seed(10 + len(models))
        mod = build_cooperative("pointpillars", m, "tiny").eval()
        if m != "early":
            mod.encoder = single.encoder
        models[m] = mod
    return models, single


def _ego_path(root, keys, models, single) -> dict:
    stamp = {"run_id": "t", "capture_time": 0.0, "compression": "none"}
    scores = {m: MethodScore(boxes=ApAccumulator()) for m in models}
    for key in keys:
        with np.load(frame_path(root / key.run, key.frame)) as f:
            cavs = [str(c) for c in f["cavs"]]
            poses = {c: Pose(*f["poses"][i]) for i, c in enumerate(cavs)}
            ego = poses[key.ego]
            near = sorted(c for c in cavs if c != key.ego and math.hypot(poses[c].x - ego.x, poses[c].y - ego.y) <= 70)
            senders = [key.ego, *near]
            inp = FusionInputs(senders=senders, rel_poses=np.zeros((len(senders), 3), np.float32))
            for i, c in enumerate(senders):  # CAV side, then the wire, then the ego's _collect
                pts = f[f"points_{c}"].astype(np.float32)
                feats = encode_points(single.encoder, pts)
                maps, boxes = late_outputs(single, feats)
                st = {**stamp, "sender_id": c, "frame": key.frame, "sender_pose": poses[c].as_tuple()}
                wire = {k: decode(encode(msg)) for k, msg in {
                    "features": Message(kind="features", payload=feats, **st),
                    "points": Message(kind="points", payload=pts, **st),
                    "outputs": Message(kind="outputs", payload=maps, extras={"boxes": boxes}, **st)}.items()}
                inp.rel_poses[i] = relative_pose(ego, Pose(*wire["features"].sender_pose))
                inp.features[c] = decompress(None, wire["features"].payload)
                inp.points[c] = wire["points"].payload.astype(np.float32)
                inp.outputs[c] = (wire["outputs"].payload.astype(np.float32),
                                  wire["outputs"].extras["boxes"].astype(np.float32))
            masks = unpack_masks(f[f"gt_{key.ego}"], 256)
            gt = {k: masks[k] for k in ("dynamic", "visible", "road", "lane")}
            boxes_gt = f[f"boxes_{key.ego}"][f[f"boxvis_{key.ego}"]]
        fuse_and_score(models, inp, 256, gt, boxes_gt, scores)
    return {m: s.to_json(box_iou) for m, s in scores.items()}


def test_validation_and_ego_give_identical_metrics(tiny_dataset) -> None:
    models, single = _models()
    ds = CooperativeDataset(tiny_dataset, "train", max_agents=16)
    idx = list(range(len(ds)))
    assert any(len(ds[i]["agents"]) > 1 for i in idx), "the recorded frames should hold neighbours in range"
    a = evaluate_samples(models, single, ds, idx)
    b = _ego_path(tiny_dataset, [ds.items[i] for i in idx], models, single)
    for m in METHODS:
        for k in ("iou_vehicle", "iou_vehicle_all", "iou_road", "iou_lane", "ap50", "ap70", "frames"):
            assert a[m][k] == b[m][k], (m, k, a[m][k], b[m][k])
    assert a["none"]["frames"] == len(idx)
