"""`v2vsim bandwidth`: the bandwidth–accuracy curve (Where2comm Fig. 4's axes) from bytes actually encoded.

Fixed policies (every CAV sends the same share of its cells, ranked by its own confidence: 0 = nothing,
1 = the whole map) run in the env (v2vsim.env) over the given seeds; the ego (cavs.ego) fuses with every
method. Per (share, method) the ego's visible-vehicle IoU against the bytes per frame its neighbours put
on the air for it (what a run's bytes_per_frame counts). Intervals: the study bootstrap over seeds
(v2vsim.study.stats). Writes bandwidth.csv (one row per share x seed x method), bandwidth.md and
bandwidth.png.
"""

from __future__ import annotations

import csv
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

from v2vsim.env import parallel_env
from v2vsim.study.stats import interval

COLUMNS = ("fraction", "seed", "method", "iou_vehicle", "bytes_per_frame", "frames")


def parse_fractions(text: str) -> list[float]:
    """'0,0.1,1' -> sorted unique shares in [0, 1]; ValueError saying what is allowed."""
    try:
        vals = sorted({float(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise ValueError(f"--fractions {text!r}: expected comma-separated numbers in [0, 1]") from None
    if not vals or vals[0] < 0 or vals[-1] > 1:
        raise ValueError(f"--fractions {text!r}: expected comma-separated numbers in [0, 1]")
    return vals


def bandwidth_curve(scenario: str, fractions: Sequence[float], seeds: Sequence[int], frames: int,
                    methods: Sequence[str], out: Path, overrides: dict | None = None,
                    log: TextIO = sys.stderr) -> list[dict]:
    """Run every (share, seed) for `frames` frames; write and return the rows."""
    out.mkdir(parents=True, exist_ok=True)
    methods = list(dict.fromkeys([*methods, "none"]))
    env = parallel_env(scenario, features="pooled", receivers="egos", methods=tuple(methods), reward="bytes",
                       **(overrides or {}))
    rows: list[dict] = []
    total, done, t0 = len(fractions) * len(seeds) * frames, 0, time.monotonic()
    try:
        for seed in seeds:
            for frac in fractions:
                env.reset(seed=seed)
                ego = env._receivers()[0]
                received: list[int] = []
                for _ in range(frames):
                    if not env.agents:
                        break
                    _, _, _, _, info = env.step({a: np.array([frac], np.float32) for a in env.agents})
                    received.append(sum(i["bytes"] for a, i in info.items() if a != ego))
                    done += 1
                    rate = done / max(time.monotonic() - t0, 1e-9)
                    print(f"\rv2vsim bandwidth: seed {seed} share {frac:g}: {done}/{total} frames, {rate:.2f} "
                          f"frames/s, ETA {(total - done) / rate:.0f} s   ", end="", file=log, flush=True)
                for m in methods:
                    score = env.scores[ego][m].vehicle
                    rows.append({"fraction": frac, "seed": seed, "method": m, "iou_vehicle": score.iou,
                                 "bytes_per_frame": float(np.mean(received)) if received else 0.0,
                                 "frames": len(received)})
    except KeyboardInterrupt:
        if rows:  # what finished is kept: every (share, seed) written so far
            write_outputs(out, rows, methods)
            print(f"\nv2vsim bandwidth: interrupted; {len(rows) // len(methods)} (share, seed) runs written to {out}",
                  file=log)
        raise
    finally:
        env.close()
        print(file=log)
    write_outputs(out, rows, methods)
    return rows


def summarise(rows: Sequence[dict], methods: Sequence[str]) -> list[dict]:
    """Per (share, method): mean IoU over seeds with its 95% interval, and the mean bytes per frame."""
    out = []
    for frac in sorted({r["fraction"] for r in rows}):
        for m in methods:
            sel = [r for r in rows if r["fraction"] == frac and r["method"] == m and r["iou_vehicle"] is not None]
            if not sel:
                continue
            iv = interval([[r["iou_vehicle"]] for r in sel], label=f"bandwidth:{frac}:{m}")
            out.append({"fraction": frac, "method": m, "iou": iv.mean, "lo": iv.lo, "hi": iv.hi, "seeds": len(sel),
                        "bytes_per_frame": float(np.mean([r["bytes_per_frame"] for r in sel]))})
    return out


def write_outputs(out: Path, rows: Sequence[dict], methods: Sequence[str]) -> None:
    with open(out / "bandwidth.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    summary = summarise(rows, methods)
    fused = [m for m in methods if m != "none"]
    lines = ["# Bandwidth vs accuracy", "",
             "Every CAV sends the same share of its BEV feature cells, ranked by its own vehicle confidence; "
             "bytes are the encoded messages the ego's neighbours sent per frame; vehicle IoU of the ego "
             "(visible vehicles, dataset-level per seed, mean over seeds [95% interval]). `none` fuses nothing.", "",
             "| share | bytes / frame | " + " | ".join(methods) + " |",
             "|---|---|" + "---|" * len(methods)]
    for frac in sorted({s["fraction"] for s in summary}):
        cells = {s["method"]: s for s in summary if s["fraction"] == frac}
        b = next(iter(cells.values()))["bytes_per_frame"]
        row = [f"{frac:g}", f"{b:,.0f}"]
        for m in methods:
            s = cells.get(m)
            row.append("–" if s is None else f"{s['iou']:.3f}" + (
                "" if s["lo"] is None else f" [{s['lo']:.3f}, {s['hi']:.3f}]"))
        lines.append("| " + " | ".join(row) + " |")
    (out / "bandwidth.md").write_text("\n".join(lines) + "\n")
    _plot(out / "bandwidth.png", summary, fused)


def _plot(path: Path, summary: Sequence[dict], methods: Sequence[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    colors = plt.get_cmap("tab10")
    for j, m in enumerate(methods):
        pts = sorted((s for s in summary if s["method"] == m), key=lambda s: s["bytes_per_frame"])
        x = [s["bytes_per_frame"] / 1024 for s in pts]
        ax.plot(x, [s["iou"] for s in pts], marker="o", color=colors(j % 10), label=m)
        lo = [s["lo"] if s["lo"] is not None else s["iou"] for s in pts]
        hi = [s["hi"] if s["hi"] is not None else s["iou"] for s in pts]
        ax.fill_between(x, lo, hi, color=colors(j % 10), alpha=0.12)
        for s in pts:
            ax.annotate(f"{s['fraction']:g}", (s["bytes_per_frame"] / 1024, s["iou"]), fontsize=7,
                        xytext=(3, 3), textcoords="offset points", color=colors(j % 10))
    none = [s["iou"] for s in summary if s["method"] == "none"]
    if none:
        ax.axhline(float(np.mean(none)), color="k", ls="--", lw=1, label="none (no fusion)")
    ax.set_xscale("symlog", linthresh=1.0)
    top = max((s["bytes_per_frame"] for s in summary), default=1024.0) / 1024
    ax.set_xlim(-0.3, max(2.0, top * 1.6))  # 0 bytes (nothing sent) at the left edge, no negative decades
    ax.set_xlabel("KiB per frame sent to the ego (encoded messages; labels: share of cells)")
    ax.set_ylabel("vehicle IoU (visible)")
    ax.set_title("Bandwidth vs accuracy (95% intervals over seeds)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
