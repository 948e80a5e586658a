"""A sweep's statistics and files: sweep.csv, sweep.json, sweep.md.

Per grid point and metric: each method's mean over seeds with a 95% interval, and paired differences
(every method minus `none`; `cobevt` minus every other method), from the two-level bootstrap in
v2vsim.study.stats. `iou_vehicle_frame_mean` is resampled over seeds and frames when every run of the
point has per-frame values (recording.rrd); every other metric is a whole-run value, resampled over seeds.
A closed-loop sweep adds its driving comparison against `none` (v2vsim.study.driving) to sweep.json and
sweep.md; an open-loop sweep's files do not change.
"""

from __future__ import annotations

import csv
import itertools
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from v2vsim.evaluation.status import as_configured
from v2vsim.study.driving import BASELINE as DRIVING_BASELINE
from v2vsim.study.driving import LABELS as DRIVING_LABELS
from v2vsim.study.driving import MEASURES, METHOD_KEY, DrivingStudy
from v2vsim.study.grid import Axis, Point
from v2vsim.study.rows import Row, methods_of, metric_columns
from v2vsim.study.stats import LEVEL, Interval, interval, paired_clusters

STAT_METRICS = ("iou_vehicle", "iou_vehicle_frame_mean", "iou_road", "iou_lane", "ap50", "ap70")
FRAME_METRIC = "iou_vehicle_frame_mean"  # the metric whose per-frame values a recording holds
LABELS = {"iou_vehicle": "vehicle IoU (visible, dataset-level)",
          "iou_vehicle_frame_mean": "vehicle IoU (per-frame mean)", "iou_road": "road IoU",
          "iou_lane": "lane IoU", "ap50": "AP@0.5", "ap70": "AP@0.7"}
BASELINE, LEADER = "none", "cobevt"
STATUS_COLUMN = "status"  # sweep.csv's last column: the run's metrics.json status


@dataclass(frozen=True)
class PointStats:
    point: Point
    metric: str
    level: str  # "seeds and frames" or "seeds"
    methods: dict[str, Interval | None]
    differences: dict[tuple[str, str], Interval | None]  # (a, b) -> a - b


def pairs(methods: Sequence[str]) -> list[tuple[str, str]]:
    """(a) every method minus none, (b) cobevt minus every other method (cobevt - none only once)."""
    out = [(m, BASELINE) for m in methods if m != BASELINE and BASELINE in methods]
    out += [(LEADER, m) for m in methods if LEADER in methods and m not in (LEADER, BASELINE)]
    return out


def _clusters(rows: dict[int, Row], seeds: Sequence[int], metric: str, frames: bool) -> list[dict[int, float]]:
    """Per seed (in order), frame -> value: the per-frame values, or the run's value as one 'frame'."""
    out = []
    for s in seeds:
        r = rows.get(s)
        if r is None:
            out.append({})
        elif frames:
            out.append(dict(r.per_frame or {}))
        else:
            v = r.metrics.get(metric)
            out.append({} if v is None else {0: float(v)})
    return out


def point_stats(rows: Sequence[Row], pts: Sequence[Point], metric: str, b: int, rng_seed: int) -> list[PointStats]:
    methods = methods_of(rows)
    by: dict[tuple[str, str], dict[int, Row]] = {}
    for r in rows:
        by.setdefault((r.point.pid, r.method), {})[r.seed] = r
    out = []
    for p in pts:
        mine = {m: by.get((p.pid, m), {}) for m in methods}
        seeds = sorted({s for d in mine.values() for s in d})
        if not seeds:
            continue
        frames = metric == FRAME_METRIC and all(r.per_frame for d in mine.values() for r in d.values())
        cl = {m: _clusters(mine[m], seeds, metric, frames) for m in methods}
        label = f"{p.pid}|{metric}"
        ivs = {m: interval([list(c.values()) for c in cl[m]], b, f"{label}|{m}", rng_seed) for m in methods}
        diffs = {(a, c): interval(paired_clusters(cl[a], cl[c]), b, f"{label}|{a}-{c}", rng_seed)
                 for a, c in pairs(methods)}
        if any(ivs.values()):  # a metric the modality cannot produce (null in every run) gets no table
            out.append(PointStats(p, metric, "seeds and frames" if frames else "seeds", ivs, diffs))
    return out


# ---- files ---------------------------------------------------------------------------------------------


def write_csv(path: Path, axes: Sequence[Axis], rows: Sequence[Row]) -> list[str]:
    """One row per (point, seed, method): swept keys, seed, method, every method metric (the contract's
    columns, in that order), then the run's `status` (complete, or degraded: ..., which a study filters on).
    Returns the header."""
    metrics = metric_columns(rows)
    header = [a.key for a in axes] + ["seed", "method", *metrics, STATUS_COLUMN]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for r in rows:
            w.writerow([*r.point.texts, r.seed, r.method, *("" if r.metrics.get(k) is None else r.metrics[k]
                                                          for k in metrics), r.status])
    return header


def _point_json(axes: Sequence[Axis], p: Point) -> dict[str, Any]:
    return {a.key: a.values[i] for a, i in zip(axes, p.indices, strict=True)}


def sweep_json(meta: dict, axes: Sequence[Axis], rows: Sequence[Row], stats: Sequence[PointStats],
               out: Path, driving: DrivingStudy | None = None) -> dict:
    """sweep.json's document; `driving` (a closed-loop sweep's comparison) adds its "driving" block."""
    doc = dict(meta)
    doc["grid"] = [{"key": a.key, "values": list(a.values), "texts": list(a.texts)} for a in axes]
    doc["methods"] = methods_of(rows)
    doc["rows"] = []
    for r in rows:
        row: dict[str, Any] = {**_point_json(axes, r.point), "seed": r.seed, "method": r.method, **r.metrics,
                               "point": r.point.pid, "run": str(r.run_dir.relative_to(out)), "status": r.status}
        if r.per_frame:
            row["per_frame_iou_vehicle"] = [[f, round(v, 6)] for f, v in sorted(r.per_frame.items())]
        doc["rows"].append(row)
    doc["stats"] = [{"point": _point_json(axes, s.point), "pid": s.point.pid, "metric": s.metric,
                     "resampled": s.level,
                     "methods": {m: iv.to_json() if iv else None for m, iv in s.methods.items()},
                     "differences": [{"a": a, "b": c, **(iv.to_json() if iv else {"mean": None})}
                                     for (a, c), iv in s.differences.items()]}
                    for s in stats]
    if driving is not None:  # only then: an open-loop sweep's document is unchanged
        doc["driving"] = driving.to_json()
    return doc


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def cell(iv: Interval | None, signed: bool = False) -> str:
    """A mean with its interval for a markdown table (signed: a difference, starred when its interval excludes 0)."""
    if iv is None:
        return "-"
    mean = f"{iv.mean:+.3f}" if signed else f"{iv.mean:.3f}"
    if iv.lo is None:
        return f"{mean} (no CI)"
    mark = " **\\***" if signed and iv.excludes_zero else ""
    return f"{mean} [{iv.lo:.3f}, {iv.hi:.3f}]{mark}"


def groups(axes: Sequence[Axis], k: int) -> list[tuple[str, list[tuple[int, ...]]]]:
    """For swept key k: per combination of the other keys' values, a caption and the index tuples of the
    points along key k (the conditional view the tables and plots use)."""
    others = [j for j in range(len(axes)) if j != k]
    out = []
    for combo in itertools.product(*(range(len(axes[j].texts)) for j in others)):
        caption = ", ".join(f"{axes[j].key}={axes[j].texts[i]}" for j, i in zip(others, combo, strict=True))
        idx = []
        for v in range(len(axes[k].texts)):
            full = dict(zip(others, combo, strict=True))
            full[k] = v
            idx.append(tuple(full[j] for j in range(len(axes))))
        out.append((caption, idx))
    return out


def _metric_tables(key: str, entries: Sequence[tuple[str, PointStats | None]], caption: str, metric: str,
                   methods: Sequence[str]) -> list[str]:
    """Two markdown tables for one metric along one key: mean [CI] per method, then the paired differences."""
    got = [s for _, s in entries if s]
    if not got:
        return []
    lines = [f"### {LABELS[metric]}" + (f", at {caption}" if caption else "") + f" (resampled: {got[0].level})", "",
             f"| {key} | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for label, s in entries:
        lines.append(f"| {label} | " + " | ".join(cell(s.methods.get(m)) if s else "-" for m in methods) + " |")
    prs = pairs(methods)
    if prs:
        lines += ["", f"| {key} | " + " | ".join(f"{a} - {b}" for a, b in prs) + " |", "|---|" + "---|" * len(prs)]
        for label, s in entries:
            cells = [cell(s.differences.get(p), signed=True) if s else "-" for p in prs]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def driving_md(d: DrivingStudy) -> list[str]:
    """sweep.md's closed-loop section: per driving measure, every method against none at the same other grid
    values, paired by seed."""
    lines = ["## Driving against none (closed loop)", ""]
    if d.method_axis is None:
        return [*lines, f"{METHOD_KEY} is not swept (one method drives every run): nothing to compare against "
                f"{DRIVING_BASELINE}; sweep.json's `driving.points` has each point's means.", ""]
    if not d.versus:
        return [*lines, f"No {METHOD_KEY} but {DRIVING_BASELINE} has finished runs with a {DRIVING_BASELINE} twin "
                f"(the same values of the other swept keys): nothing to compare.", ""]
    lines += [f"Each run drives one method ({METHOD_KEY}); a method is compared with the {DRIVING_BASELINE} runs at "
              f"the same values of the other swept keys **on the same seeds** (the same traffic). Cells: mean over "
              f"the seeds both have a value for; difference = method - {DRIVING_BASELINE}, paired by seed, "
              f"[{int(100 * LEVEL)}% interval] from a bootstrap over seeds (B = {d.b}, RNG seed {d.rng_seed}, "
              "expanded percentile intervals); **\\*** = the interval excludes 0. A run without a value for a "
              "measure (no conflict met: no TTC; the junction not cleared) leaves that seed out of that measure. "
              "A collision or near miss is 0/1 per run, so its mean is a share of runs.", ""]
    for name in MEASURES:
        lines += [f"### {DRIVING_LABELS[name]}", "",
                  f"| point | method | mean | {DRIVING_BASELINE} | difference [{int(100 * LEVEL)}% CI] | seeds |",
                  "|---|---|---|---|---|---|"]
        for v in d.versus:
            pr = v.measures[name]
            where = ", ".join(f"{k}={t}" for k, t in zip((a.key for a in d.axes), v.point.texts, strict=True)
                              if k != METHOD_KEY) or "-"
            lines.append(f"| {where} | {v.method} | {_num(pr.mean)} | {_num(pr.twin_mean)} | "
                         f"{cell(pr.diff, signed=True)} | {pr.n} |")
        lines.append("")
    return lines


def sweep_md(meta: dict, axes: Sequence[Axis], rows: Sequence[Row], stats: Sequence[PointStats],
             failed: Sequence[dict], pngs: Sequence[str], driving: DrivingStudy | None = None) -> str:
    methods = methods_of(rows)
    lines = [f"# v2vsim sweep: {meta['scenario_name']}", ""]
    seeds = meta["seeds"]
    lines.append(f"Scenario `{meta['scenario']}`; {len(meta['points'])} grid point(s) x {len(seeds)} seed(s) "
                 f"({seeds[0]}-{seeds[-1]}), {meta['frames'] or 'all'} frames per run; overrides: "
                 + (", ".join(f"`{o}`" for o in meta["overrides"]) or "none") + ".")
    runs = meta["runs"]
    degraded = runs.get("degraded", [])
    lines.append(f"Runs: {runs['complete']} complete ({runs['reused']} reused), "
                 + (f"{len(degraded)} degraded, " if degraded else "")
                 + f"{len(failed)} failed" + (", **interrupted**" if meta.get("interrupted") else "") + ".")
    counted = "**counted** in the tables and plots below (--include-degraded)" if runs.get(
        "include_degraded") else "left out of the tables and plots below (--include-degraded counts them)"
    for flagged_only, head in (
            (False, "**Degraded runs** (every frame, but agents lost or a method with no score: not the configured "
                    f"run) are in sweep.csv with their `status`, and {counted}:"),
            (True, "**Runs with a sender flagged** by the misbehaviour check (`defence`): each went as configured "
                   "and is counted in the tables and plots below; the flag is the check's finding:")):
        group = [d for d in degraded if as_configured(d["status"]) == flagged_only]
        if group:
            lines += [head, "", *(f"- {d['point'] or 'no grid'} seed {d['seed']}: {d['status']}" for d in group), ""]
    if runs.get("replayed"):
        lines.append(f"{runs['simulated']} runs simulated, {runs['replayed']} replayed with `v2vsim evaluate` "
                     "from the recording of the same seed at a point that differs only in receiver-side keys "
                     "(bit for bit the runs they stand for); replayed points: "
                     + ", ".join(f"`{p}`" for p in runs["replayed_points"]) + ".")
    bs = meta["bootstrap"]
    lines += ["", f"Cells: mean over seeds [{int(100 * LEVEL)}% interval]: a paired two-level bootstrap (B = "
              f"{bs['b']}, RNG seed {bs['rng_seed']}) resamples seeds, then frames within each seed where per-frame "
              "values exist (the per-frame vehicle IoU each run keeps in its metrics.json); the other metrics are "
              "whole-run values, resampled over seeds. "
              "Percentile intervals, expanded for the number of seeds (Hesterberg's expanded percentile; the plain "
              "one covers ~90% at 10 seeds). Differences are a - b on the same seeds (and frames); **\\*** = the "
              "interval excludes 0. Fewer than 5 seeds: treat the intervals as rough.", ""]
    if len(seeds) < 2:
        lines += ["**One seed**: run-level intervals cannot be estimated (shown as 'no CI'); frame-level "
                  "intervals describe this one traffic realisation only.", ""]
    index = {(s.point.indices, s.metric): s for s in stats}
    for k, axis in enumerate(axes):
        lines += [f"## {axis.key}", ""]
        for caption, idx in groups(axes, k):
            for metric in STAT_METRICS:
                entries = [(axis.texts[i[k]], index.get((i, metric))) for i in idx]
                lines += _metric_tables(axis.key, entries, caption, metric, methods)
    if not axes:  # no --grid: one point
        lines += ["## Results", ""]
        for metric in STAT_METRICS:
            lines += _metric_tables("point", [("(no grid)", index.get(((), metric)))], "", metric, methods)
    if driving is not None:  # only then: an open-loop sweep's report is unchanged
        lines += driving_md(driving)
    other = [c for c in metric_columns(rows) if c not in STAT_METRICS]
    lines += ["## Other metrics (mean over seeds)", "", "| point | method | " + " | ".join(other) + " |",
              "|---|---|" + "---|" * len(other)]
    by: dict[tuple[str, str], list[Row]] = {}
    for r in rows:
        by.setdefault((r.point.pid, r.method), []).append(r)
    for rs in by.values():
        vals = []
        for c in other:
            xs = [float(r.metrics[c]) for r in rs if isinstance(r.metrics.get(c), (int, float))]
            vals.append(_num(float(np.mean(xs))) if xs else "-")
        lines.append(f"| {', '.join(rs[0].point.texts) or '-'} | {rs[0].method} | " + " | ".join(vals) + " |")
    if failed:
        lines += ["", "## Failed runs", ""]
        for f in failed:
            lines.append(f"- {f['point'] or 'no grid'} seed {f['seed']}: {f['why']} (`{f['log']}`)")
    if pngs:
        lines += ["", "## Plots", "", *(f"![{p}]({p})" for p in pngs)]
    lines.append("")
    return "\n".join(lines)


def write_json(path: Path, doc: dict) -> None:
    path.write_text(json.dumps(doc, indent=2, default=str))
