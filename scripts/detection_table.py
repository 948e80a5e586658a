"""The misbehaviour check as a detector (issue 55; docs/results.md "A lying CAV"): true and false positive rates
from runs made with `defence.detect: true`, clean and attacked (scripts/detection_study.sh makes them).

Each run's metrics.json holds, per sender, every frame it was compared in (`defence.senders.<id>.per_frame`:
frame, road, vehicle_m2, shared_m2, flagged, road_corr, road_vs_map). Per lie (an attacked run's `misbehaviour`):
TPR = the liar's frames flagged / its frames compared from the lie's first frame on. Over the clean runs: FPR =
honest sender-frames flagged / compared, and the runs a sender was flagged in on `min_frames` frames or more (the
status a user sees). With --road-threshold / --vehicle-threshold the flags are recomputed from the recorded scores
(calibration; --camera-road-threshold for runs where a CAV has cameras); without, the flags the runs recorded
are counted.

    python scripts/detection_table.py RUN_DIR... [--road-threshold 0.2 --camera-road-threshold 0.45
                                                  --vehicle-threshold 40 --min-frames 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path


def _flag(row: list, road_t: float | None, veh_t: float | None, min_shared: float) -> bool:
    if road_t is None and veh_t is None:
        return bool(row[4])
    vs_map = row[6] if len(row) > 6 else None
    if row[3] < min_shared:
        return False
    return (vs_map is not None and vs_map > road_t) or row[2] > veh_t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run directories (or folders holding them)")
    ap.add_argument("--road-threshold", type=float)
    ap.add_argument("--vehicle-threshold", type=float)
    ap.add_argument("--camera-road-threshold", type=float,
                    help="--road-threshold for runs where a CAV has cameras (default: --road-threshold)")
    ap.add_argument("--min-shared", type=float, default=100.0)
    ap.add_argument("--min-frames", type=int, default=3)
    a = ap.parse_args(argv)
    if (a.road_threshold is None) != (a.vehicle_threshold is None):
        ap.error("give both --road-threshold and --vehicle-threshold, or neither")
    docs = sorted({p for r in a.runs for p in ([r / "metrics.json"] if (r / "metrics.json").is_file()
                                                 else r.rglob("metrics.json"))})
    honest_n = honest_fp = 0
    clean_runs: list[tuple[str, int]] = []  # (run, most frames any sender was flagged in)
    per_lie: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0, 0])  # kind -> [tp, n, runs detected, runs]
    first: dict[str, list[int]] = defaultdict(list)  # kind -> frames from the first comparison to the first flag
    for path in docs:
        m = json.loads(path.read_text())
        if "defence" not in m:
            continue
        lies = m.get("misbehaviour", [])
        cameras = m.get("modality") == "camera" or any(
            str(t).startswith("camera") for t in m.get("fleet", {}).get("cavs", {}).values())
        road_t = a.camera_road_threshold if cameras and a.camera_road_threshold is not None else a.road_threshold
        liars = {c: lie for lie in lies for c in lie["cavs"]}
        most = 0
        for sender, v in m["defence"]["senders"].items():
            rows = v["per_frame"]
            if sender in liars:
                lie = liars[sender]
                rows = [r for r in rows if r[0] >= lie["from_frame"]]
                hits = [_flag(r, road_t, a.vehicle_threshold, a.min_shared) for r in rows]
                t = per_lie[lie["kind"]]
                t[0] += sum(hits)
                t[1] += len(hits)
                t[2] += sum(hits) >= a.min_frames
                t[3] += 1
                if any(hits):
                    first[lie["kind"]].append(hits.index(True))
                continue
            hits = [_flag(r, road_t, a.vehicle_threshold, a.min_shared) for r in rows]
            if not lies:
                honest_n += len(hits)
                honest_fp += sum(hits)
                most = max(most, sum(hits))
        if not lies:
            clean_runs.append((str(path.parent), most))
    print("| lie | liar frames flagged (TPR) | runs flagged | frames to the first flag (median) |")
    print("|---|---|---|---|")
    for kind, (tp, n, runs_hit, runs) in sorted(per_lie.items()):
        f = sorted(first[kind])
        med = f[len(f) // 2] if f else "-"
        print(f"| {kind} | {tp} / {n} ({tp / max(n, 1):.2f}) | {runs_hit} / {runs} | {med} |")
    flagged_runs = [r for r, most in clean_runs if most >= a.min_frames]
    print(f"\nclean runs: honest sender-frames flagged (FPR) {honest_fp} / {honest_n} "
          f"({honest_fp / max(honest_n, 1):.3f}); runs with a sender flagged in >= {a.min_frames} frames: "
          f"{len(flagged_runs)} / {len(clean_runs)}")
    for r in flagged_runs:
        print(f"  flagged: {r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
