"""Sweep plots: per swept key and metric, one line per method with its 95% confidence band.

With several swept keys, each plot has one panel per combination of the other keys' values (the
conditional view: nothing is averaged over another factor, so an interaction stays visible).

A closed-loop sweep also gets sweep_driving_<key>.png per numeric swept key besides control.method: the
share of runs with a collision or near miss and the mean min TTC against that key, one line per method
(a bar chart over the points when there is no such key)."""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from v2vsim.study.driving import EITHER, DrivingStudy, PointDriving
from v2vsim.study.driving import LABELS as DRIVING_LABELS
from v2vsim.study.grid import Axis
from v2vsim.study.stats import Interval
from v2vsim.study.summary import LABELS, PointStats, groups

PLOT_METRICS = ("iou_vehicle", "iou_vehicle_frame_mean", "ap50", "ap70")
MAX_PANELS = 16
DRIVING_PANELS = (EITHER, "min_ttc_s")  # safety: how often it went wrong, and how close it came
MAX_DRIVING_ROWS = 6


def _safe(key: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", key)


def plot_all(out: Path, axes: Sequence[Axis], methods: Sequence[str], stats: Sequence[PointStats],
             scenario: str) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    index = {(s.point.indices, s.metric): s for s in stats}
    colors = plt.get_cmap("tab10")
    paths = []
    for k, axis in enumerate(axes):
        panels = groups(axes, k)[:MAX_PANELS]  # more combinations than this: see sweep.md's tables
        ncol = min(4, len(panels))
        nrow = math.ceil(len(panels) / ncol)
        # numeric values on a numeric axis; anything else (strings, lists, booleans) evenly spaced
        xs = np.asarray(axis.values, dtype=float) if axis.numeric else np.arange(len(axis.texts), dtype=float)
        for metric in PLOT_METRICS:
            if not any(index.get((i, metric)) for _, idx in panels for i in idx):
                continue
            fig, grid = plt.subplots(nrow, ncol, figsize=(4.4 * ncol + 1.6, 3.4 * nrow + 0.6), squeeze=False,
                                     sharey=True)
            level = "seeds"
            for n, (caption, idx) in enumerate(panels):
                ax = grid[n // ncol][n % ncol]
                for j, m in enumerate(methods):
                    mean, lo, hi = [], [], []
                    for i in idx:
                        s = index.get((i, metric))
                        iv = s.methods.get(m) if s else None
                        level = s.level if s else level
                        mean.append(np.nan if iv is None else iv.mean)
                        lo.append(np.nan if iv is None or iv.lo is None else iv.lo)
                        hi.append(np.nan if iv is None or iv.hi is None else iv.hi)
                    c = colors(j % 10)
                    ax.plot(xs, mean, marker="o", lw=1.5, color=c, label=m)
                    ax.fill_between(xs, lo, hi, color=c, alpha=0.18, lw=0)
                ax.set_xlabel(axis.key)
                if not axis.numeric:
                    ax.set_xticks(xs, list(axis.texts), fontsize=8)
                ax.set_ylim(0, 1)
                ax.grid(alpha=0.3)
                if caption:
                    ax.set_title(caption, fontsize=9)
            for n in range(len(panels), nrow * ncol):
                grid[n // ncol][n % ncol].set_visible(False)
            for row in grid:
                row[0].set_ylabel(LABELS[metric])
            grid[0][0].legend(ncol=2, fontsize=8)
            fig.suptitle(f"{scenario}: {LABELS[metric]} vs {axis.key}\nmean and 95% CI over {level}", fontsize=10)
            fig.tight_layout()
            paths.append(out / f"sweep_{_safe(axis.key)}_{metric}.png")
            fig.savefig(paths[-1], dpi=100)
            plt.close(fig)
    return paths


def _bars(iv_list: Sequence[Interval | None]) -> tuple[np.ndarray, np.ndarray]:
    """Means and asymmetric error-bar lengths (2 x n) of intervals, NaN where there is none."""
    mean = np.array([np.nan if iv is None else iv.mean for iv in iv_list])
    lo = np.array([np.nan if iv is None or iv.lo is None else iv.lo for iv in iv_list])
    hi = np.array([np.nan if iv is None or iv.hi is None else iv.hi for iv in iv_list])
    return mean, np.nan_to_num(np.vstack([mean - lo, hi - mean]), nan=0.0)


def plot_driving(out: Path, study: DrivingStudy, scenario: str) -> list[Path]:
    """The closed-loop plots (module doc); [] when no point has a driving value."""
    if not study.points:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    axes = study.axes
    others = [j for j in range(len(axes)) if j != study.method_axis]
    numeric = [j for j in others if axes[j].numeric]
    seeds = max(p.seeds for p in study.points)
    methods = list(dict.fromkeys(p.method for p in study.points))
    colors = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(methods)}
    paths = []
    if not numeric:
        fig, grid = plt.subplots(1, 2, figsize=(max(7.0, 1.1 * len(study.points) + 3), 4.2), squeeze=False)
        labels = [p.method + "".join(f"\n{axes[j].texts[p.point.indices[j]]}" for j in others) for p in study.points]
        for ax, name in zip(grid[0], DRIVING_PANELS, strict=True):
            mean, err = _bars([p.measures.get(name) for p in study.points])
            ax.bar(np.arange(len(labels)), np.nan_to_num(mean), yerr=err, capsize=4,
                   color=[colors[p.method] for p in study.points])
            ax.set_xticks(np.arange(len(labels)), labels, fontsize=8)
            ax.set_ylabel(DRIVING_LABELS[name])
            ax.grid(alpha=0.3, axis="y")
        grid[0][0].set_ylim(0, 1)
        key = axes[study.method_axis].key if study.method_axis is not None else ""
        _driving_figure(fig, f"{scenario}: closed loop, per method", seeds)
        paths.append(out / (f"sweep_driving_{_safe(key)}.png" if key else "sweep_driving.png"))
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
        return paths
    by = {p.point.indices: p for p in study.points}
    for x in numeric:
        rest = [j for j in others if j != x]
        combos = list(itertools.product(*(range(len(axes[j].texts)) for j in rest)))[:MAX_DRIVING_ROWS]
        xs = np.asarray(axes[x].values, dtype=float)
        span = float(np.ptp(xs)) or 1.0
        fig, grid = plt.subplots(len(combos), 2, figsize=(10.5, 3.6 * len(combos) + 0.8), squeeze=False)
        for r, combo in enumerate(combos):
            fixed = dict(zip(rest, combo, strict=True))
            caption = ", ".join(f"{axes[j].key}={axes[j].texts[i]}" for j, i in fixed.items())
            for j, m in enumerate(methods):
                line = [_at(by, x, v, fixed, m) for v in range(len(xs))]
                dodge = (j - (len(methods) - 1) / 2) * 0.012 * span  # error bars side by side, not on top
                for ax, name in zip(grid[r], DRIVING_PANELS, strict=True):
                    mean, err = _bars([p.measures.get(name) if p else None for p in line])
                    if np.isfinite(mean).any():
                        ax.errorbar(xs + dodge, mean, yerr=err, marker="o", lw=1.5, capsize=3, color=colors[m],
                                    label=m)
            for ax, name in zip(grid[r], DRIVING_PANELS, strict=True):
                ax.set_xlabel(axes[x].key)
                ax.set_ylabel(DRIVING_LABELS[name])
                ax.grid(alpha=0.3)
                if caption:
                    ax.set_title(caption, fontsize=9)
            grid[r][0].set_ylim(-0.02, 1.02)
        grid[0][0].legend(ncol=2, fontsize=8)
        _driving_figure(fig, f"{scenario}: closed loop, driving vs {axes[x].key}", seeds)
        paths.append(out / f"sweep_driving_{_safe(axes[x].key)}.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    return paths


def _at(by: dict[tuple[int, ...], PointDriving], x: int, v: int, fixed: dict[int, int],
        method: str) -> PointDriving | None:
    """The point at value v of axis x, with the other non-method axes at `fixed`, that drove `method`."""
    for idx, p in by.items():
        if idx[x] == v and all(idx[j] == i for j, i in fixed.items()) and p.method == method:
            return p
    return None


def _driving_figure(fig: Any, title: str, seeds: int) -> None:
    fig.suptitle(f"{title}\nmean and 95% CI over {seeds} seed(s) (bootstrap over seeds)", fontsize=10)
    fig.tight_layout()
