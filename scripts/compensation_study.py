"""What latency compensation recovers, from a `v2vsim sweep` over comm.latency_ms.mean x comm.compensation.

    python scripts/compensation_study.py SWEEP_DIR [--methods cobevt,late] [--json OUT.json]

For each added latency d and method, paired over the same seeds and frames (per-frame visible-vehicle IoU,
clustered by seed, as `v2vsim sweep` pairs methods; v2vsim.study.stats):
    loss      IoU(0 ms, off) - IoU(d, off)     what latency costs without compensation
    gain      IoU(d, on) - IoU(d, off)         what compensation gives back
    recovered gain / loss                      (dataset-level IoU means)
with 95 % intervals. Prints a markdown table (docs/results.md "Latency compensation").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections import defaultdict
from pathlib import Path

from v2vsim.study.stats import interval, paired_clusters

LATENCY = "comm.latency_ms.mean"
COMPENSATION = "comm.compensation"


def _overrides(doc: dict) -> dict[str, str]:
    return dict(o.split("=", 1) for o in doc.get("overrides", []))


def load(sweep: Path) -> dict[tuple[float, bool, str], dict[int, tuple[float, dict[int, float]]]]:
    """(latency ms, compensation, method) -> seed -> (dataset-level IoU, frame -> IoU)."""
    out: dict = defaultdict(dict)
    for path in sorted(sweep.glob("runs/*/seed*/metrics.json")):
        doc = json.loads(path.read_text())
        if doc.get("status") != "complete":
            continue
        o = _overrides(doc)
        lat = float(o.get(LATENCY, 0))
        comp = o.get(COMPENSATION, "false").lower() in ("true", "1", "yes", "on")
        for m, r in doc["methods"].items():
            frames = {k: i / u for k, (i, u) in enumerate(r.get("iou_vehicle_counts") or []) if u}
            out[(lat, comp, m)][int(doc["seed"])] = (r["iou_vehicle"], frames)
    return out


def _mean(table: dict[int, tuple[float, dict]], seeds: list[int]) -> float:
    return sum(table[s][0] for s in seeds) / len(seeds)


def _diff(a: dict, b: dict, seeds: list[int], label: str):
    return interval(paired_clusters([a[s][1] for s in seeds], [b[s][1] for s in seeds]), label=label)


def study(data: dict, methods: list[str]) -> list[dict]:
    rows = []
    lats = sorted({k[0] for k in data})
    for m in methods:
        base = data.get((0.0, False, m))
        if not base:
            continue
        for lat in lats:
            off, on = data.get((lat, False, m)), data.get((lat, True, m))
            if not off or not on:
                continue
            seeds = sorted(set(base) & set(off) & set(on))
            loss = _diff(base, off, seeds, f"loss {m} {lat}")
            gain = _diff(on, off, seeds, f"gain {m} {lat}")
            l_mean = _mean(base, seeds) - _mean(off, seeds)
            g_mean = _mean(on, seeds) - _mean(off, seeds)
            rows.append({"latency_ms": lat, "method": m, "seeds": seeds, "iou_0ms": _mean(base, seeds),
                         "iou_off": _mean(off, seeds), "iou_on": _mean(on, seeds),
                         "loss": dataclasses.asdict(loss), "gain": dataclasses.asdict(gain),
                         "recovered": g_mean / l_mean if abs(l_mean) > 1e-9 else None})
    return rows


def _iv(d: dict) -> str:
    lo, hi = d.get("lo"), d.get("hi")
    star = "*" if lo is not None and hi is not None and (lo > 0 or hi < 0) else ""
    return f"{d['mean']:+.3f} [{lo:+.3f}, {hi:+.3f}]{star}" if lo is not None else f"{d['mean']:+.3f}"


def markdown(rows: list[dict]) -> str:
    lines = ["| added latency ms | method | IoU 0 ms | IoU off | IoU on | loss vs 0 ms (off), per-frame [95 %] "
             "| gain on - off, per-frame [95 %] | share of the loss recovered |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rec = "-" if r["recovered"] is None else f"{100 * r['recovered']:.0f} %"
        lines.append(f"| {r['latency_ms']:g} | {r['method']} | {r['iou_0ms']:.3f} | {r['iou_off']:.3f} | "
                     f"{r['iou_on']:.3f} | {_iv(r['loss'])} | {_iv(r['gain'])} | {rec} |")
    seeds = sorted({s for r in rows for s in r["seeds"]})
    lines += ["", f"Seeds {', '.join(map(str, seeds))}; IoU: dataset-level visible-vehicle IoU, mean over seeds; "
              "intervals: paired per-frame differences clustered by seed (v2vsim.study.stats), * excludes 0; "
              "share recovered: gain / loss of the dataset-level means."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sweep", type=Path)
    ap.add_argument("--methods", default="cobevt,late")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    rows = study(load(a.sweep), a.methods.split(","))
    if not rows:
        print(f"{a.sweep}: no complete runs with {LATENCY} 0 and both {COMPENSATION} values", file=sys.stderr)
        return 2
    print(markdown(rows))
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
