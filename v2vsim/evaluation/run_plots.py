"""A run's PNG plots: IoU by method, vehicle IoU per frame, and (tr37885) delivery by distance and link state."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from v2vsim.comm.tr37885 import expected_delivery
from v2vsim.config import ChannelConfig
from v2vsim.evaluation.metrics import MethodScore


def distance_bins(comm: dict) -> list[str]:
    """The distance bins of comm.delivery_by_distance ("0-10", ...), nearest first."""
    bins = {b for per in (comm.get("delivery_by_distance") or {}).values() for b in per}
    return sorted(bins, key=lambda b: float(b.split("-")[0]))


def plot(out: Path, doc: dict, scores: dict[str, MethodScore], channel: ChannelConfig | None = None) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    methods = list(doc["methods"])
    keys = [("iou_vehicle", "vehicle (visible)"), ("iou_road", "road"), ("iou_lane", "lane")]
    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(methods) + 2), 4))
    w = 0.8 / len(keys)
    for j, (k, label) in enumerate(keys):
        vals = [doc["methods"][m][k] or 0.0 for m in methods]
        ax.bar(np.arange(len(methods)) + (j - 1) * w, vals, w, label=label)
    ax.set_xticks(np.arange(len(methods)), methods)
    ax.set_ylabel("IoU")
    ax.set_ylim(0, 1.15)  # room above the bars for the legend
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.set_title(f"{doc['scenario']}: IoU by method ({doc['frames']} frames)")
    ax.legend(ncol=3, loc="upper center", fontsize=9)
    fig.tight_layout()
    paths.append(out / "iou_by_method.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 4))
    for m in methods:
        ax.plot(scores[m].vehicle.per_frame, label=m, lw=1)
    ax.set_xlabel("frame (with vehicle cells)")
    ax.set_ylabel("IoU vehicle (visible)")
    ax.set_ylim(0, 1)
    ax.legend(ncol=4, fontsize=8)
    fig.tight_layout()
    paths.append(out / "iou_per_frame.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    if doc["comm"].get("delivery_by_distance") is not None:
        paths.append(plot_delivery_by_distance(out / "delivery_by_distance.png", doc, channel))
    return paths


def plot_delivery_by_distance(path: Path, doc: dict, channel: ChannelConfig | None) -> Path:
    """Delivery ratio per distance bin and link state (tr37885), with the expected LOS / NLOS curves."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = distance_bins(doc["comm"])
    fig, ax = plt.subplots(figsize=(7, 4))
    for state, per in doc["comm"]["delivery_by_distance"].items():
        xs = [sum(map(float, b.split("-"))) / 2 for b in bins if b in per]
        line, = ax.plot(xs, [per[b]["ratio"] for b in bins if b in per], "o-", label=f"{state.upper()} (measured)")
        if channel is not None and state != "nlosv" and bins:
            ds = np.linspace(1.0, float(bins[-1].split("-")[1]), 120)
            ax.plot(ds, [expected_delivery(channel, state, d) for d in ds], "--", color=line.get_color(), lw=1,
                    label=f"{state.upper()} (TR 37.885, expected)")
    ax.set_xlabel("sender-receiver distance (m, bin centre)")
    ax.set_ylabel("delivery ratio")
    ax.set_ylim(0, 1.05)
    ax.set_title(f"{doc['scenario']}: delivery by distance and link state (tr37885)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
