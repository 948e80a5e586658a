"""Issue 67's evidence study table (scripts/evidence_study.sh): from each run's metrics.json `defence.evidence`,
the honest senders' figures on the clean runs (per sender-frame: median, 98th percentile, max) and, per lie, the
liar's frames past the clean runs' 98th percentile and the frames to the first one.

    python scripts/evidence_table.py runs/evidence/seed0 [--clean runs/evidence/seed100]

--clean: take the clean distribution (the thresholds) from another seed's runs (the tuning seed), so that the lie
rows are judged on thresholds their seed never set."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

# per-frame row of metrics.json defence.evidence (agents/ego_defence.py): figure -> its column, and how it is read
FIGURES = {"phantom_m2": 1, "removed_m2": 2, "unclaimed_m2": 3, "pose_gain": None, "later_m2": None,
           "pose_cusum": 13}
POSE_CUSUM_DRIFT = 0.16  # DefenceConfig.pose_cusum_drift: rows of runs from before the CUSUM get it recomputed


def _value(row: list, name: str) -> float | None:
    if name == "pose_gain":  # walls on the map after the best correction minus as claimed
        return None if row[7] is None else float(row[8]) - float(row[7])
    if name == "later_m2":  # the ego's later view: the larger of its phantom and removed areas (null: none kept)
        return None if len(row) < 13 or row[11] is None else max(float(row[11]), float(row[12]))
    return float(row[FIGURES[name]])


def rows_of(run: Path) -> dict[str, list[list]]:
    """Per sender its evidence rows, each with its pose gain's CUSUM at index 13 (recomputed with the default drift
    for a run recorded before the defence kept it)."""
    doc = json.loads((run / "metrics.json").read_text())
    ev = (doc.get("defence") or {}).get("evidence") or {}
    out = {}
    for s, x in ev.items():
        rows, total = [], 0.0
        for r in x["per_frame"]:
            if len(r) < 14:
                gain = 0.0 if r[7] is None else float(r[8]) - float(r[7])
                total = max(0.0, total + gain - POSE_CUSUM_DRIFT)
                r = [*r, *([None] * (13 - len(r))), round(total, 4)]
            rows.append(r)
        out[s] = rows
    return out


def liars_of(run: Path) -> set[str]:
    doc = json.loads((run / "metrics.json").read_text())
    return {c for lie in doc.get("misbehaviour") or [] for c in lie.get("cavs", [])}


def honest_rows(run: Path) -> list[list]:
    """Every honest sender's per-frame rows of one run."""
    liars = liars_of(run)
    return [r for s, rows in rows_of(run).items() if s not in liars for r in rows]


def consistency_flags(run: Path) -> dict[str, dict[int, bool]]:
    """Per sender and frame, the consistency check's own verdict (metrics.json defence.senders per_frame: [frame,
    road, vehicle_m2, shared_m2, flagged, ...]): camera senders send no evidence, and this is all that judges them."""
    doc = json.loads((run / "metrics.json").read_text())
    senders = (doc.get("defence") or {}).get("senders") or {}
    return {s: {int(r[0]): bool(r[4]) for r in x.get("per_frame", [])} for s, x in senders.items()}


def honest_alarms(run: Path, limit: dict[str, float]) -> tuple[int, int]:
    """The honest sender-frames a run judged (by the consistency check or by evidence) and those flagged by either:
    the defence's rule, one figure past its threshold or the consistency check's flag."""
    liars, ev = liars_of(run), rows_of(run)
    judged = flagged = 0
    cons = consistency_flags(run)
    for s in sorted(set(cons) | set(ev)):
        if s in liars:
            continue
        frames = cons.get(s, {})
        by_ev = {int(r[0]): flagged_by(r, limit) for r in ev.get(s, [])}
        both = set(by_ev) | set(frames)
        judged += len(both)
        flagged += sum(by_ev.get(f, False) or frames.get(f, False) for f in both)
    return judged, flagged


def flagged_by(row: list, limit: dict[str, float]) -> bool:
    """The sender-frame is past a figure's threshold (the defence's rule: any figure flags)."""
    return any((v := _value(row, k)) is not None and v > limit[k] for k in limit)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--clean", type=Path, default=None)
    ap.add_argument("--percentile", type=float, default=100.0,
                    help="each threshold at this percentile of the clean sender-frames (100: their maximum)")
    ap.add_argument("--margin", type=float, default=1.25, help="and this times it (room for seeds it never saw)")
    a = ap.parse_args(argv)
    clean_dir = a.clean or a.folder
    clean: dict[str, list[float]] = {k: [] for k in FIGURES}
    for run in sorted(clean_dir.glob("clean_*")):
        if (run / "metrics.json").is_file():
            for r in honest_rows(run):
                for k in FIGURES:
                    if (v := _value(r, k)) is not None:
                        clean[k].append(v)
    if not clean["phantom_m2"]:
        print(f"no clean runs with evidence under {clean_dir}", file=sys.stderr)
        return 1
    limit = {k: round(a.margin * float(np.percentile(v, a.percentile)), 2) for k, v in clean.items() if v}
    print(f"Honest senders, clean runs of {clean_dir} (sender-frames); threshold = {a.margin} x the "
          f"{a.percentile:g}th percentile:\n")
    print("| figure | sender-frames | median | 98th percentile | max | threshold |\n|---|---|---|---|---|---|")
    for k, v in clean.items():
        if v:
            print(f"| {k} | {len(v)} | {np.median(v):.2f} | {np.percentile(v, 98):.2f} | {max(v):.2f} | "
                  f"{limit[k]:.2f} |")
    names = {"phantom_m2": "phantom_threshold_m2", "removed_m2": "removed_threshold_m2",
             "unclaimed_m2": "unclaimed_threshold_m2", "pose_gain": "pose_gain_threshold",
             "later_m2": "later_threshold_m2", "pose_cusum": "pose_cusum_threshold"}
    print("\nAs settings: " + " ".join(f"--set defence.{names[k]}={v}" for k, v in limit.items()))
    print(f"\nHonest sender-frames flagged, {a.folder} (the false alarms: by any evidence figure or by the consistency "
          "check; goal <= 2 %), and the ego's check per frame (the `consistency` stage, ms):\n")
    print("| run | honest sender-frames judged | flagged | share | check ms |\n|---|---|---|---|---|")
    for run in sorted(a.folder.glob("*")):
        if not (run / "metrics.json").is_file():
            continue
        judged, n = honest_alarms(run, limit)
        ms = json.loads((run / "metrics.json").read_text())["timing"]["ms_per_frame"].get("consistency")
        print(f"| {run.name} | {judged} | {n} | {100 * n / max(1, judged):.1f} % | "
              f"{'-' if ms is None else f'{ms:.0f}'} |")
    print(f"\nLies, {a.folder}: the liar's sender-frames past each threshold (frames to the first), and by any:\n")
    print("| run | liar frames | " + " | ".join(FIGURES) + " | any |\n|---|---|" + "---|" * (len(FIGURES) + 1))
    for run in sorted(a.folder.glob("lie_*")):
        if not (run / "metrics.json").is_file():
            continue
        rows = {s: r for s, r in rows_of(run).items() if s in liars_of(run)}
        n = sum(len(r) for r in rows.values())
        cells = []
        for k in [*FIGURES, None]:
            one = limit if k is None else {k: limit.get(k, np.inf)}  # None: any figure
            past = [[flagged_by(r, one) for r in rs] for rs in rows.values()]
            hit = sum(sum(p) for p in past)
            first = min((p.index(True) for p in past if True in p), default=None)
            cells.append(f"{hit} ({'-' if first is None else first})")
        print(f"| {run.name} | {n} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
