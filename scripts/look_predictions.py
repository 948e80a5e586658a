"""Render zoo predictions against ground truth for a few recorded frames (a PNG to look at).

    python scripts/look_predictions.py DATASET SPLIT OUT.png [--methods none,late,early,cobevt] [--samples 3]
        [--weights auto|ZOO_DIR] [--encoder pointpillars|sinbevt|lara]

Rows: samples (ego = first CAV, frames with the most neighbours in range; the neighbours' features through the
zoo's wire compressor, as in a run); columns: the points of
every agent in the ego frame (camera encoders: the ego's front camera), GT (visible vehicles white,
unseen grey, road dark; camera: lane yellow), then per method
- LiDAR: the vehicle probability (colour) with the error outline: TP green, FP red, FN blue;
- camera: the predicted road (dark grey) and lane (yellow) under the same vehicle error colours, titled
  with the frame's vehicle / road / lane IoU.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from models.fusion.early import merge_points_to_ego  # noqa: E402
from models.registry import MODALITY  # noqa: E402
from v2vsim.config import load_scenario  # noqa: E402
from v2vsim.data.torch_dataset import CooperativeDataset  # noqa: E402
from v2vsim.perception.build import build_agent_encoder, build_compressor, build_method_models  # noqa: E402
from v2vsim.perception.fuse import predict  # noqa: E402
from v2vsim.perception.plan import plan_models  # noqa: E402
from v2vsim.training.validate import sample_fusion_inputs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("split")
    ap.add_argument("out")
    ap.add_argument("--methods", default="none,late,early,cobevt")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--weights", default="auto", help="perception.weights: auto (the shipped zoo) or a zoo folder")
    ap.add_argument("--encoder", default="pointpillars", choices=list(MODALITY))
    a = ap.parse_args()
    torch.set_num_threads(2)
    methods = tuple(a.methods.split(","))
    camera = MODALITY[a.encoder] == "camera"
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={a.weights}",
                                                       f"perception.modality={MODALITY[a.encoder]}",
                                                       f"perception.encoder={a.encoder}"])
    plan = plan_models(sc, extra=(*methods, "late"))
    enc = build_agent_encoder(plan)
    models = build_method_models(plan, enc, methods)
    single = build_method_models(plan, enc, ("late",))["late"]  # what each CAV runs for its late outputs
    wire = build_compressor(plan, enc.out_channels)  # the neighbours' maps as the ego receives them (None: raw)
    ds = CooperativeDataset(a.data, a.split, max_agents=5, egos="first", with_points=not camera, with_images=camera)
    counts = [len(ds[i]["agents"]) for i in range(0, len(ds), 5)]
    order = np.argsort(-np.array(counts), kind="stable")[: a.samples] * 5
    fig, axes = plt.subplots(len(order), 2 + len(methods), figsize=(3.2 * (2 + len(methods)), 3.3 * len(order)))
    axes = np.atleast_2d(axes)
    for r, i in enumerate(order):
        s = ds[int(i)]
        inp = sample_fusion_inputs(s, single, wire=wire)
        if camera:
            axes[r, 0].imshow(s["images"][0][0].permute(1, 2, 0).numpy())  # the ego's first (front) camera
        else:
            axes[r, 0].imshow(np.minimum(_points_bev(s), 4), cmap="gray")
        axes[r, 0].set_title(f"{s['key'].run} f{s['key'].frame}: {len(s['agents'])} agents")
        vis, dyn, road, lane = (s[k].numpy() for k in ("vehicle", "dynamic", "road", "lane"))
        if camera:  # the predictions' palette, vehicles white (unseen: grey)
            gt_img = _map_rgb(road, lane)
            gt_img[dyn & ~vis] = 0.6
            gt_img[vis] = 1.0
            axes[r, 1].imshow(gt_img)
        else:
            axes[r, 1].imshow(0.25 * road + 0.5 * (dyn & ~vis) + 1.0 * vis, cmap="gray", vmin=0, vmax=1)
        axes[r, 1].set_title("GT (white: visible)")
        for k, m in enumerate(methods):
            p = predict(m, models[m], inp, 256)
            v = p.probs["vehicle"]
            ax = axes[r, 2 + k]
            if camera:
                ax.imshow(_map_rgb(p.probs["road"] >= 0.5, p.probs["lane"] >= 0.5))
            else:
                ax.imshow(v, cmap="viridis", vmin=0, vmax=1)
            pred = v >= 0.5
            care = ~(dyn & ~vis)
            err = np.zeros((256, 256, 4))
            err[pred & vis] = (0, 1, 0, 0.6)
            err[pred & ~dyn & care] = (1, 0, 0, 0.8)
            err[~pred & vis] = (0.2, 0.4, 1, 0.8)
            ax.imshow(err)
            title = f"{m}: IoU {_iou(pred & care, vis & care):.2f}"
            if camera:
                title += "".join(f" / {_iou(p.probs[c] >= 0.5, gt):.2f}" for c, gt in (("road", road), ("lane", lane)))
            ax.set_title(title)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(a.out, dpi=70)


def _points_bev(s: dict) -> np.ndarray:
    """Point count per ego-grid cell of every agent's cloud above 0.3 m (100 m, 256 cells)."""
    merged = merge_points_to_ego(list(s["points"]), s["rel_poses"]).numpy()
    res = 100 / 256
    rr, cc = ((50 - merged[:, 0]) / res).astype(int), ((50 - merged[:, 1]) / res).astype(int)
    ok = (rr >= 0) & (rr < 256) & (cc >= 0) & (cc < 256) & (merged[:, 2] > 0.3)
    img = np.zeros((256, 256))
    np.add.at(img, (rr[ok], cc[ok]), 1)
    return img


def _map_rgb(road: np.ndarray, lane: np.ndarray) -> np.ndarray:
    """Road dark grey and lane yellow on black: the camera track's static classes."""
    img = np.zeros((*road.shape, 3))
    img[road] = 0.3
    img[lane] = (0.9, 0.8, 0.1)
    return img


def _iou(pred: np.ndarray, gt: np.ndarray) -> float:
    return float((pred & gt).sum() / max((pred | gt).sum(), 1))


if __name__ == "__main__":
    main()
