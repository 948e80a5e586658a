"""Render zoo predictions against ground truth for a few recorded frames (a PNG to look at).

    python scripts/look_predictions.py DATASET SPLIT OUT.png [--methods none,late,early,cobevt] [--samples 3]
        [--weights auto|ZOO_DIR]

Rows: samples (ego = first CAV, frames with the most neighbours in range); columns: the points of
every agent in the ego frame, GT (visible vehicles white, unseen grey, road dark), then per method
the vehicle probability (colour) with the error outline: TP green, FP red, FN blue.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from models.fusion.early import merge_points_to_ego  # noqa: E402
from v2vsim.config import load_scenario  # noqa: E402
from v2vsim.data.torch_dataset import CooperativeDataset  # noqa: E402
from v2vsim.perception import build_agent_encoder, build_method_models, predict  # noqa: E402
from v2vsim.training.train import sample_fusion_inputs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("data")
    ap.add_argument("split")
    ap.add_argument("out")
    ap.add_argument("--methods", default="none,late,early,cobevt")
    ap.add_argument("--samples", type=int, default=3)
    ap.add_argument("--weights", default="auto", help="perception.weights: auto (the shipped zoo) or a zoo folder")
    a = ap.parse_args()
    torch.set_num_threads(2)
    methods = tuple(a.methods.split(","))
    sc = load_scenario("scenarios/intersection.yaml", [f"perception.weights={a.weights}"])
    enc = build_agent_encoder(sc)
    models = build_method_models(sc, enc, methods)
    single = build_method_models(sc, enc, ("late",))["late"]  # what each CAV runs for its late outputs
    ds = CooperativeDataset(a.data, a.split, max_agents=5, egos="first")
    counts = [len(ds[i]["agents"]) for i in range(0, len(ds), 5)]
    order = np.argsort(-np.array(counts), kind="stable")[: a.samples] * 5
    fig, axes = plt.subplots(len(order), 2 + len(methods), figsize=(3.2 * (2 + len(methods)), 3.3 * len(order)))
    axes = np.atleast_2d(axes)
    for r, i in enumerate(order):
        s = ds[int(i)]
        inp = sample_fusion_inputs(s, single)
        merged = merge_points_to_ego(list(s["points"]), s["rel_poses"]).numpy()
        res = 100 / 256
        rr, cc = ((50 - merged[:, 0]) / res).astype(int), ((50 - merged[:, 1]) / res).astype(int)
        ok = (rr >= 0) & (rr < 256) & (cc >= 0) & (cc < 256) & (merged[:, 2] > 0.3)
        img = np.zeros((256, 256))
        np.add.at(img, (rr[ok], cc[ok]), 1)
        axes[r, 0].imshow(np.minimum(img, 4), cmap="gray")
        axes[r, 0].set_title(f"{s['key'].run} f{s['key'].frame}: {len(s['agents'])} agents")
        vis, dyn, road = s["vehicle"].numpy(), s["dynamic"].numpy(), s["road"].numpy()
        gt_img = 0.25 * road + 0.5 * (dyn & ~vis) + 1.0 * vis
        axes[r, 1].imshow(gt_img, cmap="gray", vmin=0, vmax=1)
        axes[r, 1].set_title("GT (white: visible)")
        for k, m in enumerate(methods):
            p = predict(m, models[m], inp, 256)
            v = p.probs["vehicle"]
            ax = axes[r, 2 + k]
            ax.imshow(v, cmap="viridis", vmin=0, vmax=1)
            pred = v >= 0.5
            care = ~(dyn & ~vis)
            err = np.zeros((256, 256, 4))
            err[pred & vis] = (0, 1, 0, 0.6)
            err[pred & ~dyn & care] = (1, 0, 0, 0.8)
            err[~pred & vis] = (0.2, 0.4, 1, 0.8)
            ax.imshow(err)
            inter, union = (pred & vis & care).sum(), ((pred | vis) & care).sum()
            ax.set_title(f"{m}: IoU {inter / max(union, 1):.2f}")
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(a.out, dpi=70)


if __name__ == "__main__":
    main()
