"""The wire-compression study's table (docs/results.md): per channel compression ratio, each method's visible-vehicle
IoU and AP@0.5 (mean over seeds) and the bytes of one feature message, from a sweep over comm.channel_compression
(scripts/compression_study.sh), beside the figures the field publishes (a different dataset: OPV2V). The cost of a
ratio is CoBEVT's IoU there minus its IoU uncompressed (ratio 1), paired by seed, with the sweep's 95 % interval
(v2vsim.study.stats: a bootstrap over seeds, expanded for their number); its gain over `none` likewise. With
--plot PNG, CoBEVT's IoU relative to uncompressed against the ratio, beside the field's relative figures.

    python scripts/compression_table.py SWEEP_DIR [SWEEP_DIR ...] [--plot PNG]
"""

from __future__ import annotations

import json
import re
import sys
from collections import defaultdict
from pathlib import Path

from v2vsim.study.stats import interval

# OpenCOOD's OPV2V LiDAR table (README, "AP@0.7 for no-compression/compression", PointPillar backbone, its learned
# compressor at about 64x: 72.08 -> 1.12 Mbit a message); the CoBEVT paper's Table 4 (camera track, vehicle IoU)
# as quoted by a secondary source, not checked against the paper.
FIELD = {
    "OpenCOOD LiDAR, AP@0.7 none -> ~64x (72.08 -> 1.12 Mbit)": {
        "v2vnet": "0.822 -> 0.814", "fcooper": "0.790 -> 0.788", "attfuse": "0.815 -> 0.810",
        "cobevt": "0.861 -> 0.836"},
    "CoBEVT Table 4, camera vehicle IoU 0x / 8x / 16x / 32x / 64x (524 / 66 / 33 / 16 / 8 KB; unverified)": {
        "cobevt": "60.4 / 60.1 / 58.9 / 56.2 / 54.8"},
}


# The same figures relative to uncompressed, by ratio, for the plot: CoBEVT Table 4 (camera vehicle IoU; unverified) and
# OpenCOOD's CoBEVT LiDAR AP@0.7 (its compressor at about 64x).
FIELD_RELATIVE = {
    "CoBEVT Table 4 (camera, OPV2V; unverified)": {1: 1.0, 8: 60.1 / 60.4, 16: 58.9 / 60.4, 32: 56.2 / 60.4,
                                                   64: 54.8 / 60.4},
    "OpenCOOD CoBEVT LiDAR AP@0.7 (OPV2V, ~64x)": {1: 1.0, 64: 0.836 / 0.861},
}


def _paired(a: list[dict], b: list[dict], method_a: str, method_b: str, label: str) -> str:
    """mean [lo, hi] of IoU(a, method_a) - IoU(b, method_b) over the seeds both hold."""
    by_seed = {(d["scenario"], d["seed"]): d for d in b}
    diffs = [[d["methods"][method_a]["iou_vehicle"] - by_seed[key]["methods"][method_b]["iou_vehicle"]]
             for d in a if (key := (d["scenario"], d["seed"])) in by_seed]
    iv = interval(diffs, label=label)
    if iv is None:
        return "-"
    star = " *" if iv.excludes_zero else ""
    return f"{iv.mean:+.3f} [{iv.lo:+.3f}, {iv.hi:+.3f}]{star}" if iv.lo is not None else f"{iv.mean:+.3f}"


def plot(runs: dict[tuple[str, int], list[dict]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for scenario in sorted({s for s, _ in runs}):
        ratios = sorted(r for s, r in runs if s == scenario)
        iou = {r: sum(d["methods"]["cobevt"]["iou_vehicle"] for d in runs[(scenario, r)]) / len(runs[(scenario, r)])
               for r in ratios}
        if 1 in iou:
            ax.plot(ratios, [iou[r] / iou[1] for r in ratios], "o-", label=f"ours, CoBEVT LiDAR, {scenario}")
    for source, rel in FIELD_RELATIVE.items():
        ax.plot(list(rel), list(rel.values()), "s--", alpha=0.7, label=source)
    ax.set_xscale("log", base=2)
    ax.set_xlabel("channel compression ratio r (C -> C/r)")
    ax.set_ylabel("vehicle IoU (AP) relative to uncompressed")
    ax.set_title("Wire compression: what each ratio costs CoBEVT")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nplot: {path}")


def main(argv: list[str]) -> None:
    plot_to = None
    if "--plot" in argv:
        i = argv.index("--plot")
        plot_to, argv = Path(argv[i + 1]), argv[:i] + argv[i + 2:]
    dirs = argv
    runs: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for d in dirs:
        for m in sorted(Path(d).glob("runs/*/seed*/metrics.json")):
            ratio = re.search(r"channel_compression=(\w+)", str(m))
            if ratio is None:
                continue
            doc = json.loads(m.read_text())
            runs[(doc["scenario"], int(doc["grid"]["wire_ratio"]))].append(doc)
    for scenario in sorted({s for s, _ in runs}):
        ratios = sorted(r for s, r in runs if s == scenario)
        methods = list(runs[(scenario, ratios[0])][0]["methods"])
        print(f"\n### {scenario} ({len(runs[(scenario, ratios[0])])} seeds per ratio)\n")
        cost = "cobevt" in methods and 1 in ratios
        extra = ["CoBEVT - CoBEVT uncompressed", "CoBEVT - none"] if cost else []
        print("| ratio | message (bytes) | " + " | ".join([f"{m} IoU veh / AP@0.5" for m in methods] + extra) + " |")
        print("|---:|---:|" + "---|" * (len(methods) + len(extra)))
        for r in ratios:
            docs = runs[(scenario, r)]
            size = sum(d["comm"]["bytes_per_message"] for d in docs) / len(docs)
            cells = []
            for m in methods:
                iou = sum(d["methods"][m]["iou_vehicle"] for d in docs) / len(docs)
                ap = [d["methods"][m]["ap50"] for d in docs if d["methods"][m].get("ap50") is not None]
                cells.append(f"{iou:.3f} / {sum(ap) / len(ap):.3f}" if ap else f"{iou:.3f}")
            if cost:
                cells.append("–" if r == 1 else _paired(docs, runs[(scenario, 1)], "cobevt", "cobevt",
                                                        f"{scenario}:cobevt@{r}-cobevt@1"))
                cells.append(_paired(docs, docs, "cobevt", "none", f"{scenario}:cobevt@{r}-none") if "none" in methods
                             else "-")
            print(f"| {r} | {size:,.0f} | " + " | ".join(cells) + " |")
    scenarios = sorted({s for s, _ in runs})
    common = sorted(set.intersection(*[{r for s, r in runs if s == sc} for sc in scenarios])) if scenarios else []
    if len(scenarios) > 1 and 1 in common:
        pooled = {r: [d for sc in scenarios for d in runs[(sc, r)]] for r in common}
        print(f"\n### both junctions pooled ({len(pooled[1])} runs per ratio: each seed of each junction one pair)\n")
        print("| ratio | CoBEVT IoU veh | CoBEVT - CoBEVT uncompressed | CoBEVT - none |")
        print("|---:|---|---|---|")
        for r in common:
            docs = pooled[r]
            iou = sum(d["methods"]["cobevt"]["iou_vehicle"] for d in docs) / len(docs)
            c = "–" if r == 1 else _paired(docs, pooled[1], "cobevt", "cobevt", f"pooled:cobevt@{r}-cobevt@1")
            print(f"| {r} | {iou:.3f} | {c} | {_paired(docs, docs, 'cobevt', 'none', f'pooled:cobevt@{r}-none')} |")
    print("\nThe field's figures (OPV2V, a different dataset):\n")
    for source, rows in FIELD.items():
        print(f"- {source}: " + "; ".join(f"{m} {v}" for m, v in rows.items()))
    if plot_to is not None:
        plot(runs, plot_to)


if __name__ == "__main__":
    main(sys.argv[1:])
