"""The heterogeneous-collaboration tables (issue 48) from scripts/hetero_study.sh's sweeps.

    python scripts/hetero_table.py OUT

1. Per fleet and method: vehicle IoU, AP@0.5 / AP@0.7 (means over every complete run: seeds x junctions), and the
   paired differences in vehicle IoU and AP@0.5 to the ego alone (`none` of the same run: the same frames and scored
   vehicles), each with its 95 % bootstrap interval over runs (v2vsim.study.stats.interval; a run is a cluster of
   one value).
2. The camera-only fleet in the aligned space against the shipped camera zoo: per method, each one's vehicle IoU
   and the paired difference (aligned - zoo) over the same (junction, seed) runs.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

from v2vsim.study.stats import interval

FLEETS = {
    "lidar": "LiDAR ego + 3 LiDAR CAVs (the base)",
    "l_cam3": "LiDAR ego + 3 camera CAVs (aligned)",
    "l_lid1_cam2": "LiDAR ego + 1 LiDAR + 2 camera CAVs",
    "c_lid3": "camera ego (aligned) + 3 LiDAR CAVs",
    "cam_aligned": "camera ego + 3 camera CAVs, all aligned",
    "cam_zoo": "camera ego + 3 camera CAVs, the shipped camera zoo",
}
METRICS = ("iou_vehicle", "ap50", "ap70")


def load(out: Path, fleet: str) -> dict[tuple[str, int], dict[str, dict[str, float | None]]]:
    """(junction, seed) -> method -> scores, complete runs only."""
    runs: dict[tuple[str, int], dict[str, dict[str, float | None]]] = {}
    for sweep in sorted(out.glob(f"*/{fleet}/sweep.csv")):
        junction = sweep.parent.parent.name
        with open(sweep) as f:
            for r in csv.DictReader(f):
                if r["status"] != "complete":
                    continue
                runs.setdefault((junction, int(r["seed"])), {})[r["method"]] = {
                    m: float(r[m]) if r[m] not in ("", None) else None for m in METRICS}
    return runs


def _fmt(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"


def _mean(vals: list[float | None]) -> float | None:
    vals = [v for v in vals if v is not None]
    return sum(vals) / len(vals) if vals else None


def _diff(pairs: list[float]) -> str:
    iv = interval([[d] for d in pairs], label="hetero")
    if iv is None:
        return "–"
    if iv.lo is None:
        return f"{iv.mean:+.3f}"
    mark = " **" if iv.excludes_zero and iv.mean > 0 else ""
    return f"{iv.mean:+.3f} [{iv.lo:+.3f}, {iv.hi:+.3f}]{mark}"


def fleet_table(out: Path) -> None:
    print("| fleet | method | runs | vehicle IoU | AP@0.5 | AP@0.7 | vehicle IoU − ego alone [95 % CI] | "
          "AP@0.5 − ego alone [95 % CI] |")
    print("|---|---|---:|---:|---:|---:|---|---|")
    for fleet, label in FLEETS.items():
        runs = load(out, fleet)
        if not runs:
            continue
        methods = list(dict.fromkeys(m for per in runs.values() for m in per))
        for m in methods:
            have = [per for per in runs.values() if m in per]
            cells = [_fmt(_mean([per[m][k] for per in have])) for k in METRICS]
            diffs = []
            for k in ("iou_vehicle", "ap50"):
                pairs = [per[m][k] - per["none"][k] for per in have  # type: ignore[operator]
                         if "none" in per and m != "none" and per[m][k] is not None and per["none"][k] is not None]
                diffs.append(_diff(pairs) if pairs else "")
            print(f"| {label} | {m} | {len(have)} | " + " | ".join(cells + diffs) + " |")


def camera_table(out: Path) -> None:
    aligned, shipped = load(out, "cam_aligned"), load(out, "cam_zoo")
    common = sorted(set(aligned) & set(shipped))
    print(f"\nCamera-only fleets on the same {len(common)} runs (junction, seed):\n")
    print("| method | aligned into the LiDAR space: vehicle IoU | shipped camera zoo: vehicle IoU | "
          "aligned − zoo [95 % CI] |")
    print("|---|---:|---:|---|")
    methods = [m for m in dict.fromkeys(m for per in shipped.values() for m in per)
               if all(m in aligned[k] for k in common)]
    for m in methods:
        a = [aligned[k][m]["iou_vehicle"] for k in common]
        z = [shipped[k][m]["iou_vehicle"] for k in common]
        pairs = [x - y for x, y in zip(a, z, strict=True) if x is not None and y is not None]
        print(f"| {m} | {_fmt(_mean(a))} | {_fmt(_mean(z))} | {_diff(pairs)} |")


def main(argv: list[str]) -> int:
    out = Path(argv[0])
    fleet_table(out)
    camera_table(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
