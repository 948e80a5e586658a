"""Summarise `v2vsim run` outputs into the zoo's comparison table (README "Results").

    python benchmarks/zoo_table.py RUN_DIR [RUN_DIR ...]

Each RUN_DIR holds a metrics.json. Prints, per (scenario, camera encoder, channel), one row per method with
visible-vehicle IoU, all-vehicle IoU, road, lane, AP@0.5, AP@0.7 and bytes/frame, averaged over
the runs (seeds) given, and the number of runs.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

KEYS = ("iou_vehicle", "iou_vehicle_all", "iou_road", "iou_lane", "ap50", "ap70", "bytes_per_frame")


def main(dirs: list[str]) -> None:
    groups: dict[tuple[str, str, str], list[dict]] = defaultdict(list)
    for d in dirs:
        doc = json.loads((Path(d) / "metrics.json").read_text())
        channel = "ideal" if "ideal" in Path(d).name else "default"
        encoder = "" if doc.get("modality", "lidar") == "lidar" else f" ({doc['encoder']})"
        groups[(doc["scenario"], encoder, channel)].append(doc)
    for (scenario, encoder, channel), docs in sorted(groups.items()):
        print(f"\n### {scenario}{encoder}, {channel} channel ({len(docs)} run(s), {docs[0]['frames']} frames each)\n")
        print("| method | IoU veh (visible) | IoU veh (all) | road | lane | AP@0.5 | AP@0.7 | bytes/frame |")
        print("|---|---|---|---|---|---|---|---|")
        for m in docs[0]["methods"]:
            vals = []
            for k in KEYS:
                xs = [doc["methods"][m][k] for doc in docs if doc["methods"].get(m, {}).get(k) is not None]
                vals.append(None if not xs else sum(xs) / len(xs))
            cells = [f"{v:.3f}" if v is not None and k != "bytes_per_frame" else
                     (f"{v:,.0f}" if v is not None else "–") for k, v in zip(KEYS, vals, strict=True)]
            print(f"| {m} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
