"""The lying-CAV study in the closed loop (issue 55; docs/results.md "A lying CAV"): per lie and method, what the lie
does to the drive and to the map it drove on, and what the defence buys back, with paired intervals.

Reads a `v2vsim benchmark --profile stress --stress attack,attack_defended` directory: per family, the reference
sweep (oracle and none, which read no message, so no lie reaches them) and the two stressed sweeps (every
cooperative method x the lies, without and with `defence.exclude`). Episodes pair by the family's configuration and
seed, so "attacked - clean" is the same method on the same episode with and without the lie, and "defended -
attacked" the same lie with and without the defence. From each defended run's metrics.json (`defence.senders`): the
liars' frames flagged (true positives) and the honest senders' (false positives, each one excluded from the fusion).

    python scripts/attack_table.py DIR [--families F,G] [--boot 2000] [--csv OUT.csv] [--plot OUT.png]

--plot: per lie, each method's vehicle IoU and collisions attacked and defended (bars), its clean run (a tick) and
`none` (dashed), over every family given pooled.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from v2vsim.study.leaderboard import ALL, BASELINE, ORACLE, Episode, compare, mean_of, pooled, values_of
from v2vsim.study.stats import DEFAULT_B, Interval
from v2vsim.study.stress import level_episodes
from v2vsim.study.summary import cell

KEY = "misbehaviour"
ATTACK, DEFENDED = "attack", "attack_defended"
DEF = "+def"
MEASURES = {"driving_score": "driving score", "collision": "collision rate", "iou_vehicle": "vehicle IoU",
            "close_call": "close-call rate", "safety_score": "safety-weighted score"}
# the paired differences: the lie's cost, what the defence buys back, and where the defended drive ends against the
# honest one (issue 67: a lie that raises the CARLA-style score while causing close calls must show in the safety one)
DIFFS = ("att-clean", "def-att", "def-clean")
Episodes = dict[Episode, dict[str, dict[str, float | None]]]


def lie_text(level: list[dict[str, Any]]) -> str:
    """A lie as a table reads it: `clean`, `cav1 remove_vehicle`, `cav1 scale x8`, `cav1 pose 6 m / 25 deg`."""
    if not level:
        return "clean"
    parts = []
    for lie in level:
        kind = lie["kind"]
        extra = (f" x{lie['factor']:g}" if "factor" in lie else "") + (
            f" {lie['shift_m'][0]:g} m / {lie.get('rotate_deg', 0):g} deg" if "shift_m" in lie else "") + (
            ", evidence consistent" if lie.get("evidence") == "consistent" else "")
        parts.append(f"{'+'.join(lie['cavs'])} {kind}{extra}")
    return "; ".join(parts)


def _levels(doc: dict[str, Any]) -> list[Any]:
    for g in doc["grid"]:
        if g["key"] == KEY:
            return list(g["values"])
    raise SystemExit(f"attack_table: the sweep has no `{KEY}` axis (grid keys: {[g['key'] for g in doc['grid']]})")


def _load(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise SystemExit(f"attack_table: cannot read {path}: {e}") from e


def family_episodes(fam_dir: Path) -> tuple[Episodes, list[Any], dict[tuple[str, int], list[tuple[int, ...]]]]:
    """One family's episodes, the methods named `<method>@<lie index>` (and `...+def` with the defence on; oracle
    and none as they are), the lies, and per (method, lie index) and defended run: the liars' frames flagged and
    compared, the honest senders' frames flagged and compared."""
    ref_dir = fam_dir / "reference" if (fam_dir / "reference").is_dir() else fam_dir / f"reference-{ATTACK}"
    ref, att = _load(ref_dir / "sweep.json"), _load(fam_dir / ATTACK / "sweep.json")
    dfd = _load(fam_dir / DEFENDED / "sweep.json") if (fam_dir / DEFENDED / "sweep.json").is_file() else None
    levels = _levels(att)
    merged: Episodes = {}
    stressed = [(att, "")] + ([(dfd, DEF)] if dfd else [])
    for i, level in enumerate(levels):
        for ep, runs in level_episodes(fam_dir.name, ref, stressed, KEY, level).items():
            for m, v in runs.items():
                name = m if m in (ORACLE, BASELINE) else (m.replace(DEF, "") + f"@{i}" + (DEF if DEF in m else ""))
                merged.setdefault(ep, {})[name] = v
    flagged: dict[tuple[str, int], list[tuple[int, int, int, int]]] = {}
    if dfd:
        index = {json.dumps(lv, sort_keys=True): j for j, lv in enumerate(levels)}
        for row in dfd["rows"]:
            i = index.get(json.dumps(row.get(KEY), sort_keys=True))
            if i is None or row.get("driving_method") in (None, ORACLE, BASELINE):
                continue
            liars = {c for lie in (row.get(KEY) or []) for c in lie["cavs"]}
            mj = fam_dir / DEFENDED / row["run"] / "metrics.json" if row.get("run") else None
            doc = json.loads(mj.read_text()) if mj and mj.is_file() else {}
            senders = (doc.get("defence") or {}).get("senders", {})
            n = [0, 0, 0, 0]  # liars' frames flagged, compared; honest senders' frames flagged, compared
            for c, v in senders.items():
                j = 0 if c in liars else 2
                n[j] += v.get("frames_flagged", 0)
                n[j + 1] += v.get("frames_compared", 0)
            flagged.setdefault((row["driving_method"], i), []).append(tuple(n))
    return merged, levels, flagged


def _f(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def _rate(eps: Episodes, m: str, k: str = "collision") -> str:
    vals = list(values_of(eps, m, k).values())
    return f"{int(sum(vals))}/{len(vals)}" if vals else "-"


def _share(runs: list[tuple[int, ...]] | None, j: int) -> str:
    """Frames flagged / compared over the defended runs (j 0: the liars, 2: the honest senders), and in how many
    runs a sender of that kind was flagged at all."""
    if not runs:
        return "-"
    n, of = sum(r[j] for r in runs), sum(r[j + 1] for r in runs)
    k = sum(r[j] > 0 for r in runs)
    return "-" if not of else f"{n}/{of} ({k} run{'' if k == 1 else 's'})"


def tables(eps: Episodes, levels: list[Any], flagged: dict[tuple[str, int], list[tuple[int, ...]]], scope: str,
           boot: int) -> tuple[list[str], list[list[Any]]]:
    """Markdown lines and CSV rows for one scope."""
    methods = sorted({m.split("@")[0] for runs in eps.values() for m in runs if "@" in m})
    n = len(eps)
    lines = [f"### {scope}: {n} episodes", "",
             "References (read no message, so no lie reaches them): " + ", ".join(
                 f"{m} driving score {_f(mean_of(eps, m, 'driving_score'))}, collisions {_rate(eps, m)}"
                 for m in (ORACLE, BASELINE)) + ".", "",
             "| lie | method | driving score clean / attacked / defended | attacked - clean | defended - attacked "
             "| collisions clean / att. / def. | vehicle IoU clean / att. / def. | IoU attacked - clean "
             "| IoU defended - attacked | liar frames flagged (def.) | honest frames flagged (def.) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    rows: list[list[Any]] = []
    safety: list[str] = []
    for i, level in enumerate(levels):
        for m in methods:
            clean, att, dfd = f"{m}@0", f"{m}@{i}", f"{m}@{i}{DEF}"
            ds = [mean_of(eps, x, "driving_score") for x in (clean, att, dfd)]
            iou = [mean_of(eps, x, "iou_vehicle") for x in (clean, att, dfd)]
            vs: dict[str, Interval | None] = {}
            for k in MEASURES:
                tag = f"attack|{scope}|{i}"
                vs[f"{k}|att-clean"] = compare(eps, att, clean, k, tag, boot).diff if i else None
                vs[f"{k}|def-att"] = compare(eps, dfd, att, k, tag, boot).diff
                vs[f"{k}|def-clean"] = compare(eps, dfd, clean, k, tag, boot).diff if i else None
            fl = flagged.get((m, i))
            lines.append(
                f"| {lie_text(level)} | {m} | {' / '.join(_f(v) for v in ds)} | "
                f"{cell(vs['driving_score|att-clean'], True)} | {cell(vs['driving_score|def-att'], True)} | "
                f"{' / '.join(_rate(eps, x) for x in (clean, att, dfd))} | {' / '.join(_f(v) for v in iou)} | "
                f"{cell(vs['iou_vehicle|att-clean'], True)} | {cell(vs['iou_vehicle|def-att'], True)} | "
                f"{_share(fl, 0)} | {_share(fl, 2)} |")
            safety.append(
                f"| {lie_text(level)} | {m} | {cell(vs['driving_score|def-clean'], True)} | "
                f"{' / '.join(_rate(eps, x, 'close_call') for x in (clean, att, dfd))} | "
                f"{' / '.join(_f(mean_of(eps, x, 'safety_score')) for x in (clean, att, dfd))} | "
                f"{cell(vs['safety_score|att-clean'], True)} | {cell(vs['safety_score|def-clean'], True)} |")
            for k in MEASURES:
                for which in DIFFS:
                    iv = vs[f"{k}|{which}"]
                    rows.append([scope, lie_text(level), m, k, which,
                                 *(["", "", ""] if iv is None else [round(iv.mean, 6), iv.lo, iv.hi])])
    lines += ["", f"The drive against the honest one, {scope} (close call: no collision, yet SSM's minimum TTC under "
              "1.5 s, a PET under 1 s or the footprints within 1 m; the safety-weighted score costs a close call "
              "as v2vsim/control/score.py states):", "",
              "| lie | method | driving score defended - clean | close calls clean / att. / def. "
              "| safety-weighted score clean / att. / def. | safety attacked - clean | safety defended - clean |",
              "|---|---|---|---|---|---|---|", *safety]
    lines.append("")
    return lines, rows


def plot(path: Path, eps: Episodes, levels: list[Any], title: str) -> None:
    """Per lie (x), per method: attacked and defended bars of vehicle IoU and of collisions, the clean run's value as
    a black tick over each pair, `none` dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = sorted({m.split("@")[0] for runs in eps.values() for m in runs if "@" in m})
    n = len(eps)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    width = 0.8 / (2 * len(methods))
    xs = np.arange(len(levels))
    for ax, k in zip(axes, ("iou_vehicle", "collision"), strict=True):
        def value(m: str, measure: str = k) -> float:
            v = mean_of(eps, m, measure)
            return np.nan if v is None else (v * n if measure == "collision" else v)

        for j, m in enumerate(methods):
            for h, (suffix, label, hatch) in enumerate((("", "attacked", ""), (DEF, "defended", "//"))):
                off = (2 * j + h - len(methods) + 0.5) * width
                bars = ax.bar(xs + off, [value(f"{m}@{i}{suffix}") for i in range(len(levels))], width,
                              color=f"C{j}", alpha=0.9 if not h else 0.5, hatch=hatch, label=f"{m} {label}")
                ax.plot([b.get_x() + b.get_width() / 2 for b in bars], [value(f"{m}@0")] * len(levels), "k_",
                        markersize=10, label="the method's clean run" if j == 0 and h == 0 else None)
        ax.axhline(value(BASELINE), color="black", linestyle="--", linewidth=1, label="none")
        ax.set_xticks(xs, [textwrap.fill(lie_text(lv), 16) for lv in levels], fontsize=8)
        ax.set_ylabel("vehicle IoU of the map driven on" if k == "iou_vehicle" else f"collisions (of {n} episodes)")
    axes[0].legend(fontsize=7, ncol=2, loc="lower left")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path, help="the benchmark's --out directory")
    ap.add_argument("--families", help="comma-separated (default: every family with an attack sweep)")
    ap.add_argument("--boot", type=int, default=DEFAULT_B)
    ap.add_argument("--csv", type=Path, help="also write the intervals here")
    ap.add_argument("--plot", type=Path, help="also draw the study here (PNG)")
    a = ap.parse_args(argv)
    fams = sorted(p.parent.parent for p in (a.dir / "families").glob(f"*/{ATTACK}/sweep.json"))
    if a.families:
        want = set(a.families.split(","))
        fams = [f for f in fams if f.name in want]
    if not fams:
        print(f"attack_table: no {a.dir}/families/*/{ATTACK}/sweep.json", file=sys.stderr)
        return 2
    per_family, levels = {}, None
    flagged_all: dict[tuple[str, int], list[tuple[int, ...]]] = {}
    out: list[str] = []
    rows: list[list[Any]] = []
    for f in fams:
        eps, lv, flagged = family_episodes(f)
        per_family[f.name] = eps
        levels = levels or lv
        for k, v in flagged.items():
            flagged_all.setdefault(k, []).extend(v)
        md, r = tables(eps, lv, flagged, f.name, a.boot)
        out += md
        rows += r
    if len(fams) > 1:
        md, r = tables(pooled(per_family), levels, flagged_all, ALL, a.boot)
        out += md
        rows += r
    print("\n".join(out))
    if a.plot:
        everything = pooled(per_family) if len(fams) > 1 else per_family[fams[0].name]
        plot(a.plot, everything, levels or [], f"a lying CAV in the closed loop: {', '.join(f.name for f in fams)}, "
             f"{len(everything)} episodes")
    if a.csv:
        with a.csv.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["scope", "lie", "method", "measure", "difference", "mean", "lo", "hi"])
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
