"""The old zoo beside the new one (scripts/towns_eval.sh): per scenario, and pooled per group of scenarios (the old
training junctions, the benchmark families, the held-out generated towns), each method's visible-vehicle IoU and
AP@0.5 / 0.7 under each zoo, and its per-frame vehicle-IoU difference to `none` with a 95 % paired bootstrap interval
whose clusters are the runs (scenario x seed; v2vsim.study.stats.interval).

    python scripts/towns_table.py OUT_DIR OLD_ZOO NEW_ZOO
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from models.registry import is_intermediate
from v2vsim.study.stats import interval

METHODS = ("none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt")
OLD_JUNCTIONS = ("intersection", "t_junction")
FAMILIES = ("left_turn_truck", "crossroads_occluded", "ramp_merge", "red_light_runner", "blind_corner_stop",
            "t_junction_occluded")


def group_of(scenario: str) -> str:
    if scenario in OLD_JUNCTIONS:
        return "old training junctions (held-out seeds)"
    if scenario in FAMILIES:
        return "benchmark families (held-out seeds, cast, open loop)"
    return "generated test towns"


def load(out: Path, zoos: dict[str, str]) -> list[dict]:
    rows, seen = [], set()
    for sj in sorted(out.glob("*/*/sweep.json")):  # OUT/<old|new>[SUFFIX]/<scenario>/sweep.json
        doc = json.loads(sj.read_text())
        for r in doc["rows"]:
            zoo = zoos.get(str(r.get("perception.weights")))
            key = (zoo, sj.parent.name, r.get("seed"), r.get("method"))
            if zoo is not None and r.get("status", "complete") == "complete" and key not in seen:
                seen.add(key)  # a method added later (towns_eval.sh SUFFIX=_v2vnet) re-runs `none`: count each run once
                rows.append({**r, "zoo": zoo, "scenario_dir": sj.parent.name})
    return rows


def _mean(vals: list) -> str:
    vals = [v for v in vals if v is not None]
    return f"{np.mean(vals):.3f}" if vals else "-"


def _diff(rows: list[dict], method: str, label: str) -> str:
    """method - none, per-frame vehicle IoU, clusters = runs."""
    by = {(r["scenario_dir"], r["seed"], r["method"]): dict(r.get("per_frame_iou_vehicle") or []) for r in rows}
    clusters = []
    for (sc, seed, m), frames in by.items():
        if m != method or (sc, seed, "none") not in by:
            continue
        base = by[(sc, seed, "none")]
        common = sorted(set(frames) & set(base))
        if common:
            clusters.append([frames[f] - base[f] for f in common])
    iv = interval(clusters, 2000, label, 0)
    if iv is None:
        return "-"
    star = "*" if iv.excludes_zero else ""
    return f"{iv.mean:+.3f} [{iv.lo:+.3f}, {iv.hi:+.3f}]{star}" if iv.lo is not None else f"{iv.mean:+.3f}"


def main(out: Path, old: str, new: str) -> None:
    zoos = {str(Path(old).resolve()): "old", str(Path(new).resolve()): "new"}
    rows = load(out, zoos)
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        groups[group_of(r["scenario_dir"])].append(r)
    for g, mine in groups.items():
        runs = len({(r["scenario_dir"], r["seed"]) for r in mine})
        print(f"\n### {g}: {runs} runs per zoo\n")
        print("| method | IoU old | IoU new | IoU - none old | IoU - none new | AP@0.5 old / new | AP@0.7 old / new |")
        print("|---|---|---|---|---|---|---|")
        for m in METHODS:
            o = [r for r in mine if r["zoo"] == "old"]
            n = [r for r in mine if r["zoo"] == "new"]
            om, nm = [r for r in o if r["method"] == m], [r for r in n if r["method"] == m]
            diffs = ("-", "-") if m == "none" else (_diff(o, m, f"{g}|old|{m}"), _diff(n, m, f"{g}|new|{m}"))
            print(f"| {m} | {_mean([r['iou_vehicle'] for r in om])} | {_mean([r['iou_vehicle'] for r in nm])} | "
                  f"{diffs[0]} | {diffs[1]} | {_mean([r['ap50'] for r in om])} / {_mean([r['ap50'] for r in nm])} | "
                  f"{_mean([r['ap70'] for r in om])} / {_mean([r['ap70'] for r in nm])} |")
    print("\n### Per scenario: none / CoBEVT vehicle IoU and CoBEVT AP@0.7, old -> new\n")
    print("| scenario | runs | none | CoBEVT | CoBEVT AP@0.7 |")
    print("|---|---|---|---|---|")
    for sc in sorted({r["scenario_dir"] for r in rows}):
        mine = [r for r in rows if r["scenario_dir"] == sc]

        def pick(zoo: str, m: str, k: str, mine: list[dict] = mine) -> str:
            return _mean([r[k] for r in mine if r["zoo"] == zoo and r["method"] == m])

        runs = len({r["seed"] for r in mine})
        print(f"| {sc} | {runs} | {pick('old', 'none', 'iou_vehicle')} -> {pick('new', 'none', 'iou_vehicle')} | "
              f"{pick('old', 'cobevt', 'iou_vehicle')} -> {pick('new', 'cobevt', 'iou_vehicle')} | "
              f"{pick('old', 'cobevt', 'ap70')} -> {pick('new', 'cobevt', 'ap70')} |")

    print("\n### Per benchmark family: each intermediate method's per-frame vehicle IoU - none, old -> new "
          "(95 % paired interval over its runs; * excludes 0)\n")
    inter = [m for m in METHODS if is_intermediate(m)]
    print("| scenario | " + " | ".join(inter) + " |")
    print("|---|" + "---|" * len(inter))
    for sc in FAMILIES:
        mine = [r for r in rows if r["scenario_dir"] == sc]
        if not mine:
            continue
        cells = [f"{_diff([r for r in mine if r['zoo'] == 'old'], m, f'{sc}|old|{m}')} -> "
                 f"{_diff([r for r in mine if r['zoo'] == 'new'], m, f'{sc}|new|{m}')}" for m in inter]
        print(f"| {sc} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2], sys.argv[3])
