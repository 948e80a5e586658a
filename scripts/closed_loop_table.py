"""The closed-loop study's table and plot for docs/results.md (issue 46): from a latency sweep over control.method
and an optional second sweep with comm.compensation on, each driving measure per (method, latency) and its
difference to `none` at the same latency, paired by seed, with the sweeps' own 95 % bootstrap interval.

    python scripts/closed_loop_table.py --sweep runs/study46/latency [runs/study46/more] [--comp DIR] \
        --plot docs/img/closed_loop_latency.png
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from v2vsim.study.stats import interval  # noqa: E402

MEASURES = ("collisions", "near_misses", "either", "min_ttc_s", "min_gap_m", "cleared", "time_to_clear_s",
            "hard_braking", "phantom_braking")


def _num(text: str) -> float | None:
    return None if text in ("", "None", "null") else float(text)


def read(sweep: Path, tag: str) -> dict[tuple[str, float, int], dict[str, float | None]]:
    """(method label, latency ms, seed) -> driving measures of that run (one row per run: the first method's)."""
    out: dict[tuple[str, float, int], dict[str, float | None]] = {}
    with open(sweep / "sweep.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row.get("status", "complete") != "complete":
                continue
            key = (row["control.method"] + tag, float(row["comm.latency_ms.mean"]), int(row["seed"]))
            if key in out:
                continue
            coll, near = _num(row["driving_collisions"]), _num(row["driving_near_misses"])
            ttc = _num(row["driving_time_to_clear_s"])
            out[key] = {"collisions": coll, "near_misses": near,
                        "either": None if coll is None or near is None else float(coll > 0 or near > 0),
                        "min_ttc_s": _num(row["driving_min_ttc_s"]), "min_gap_m": _num(row["driving_min_gap_m"]),
                        "cleared": float(ttc is not None), "time_to_clear_s": ttc,
                        "hard_braking": _num(row["driving_hard_braking"]),
                        "phantom_braking": _num(row["driving_phantom_braking"])}
    return out


def _cell(values: list[float]) -> str:
    iv = interval([[v] for v in values], label="closed-loop")
    if iv is None:
        return "-"
    if iv.lo is None or iv.hi is None:
        return f"{iv.mean:.2f}"
    return f"{iv.mean:+.2f} [{iv.lo:+.2f}, {iv.hi:+.2f}]" + (" *" if iv.lo > 0 or iv.hi < 0 else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sweep", type=Path, nargs="+", required=True, help="one or more sweeps (their seeds add up)")
    ap.add_argument("--comp", type=Path)
    ap.add_argument("--plot", type=Path)
    a = ap.parse_args()
    runs: dict[tuple[str, float, int], dict[str, float | None]] = {}
    for sweep in a.sweep:
        runs |= read(sweep, "")
    if a.comp is not None and (a.comp / "sweep.csv").is_file():
        runs |= read(a.comp, "+comp")
    methods = list(dict.fromkeys(m for m, _, _ in runs))
    latencies = sorted({lat for _, lat, _ in runs})
    by = defaultdict(dict)
    for (m, lat, seed), v in runs.items():
        by[(m, lat)][seed] = v
    print("| method | latency ms | runs | collisions | near misses | collision or near miss | min TTC s | "
          "min gap m | cleared | time to clear s | hard braking | phantom braking |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for m in methods:
        for lat in latencies:
            seeds = by.get((m, lat), {})
            if not seeds:
                continue

            def mean(name: str, seeds: dict = seeds) -> str:
                vals = [s[name] for s in seeds.values() if s[name] is not None]
                return f"{sum(vals) / len(vals):.2f}" + (f" ({len(vals)})" if len(vals) < len(seeds) else "") \
                    if vals else "-"

            print(f"| {m} | {lat:g} | {len(seeds)} | " + " | ".join(mean(n) for n in MEASURES) + " |")
    print()
    print("Against none at the same latency, paired by seed: mean difference [95 % interval] (* excludes 0)")
    print()
    print("| method | latency ms | collision or near miss | min gap m | cleared | hard braking |")
    print("|---|---|---|---|---|---|")
    for m in methods:
        if m == "none":
            continue
        for lat in latencies:
            mine, base = by.get((m, lat), {}), by.get(("none", lat), {})
            cells = []
            for name in ("either", "min_gap_m", "cleared", "hard_braking"):
                d = [mine[s][name] - base[s][name] for s in sorted(set(mine) & set(base))  # type: ignore[operator]
                     if mine[s][name] is not None and base[s][name] is not None]
                cells.append(_cell(d) + f" (n={len(d)})")
            if mine:
                print(f"| {m} | {lat:g} | " + " | ".join(cells) + " |")
    if a.plot is not None:
        fig, axes = plt.subplots(1, 3, figsize=(15, 4))
        for m in methods:
            xs = [lat for lat in latencies if (m, lat) in by]
            for ax, name, label in ((axes[0], "either", "share of runs with a collision or near miss"),
                                    (axes[1], "min_ttc_s", "SSM min TTC (s), runs with a conflict"),
                                    (axes[2], "phantom_braking", "phantom-braking onsets per run")):
                ys, lo, hi = [], [], []
                for lat in xs:
                    vals = [s[name] for s in by[(m, lat)].values() if s[name] is not None]
                    iv = interval([[v] for v in vals], label=f"{m}{lat}{name}")
                    ys.append(iv.mean if iv else float("nan"))
                    lo.append(iv.mean - iv.lo if iv and iv.lo is not None else 0.0)
                    hi.append(iv.hi - iv.mean if iv and iv.hi is not None else 0.0)
                ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", capsize=3, label=m)
                ax.set_xlabel("added V2V latency (ms)")
                ax.set_ylabel(label)
        axes[0].legend(fontsize=8)
        fig.suptitle("Closed loop on t_junction_occluded: safety against latency (held-out seeds "
                     f"{min(s for *_, s in runs)}-{max(s for *_, s in runs)}, 95 % bootstrap intervals)")
        fig.tight_layout()
        a.plot.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(a.plot, dpi=110)


if __name__ == "__main__":
    main()
