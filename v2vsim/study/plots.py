"""Sweep plots: per swept key and metric, one line per method with its 95% confidence band.

With several swept keys, each plot has one panel per combination of the other keys' values (the
conditional view: nothing is averaged over another factor, so an interaction stays visible)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from v2vsim.study.grid import Axis
from v2vsim.study.summary import LABELS, PointStats, groups

PLOT_METRICS = ("iou_vehicle", "iou_vehicle_frame_mean", "ap50", "ap70")
MAX_PANELS = 16


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
