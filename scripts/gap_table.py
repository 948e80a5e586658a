"""The gap study's table (scripts/gap_study.sh): per family and variant, the mean over seeds of each method's
visible-vehicle IoU and CoBEVT's AP@0.5 / 0.7, and the run count.

    python scripts/gap_table.py OUT_DIR
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

VARIANTS = ("as_is", "dense", "no_buildings", "no_standing", "cars_only", "stripped")
WHAT = {"as_is": "as in the benchmark", "dense": "traffic 900 veh/h", "no_buildings": "no buildings",
        "no_standing": "no standing truck", "cars_only": "cars only (no vans, trucks)",
        "stripped": "all four removed: the net and the cast"}


def main(out: Path) -> None:
    print("| scenario | variant | runs | IoU none | IoU CoBEVT | IoU V2VNet | CoBEVT AP@0.5 | CoBEVT AP@0.7 |")
    print("|---|---|---|---|---|---|---|---|")
    for fam in sorted(p for p in out.iterdir() if p.is_dir()):
        for variant in VARIANTS:
            docs = [json.loads(m.read_text()) for m in sorted((fam / variant).glob("seed*/metrics.json"))]
            if not docs:
                continue

            def mean(method: str, key: str, docs: list[dict] = docs) -> str:
                vals = [d["methods"][method][key] for d in docs if d["methods"][method][key] is not None]
                return f"{sum(vals) / len(vals):.3f}" if vals else "-"

            print(f"| {fam.name} | {WHAT[variant]} | {len(docs)} | {mean('none', 'iou_vehicle')} | "
                  f"{mean('cobevt', 'iou_vehicle')} | {mean('v2vnet', 'iou_vehicle')} | {mean('cobevt', 'ap50')} | "
                  f"{mean('cobevt', 'ap70')} |")


def range_table(out: Path) -> None:
    """Per scenario and variant, none's and CoBEVT's visible-vehicle IoU in each ring of distance from the ego (runs
    that report it: iou_vehicle_by_range)."""
    print("\n| scenario | variant | runs | none 0-20 / 20-35 / 35-50 m | CoBEVT 0-20 / 20-35 / 35-50 m |")
    print("|---|---|---|---|---|")
    for fam in sorted(p for p in out.iterdir() if p.is_dir()):
        for variant in VARIANTS:
            docs = [json.loads(m.read_text()) for m in sorted((fam / variant).glob("seed*/metrics.json"))]
            docs = [d for d in docs if "iou_vehicle_by_range" in d["methods"]["none"]]
            if not docs:
                continue

            def rings(method: str, docs: list[dict] = docs) -> str:
                cells = []
                for ring in ("0-20", "20-35", "35-50"):
                    vals = [d["methods"][method]["iou_vehicle_by_range"].get(ring) for d in docs]
                    vals = [v for v in vals if v is not None]
                    cells.append(f"{sum(vals) / len(vals):.3f}" if vals else "-")
                return " / ".join(cells)

            print(f"| {fam.name} | {WHAT[variant]} | {len(docs)} | {rings('none')} | {rings('cobevt')} |")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
    range_table(Path(sys.argv[1]))
