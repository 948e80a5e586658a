"""The LiDAR grid study's table (docs/results.md): validation scores of each method per grid, read from the
zoos scripts/grid_study.sh wrote, beside the CPU cost per frame of `v2vsim bench models --cells ... --json`.

    python scripts/grid_table.py OUT [--cost BENCH.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def scores(out: Path) -> dict[int, dict[str, dict]]:
    """{cells: {method: validation metrics}} of every OUT/g<F>/zoo."""
    table: dict[int, dict[str, dict]] = {}
    for zoo in sorted(out.glob("g*/zoo/manifest.json")):
        if not zoo.parent.parent.name[1:].isdigit():  # e.g. g64bf16: a variant, not a grid
            continue
        cells = int(zoo.parent.parent.name[1:])
        entry = json.loads(zoo.read_text())["zoos"].get("pointpillars_tiny") or {}
        for name, info in (entry.get("files") or {}).items():
            if name == "single.pt" or not info.get("validation"):
                continue
            for method, metrics in info["validation"].items():
                table.setdefault(cells, {})[method] = {**metrics, "wall_s": info["wall_s"]}
    return table


def cost(path: Path | None) -> dict[int, dict[str, float]]:
    """{cells: {row name: ms}} from a `v2vsim bench models --json` file (one thread)."""
    if path is None:
        return {}
    out: dict[int, dict[str, float]] = {}
    for r in json.loads(path.read_text()):
        cells = int(r["preset"].split()[-1].split("x")[0])
        if r["kind"] == "fusion" and r["agents"] != 4:
            continue
        out.setdefault(cells, {})[r["name"]] = r["ms"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--cost", type=Path, default=None)
    args = ap.parse_args()
    table, ms = scores(args.out), cost(args.cost)
    methods = ["none", "late", "v2vnet", "cobevt"]
    print("| grid | cell | method | IoU vehicle | IoU road | IoU lane | AP@0.5 | AP@0.7 | stage wall (min) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for cells in sorted(table):
        for m in methods:
            v = table[cells].get(m)
            if v is None:
                continue
            print(f"| {cells} x {cells} | {100 / cells:.2f} m | {m} | {v['iou_vehicle']:.3f} | {v['iou_road']:.3f} | "
                  f"{v['iou_lane']:.3f} | {v['ap50']:.3f} | {v['ap70']:.3f} | {v['wall_s'] / 60:.1f} |")
    if ms:
        print()
        print("| grid | message (KB, float16) | PointPillars | V2VNet (4 agents) | FuseBEVT (4 agents) | "
              "decoder + heads | PointPillars + warp + FuseBEVT + heads |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for cells in sorted(ms):
            r = ms[cells]
            print(f"| {cells} x {cells} | {64 * cells * cells * 2 / 1024:.0f} | {r.get('pointpillars', 0):.1f} | "
                  f"{r.get('v2vnet', 0):.1f} | {r.get('cobevt', 0):.1f} | {r.get('heads-lidar', 0):.1f} | "
                  f"{r.get('pointpillars+warp+cobevt+heads', 0):.1f} |")


if __name__ == "__main__":
    main()
