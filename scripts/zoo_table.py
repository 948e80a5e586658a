"""Summarise `v2vsim run` outputs into the zoo's comparison table (docs/results.md).

    python scripts/zoo_table.py RUN_DIR [RUN_DIR ...]

Each RUN_DIR holds a metrics.json (a sweep's runs: OUT/runs/<point>/seed<N>).
Prints, per (scenario, camera encoder, channel), one row per method with
visible-vehicle IoU, all-vehicle IoU, road, lane, AP@0.5, AP@0.7 and bytes/frame, averaged over
the runs (seeds) given, and the number of runs.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

KEYS = ("iou_vehicle", "iou_vehicle_all", "iou_road", "iou_lane", "ap50", "ap70", "bytes_per_frame")
HEADERS = ("IoU veh (visible)", "IoU veh (all)", "road", "lane", "AP@0.5", "AP@0.7", "bytes/frame")


def main(dirs: list[str]) -> None:
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for d in dirs:
        doc = json.loads((Path(d) / "metrics.json").read_text())
        # a run of scripts/eval_zoo.sh's sweep: .../runs/comm.bandwidth_mbps=null/seed3 (older: .../NAME_ideal)
        channel = "ideal" if "ideal" in Path(d).name or "bandwidth_mbps=null" in str(d) else "default"
        encoder = "" if doc.get("modality", "lidar") == "lidar" else f" ({doc['encoder']})"
        groups[(doc["scenario"], encoder, channel)].append(doc)
    for (scenario, encoder, channel), docs in sorted(groups.items()):
        print(f"\n### {scenario}{encoder}, {channel} channel ({len(docs)} run(s), {docs[0]['frames']} frames each)\n")
        rows = {m: [_mean(docs, m, k) for k in KEYS] for m in docs[0]["methods"]}
        # the camera track has no detection head: AP columns that are empty for every method are left out
        keep = [i for i, k in enumerate(KEYS) if not k.startswith("ap") or any(r[i] is not None for r in rows.values())]
        print("| method | " + " | ".join(HEADERS[i] for i in keep) + " |")
        print("|---|" + "---|" * len(keep))
        for m, vals in rows.items():
            cells = [_cell(KEYS[i], vals[i]) for i in keep]
            print(f"| {m} | " + " | ".join(cells) + " |")


def _mean(docs: list[dict], method: str, key: str) -> float | None:
    xs = [doc["methods"][method][key] for doc in docs if doc["methods"].get(method, {}).get(key) is not None]
    return None if not xs else sum(xs) / len(xs)


def _cell(key: str, v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v:,.0f}" if key == "bytes_per_frame" else f"{v:.3f}"


if __name__ == "__main__":
    main(sys.argv[1:])
