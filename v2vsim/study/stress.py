"""Where cooperation stops helping (`v2vsim benchmark --stress latency,...`, docs/benchmark.md "Stress"): the
catalogue's families driven with the channel degraded step by step along one axis (latency, Bernoulli loss, burst
loss, pose error, the share of connected vehicles, a lying CAV), every cooperative method against `none`, and each
method's breaking point.

    DIR/families/<family>/reference/       oracle and none, once per episode: neither reads a message, so no level
                                           of any stress can change their drive (measured: docs/benchmark.md);
                                           reference-<stress>/ for a stress with overrides of its own (`set`, e.g.
                                           the age limit for latency), run with them
    DIR/families/<family>/<stress>/        every cooperative method x the stress's levels
    DIR/families/<family>/<stress>+comp/   the methods that have compensation (late fusion's model-free one, and
                                           those whose zoo ships an extrapolation module) x the levels, with
                                           comm.compensation on; reported as "<method>+comp"
    DIR/breaking_points.md|csv|json        per stress, method and scope (family, overall): the curves and the
                                           breaking points, driving and perception side by side
    DIR/stress_<stress>.png                driving score, success and vehicle IoU against the level, one line per
                                           method; with several families also stress_<stress>_<family>.png

A method's breaking point on a stress, for a measure, is the mildest level at which its paired 95 % interval against
`none` (the same episodes) no longer lies above 0: from there on the data no longer show that cooperation helps.
`None` when it never does within the levels run; the first level when it never showed a gain at all. Beside it,
the first level whose driving interval lies wholly below 0 (`harm_index`: cooperation doing harm). Levels are
listed mildest first; x rises along them, or falls for an axis that grows harsher downwards (penetration).
"""

from __future__ import annotations

import csv
import json
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from v2vsim.study.catalogue import Stress
from v2vsim.study.leaderboard import (
    ALL,
    BASELINE,
    ORACLE,
    Episode,
    Versus,
    compare,
    driven_note,
    episodes_of,
    mean_of,
    pooled,
)
from v2vsim.study.stats import DEFAULT_B, Interval
from v2vsim.study.summary import cell

REFERENCE = "reference"
COMP = "+comp"
CURVE_MEASURES = {"driving_score": "driving score", "iou_vehicle": "vehicle IoU", "ap50": "AP@0.5",
                  "success": "success rate", "collision": "collision rate"}
BREAKING = ("driving_score", "iou_vehicle", "ap50")  # the measures a breaking point is given for

Episodes = dict[Episode, dict[str, dict[str, float | None]]]


@dataclass(frozen=True)
class BreakingPoint:
    method: str
    stress: str
    scope: str  # a family, or "overall"
    measure: str
    index: int | None  # the level's index (None: never broke within the levels run)
    diff: Interval | None  # method - none at that level (at the last level when it never broke)

    def text(self, s: Stress) -> str:
        if self.diff is not None and self.diff.lo is None:
            return "- (no interval: one episode)"
        if self.index is None:  # it held even at the harshest level, the last (x falls along a harsher-down axis)
            return f"{'<' if s.x[-1] < s.x[0] else '>'} {_num(s.x[-1])} (never)"
        return f"{_num(s.x[self.index])}" + (" (no gain at the mildest)" if self.index == 0 else "")


def _num(v: float) -> str:
    return f"{v:g}"


def breaking_index(diffs: Sequence[Interval | None]) -> int | None:
    """The first level whose interval (method - none, levels mildest first) does not lie above 0; a level without
    data is skipped; None when every level's does."""
    for i, iv in enumerate(diffs):
        if iv is None:
            continue
        if iv.lo is None or iv.lo <= 0:
            return i
    return None


def harm_index(diffs: Sequence[Interval | None]) -> int | None:
    """The first level whose interval (method - none, levels mildest first) lies wholly below 0: from there on the
    data show cooperation doing harm; None when no level's does."""
    for i, iv in enumerate(diffs):
        if iv is not None and iv.hi is not None and iv.hi < 0:
            return i
    return None


def reference_of(s: Stress) -> str:
    """The folder of the oracle and none runs a stress is compared with (module doc)."""
    return f"{REFERENCE}-{s.name}" if s.sets else REFERENCE


def compensable(scenario: Path, methods: Sequence[str], overrides: Sequence[str] = ()) -> list[str]:
    """Of `methods`, those comm.compensation changes: late fusion (model-free) and every method whose zoo ships an
    extrapolation module (docs/run.md "Time at the receiver")."""
    from v2vsim.config import load_scenario
    from v2vsim.perception.plan import plan_models

    learned = set(plan_models(load_scenario(scenario, list(overrides))).extrapolation)
    return [m for m in methods if m == "late" or m in learned]


def _key(v: Any) -> str:
    return json.dumps(v, sort_keys=True)


def level_episodes(family: str, reference: dict[str, Any], stressed: Sequence[tuple[dict[str, Any], str]],
                   key: str, level: Any) -> Episodes:
    """One family's episodes at one level: the reference sweep's oracle and none runs, and every stressed sweep's
    runs at that level (their methods suffixed as given: "" or "+comp"), paired by the family's configuration and
    seed."""
    rows = list(reference["rows"])
    want = _key(level)
    for doc, suffix in stressed:
        for row in doc["rows"]:
            if _key(row.get(key)) == want and row.get("driving_method") not in (None, ORACLE, BASELINE):
                rows.append({**row, "driving_method": row["driving_method"] + suffix})
    return episodes_of(family, {"grid": reference["grid"], "rows": rows})


def study_levels(s: Stress, families: Sequence[str], docs: dict[str, dict[str, Any]]) -> list[dict[str, Episodes]]:
    """Per level of `s`, each family's episodes, from the study's sweep documents (sweep.json by the names
    v2vsim.study.benchmark.family_sweeps gives them: family/reference, family/<stress>, family/<stress>+comp)."""
    out = []
    for v in s.level.values:
        per = {}
        for f in families:
            stressed = [(docs[n], suffix) for suffix in ("", COMP) if (n := f"{f}/{s.name}{suffix}") in docs]
            per[f] = level_episodes(f, docs[f"{f}/{reference_of(s)}"], stressed, s.level.key, v)
        out.append(per)
    return out


@dataclass(frozen=True)
class Curve:
    """One method along one stress in one scope: per level, its difference from `none` per measure."""

    method: str
    stress: str
    scope: str
    diffs: dict[str, tuple[Versus, ...]]  # measure -> per level
    means: dict[str, tuple[float | None, ...]]  # measure -> per level, the method's own mean

    def harm(self, measure: str = "driving_score") -> int | None:
        """The level index from which the method does worse than `none` (harm_index), or None."""
        return harm_index([v.diff for v in self.diffs[measure]])

    def breaking(self, measure: str) -> BreakingPoint:
        vs = self.diffs[measure]
        i = breaking_index([v.diff for v in vs])
        at = vs[i] if i is not None else (vs[-1] if vs else None)
        return BreakingPoint(self.method, self.stress, self.scope, measure, i, at.diff if at else None)


def curves(s: Stress, levels: Sequence[dict[str, Episodes]], boot: int = DEFAULT_B) -> list[Curve]:
    """Per scope (each family, then overall: every family's episodes pooled) and method, the curves of one stress.
    `levels[i]`: family -> its episodes at level i."""
    scopes = list(levels[0]) + [ALL] if levels else []
    out = []
    for scope in scopes:
        per_level = [in_scope(lv, scope) for lv in levels]
        methods = list(dict.fromkeys(m for eps in per_level for runs in eps.values() for m in runs
                                     if m not in (ORACLE, BASELINE)))
        # one family: "overall" is that family's episodes, so it takes the same bootstrap draws (the same intervals)
        tag = scopes[0] if scope == ALL and len(scopes) == 2 else scope
        for m in methods:
            diffs = {k: tuple(compare(eps, m, BASELINE, k, f"{s.name}|{i}|{tag}", boot)
                              for i, eps in enumerate(per_level)) for k in CURVE_MEASURES}
            means = {k: tuple(mean_of(eps, m, k) for eps in per_level) for k in CURVE_MEASURES}
            out.append(Curve(m, s.name, scope, diffs, means))
    return out


def in_scope(level: dict[str, Episodes], scope: str) -> Episodes:
    """One level's episodes of a family, or of every family pooled (scope "overall")."""
    return pooled(level) if scope == ALL else level.get(scope, {})


def breaking_md(stresses: Sequence[Stress], by_stress: dict[str, list[Curve]], meta: dict[str, Any]) -> str:
    lines = ["# v2vsim closed-loop benchmark: where cooperation stops helping", "",
             f"Catalogue `{meta['catalogue']}`, profile `{meta['profile']}`, {meta['split']} seeds {meta['seeds']}. "
             "A breaking point is the mildest level at which the method's paired 95 % interval against `none` (same "
             "episodes) no longer lies above 0; `> x (never)`: it held at every level run; `(no gain at the "
             "mildest)`: the data never showed a gain; `worse than none from`: the mildest level whose interval "
             "lies wholly below 0. Driving: the driving score; perception: vehicle IoU and AP@0.5 of the map it "
             "drove on, from the same runs."
             + driven_note(meta), ""]
    for s in stresses:
        cs = by_stress.get(s.name, [])
        lines += [f"## {s.name}: {s.level.key} ({s.unit}), levels {', '.join(_num(x) for x in s.x)}", "",
                  "| scope | method | driving breaks at | its score - none there | driving worse than none from | "
                  "IoU breaks at | AP@0.5 breaks at |", "|---|---|---|---|---|---|---|"]
        for c in sorted(cs, key=lambda c: (c.scope == ALL, c.scope, c.method), reverse=False):
            d, iou, ap = (c.breaking(k) for k in BREAKING)
            h = c.harm()
            harm = "-" if h is None else f"{_num(s.x[h])}: {cell(c.diffs['driving_score'][h].diff, True)}"
            lines.append(f"| {c.scope} | {c.method} | {d.text(s)} | {cell(d.diff, True)} | {harm} | {iou.text(s)} | "
                         f"{ap.text(s)} |")
        lines += ["", f"Overall, driving score - none per level ({', '.join(_num(x) for x in s.x)} {s.unit}):", "",
                  "| method | " + " | ".join(_num(x) for x in s.x) + " |", "|---|" + "---|" * len(s.x)]
        for c in cs:
            if c.scope == ALL:
                lines.append(f"| {c.method} | " + " | ".join(cell(v.diff, True) for v in c.diffs["driving_score"])
                             + " |")
        lines.append("")
    return "\n".join(lines)


def write_csv(path: Path, stresses: Sequence[Stress], by_stress: dict[str, list[Curve]]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["stress", "scope", "method", "level", "x", "measure", "method_mean", "minus_none",
                    "minus_none_lo", "minus_none_hi", "episodes", "breaking_x"])
        for s in stresses:
            for c in by_stress.get(s.name, []):
                for k in CURVE_MEASURES:
                    bp = c.breaking(k) if k in BREAKING else None
                    brk = "" if bp is None or bp.index is None else s.x[bp.index]
                    for i, v in enumerate(c.diffs[k]):
                        iv = v.diff
                        w.writerow([s.name, c.scope, c.method, s.level.texts[i], s.x[i], k,
                                    "" if c.means[k][i] is None else round(c.means[k][i], 6),  # type: ignore[arg-type]
                                    "" if iv is None else round(iv.mean, 6),
                                    "" if iv is None or iv.lo is None else round(iv.lo, 6),
                                    "" if iv is None or iv.hi is None else round(iv.hi, 6), v.n, brk])


def to_json(stresses: Sequence[Stress], by_stress: dict[str, list[Curve]], meta: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {**meta, "stresses": []}
    for s in stresses:
        entry: dict[str, Any] = {"name": s.name, "key": s.level.key, "levels": list(s.level.values), "x": list(s.x),
                                 "unit": s.unit, "curves": []}
        for c in by_stress.get(s.name, []):
            entry["curves"].append({
                "method": c.method, "scope": c.scope,
                "breaking": {k: {"index": (bp := c.breaking(k)).index,
                                 "x": None if bp.index is None else s.x[bp.index],
                                 "diff": bp.diff.to_json() if bp.diff else None} for k in BREAKING},
                "worse_than_none_from": None if (h := c.harm()) is None else {"index": h, "x": s.x[h]},
                "levels": [{"x": s.x[i], **{k: {"mean": c.means[k][i], "n": c.diffs[k][i].n,
                                                "minus_none": c.diffs[k][i].diff.to_json() if c.diffs[k][i].diff
                                                else None} for k in CURVE_MEASURES}}
                           for i in range(len(s.x))]})
        out["stresses"].append(entry)
    return out


def plot(out: Path, s: Stress, cs: Sequence[Curve], none_means: dict[str, float | None], scope: str = ALL) -> Path:
    """stress_<name>.png (overall; stress_<name>_<family>.png for one family): driving score, success rate and
    vehicle IoU against the level, one line per method with its interval (that of method - none, placed on the
    method's mean), none's mean dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [c for c in cs if c.scope == scope]
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    for ax, k in zip(axes, ("driving_score", "success", "iou_vehicle"), strict=True):
        base = none_means.get(k)
        for c in shown:
            xs, ys, lo, hi = [], [], [], []
            for x, v, mean in zip(s.x, c.diffs[k], c.means[k], strict=True):
                if mean is None or v.diff is None:
                    continue
                xs.append(x)
                ys.append(mean)
                ref = mean - v.diff.mean  # none's mean on the same episodes
                # shown within the measure's range [0, 1]: none's mean plus the difference's bound can pass it
                lo.append(max(0.0, ref + v.diff.lo) if v.diff.lo is not None else mean)
                hi.append(min(1.0, ref + v.diff.hi) if v.diff.hi is not None else mean)
            if xs:
                line = ax.plot(xs, ys, marker="o", label=c.method)[0]
                ax.fill_between(xs, lo, hi, color=line.get_color(), alpha=0.12)
        if base is not None:
            ax.axhline(base, color="black", linestyle="--", linewidth=1, label="none")
        ax.set_xlabel(textwrap.fill(f"{s.name} ({s.unit})", 48), fontsize=8)
        ax.set_ylabel(textwrap.fill(f"{CURVE_MEASURES[k]} (95 % CI of the difference from none)", 36), fontsize=8)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"where cooperation stops helping: {s.name}" + ("" if scope == ALL else f", {scope}"))
    fig.tight_layout()
    path = out / (f"stress_{s.name}.png" if scope == ALL else f"stress_{s.name}_{scope}.png")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_stress(out: Path, stresses: Sequence[Stress], levels: dict[str, list[dict[str, Episodes]]],
                 meta: dict[str, Any], boot: int = DEFAULT_B) -> list[Path]:
    """breaking_points.md/csv/json and one plot per stress from `levels`: stress -> per level, family -> episodes."""
    by_stress = {s.name: curves(s, levels[s.name], boot) for s in stresses if s.name in levels}
    paths = [out / "breaking_points.md", out / "breaking_points.csv", out / "breaking_points.json"]
    paths[0].write_text(breaking_md(stresses, by_stress, meta))
    write_csv(paths[1], stresses, by_stress)
    paths[2].write_text(json.dumps(to_json(stresses, by_stress, meta), indent=1))
    for s in stresses:
        if s.name not in by_stress:
            continue
        families = list(levels[s.name][0]) if levels[s.name] else []
        # overall, and with several families each one's own (pooled curves hide where a family differs)
        for scope in [ALL, *families] if len(families) > 1 else [ALL]:
            nm = {k: mean_of(in_scope(levels[s.name][0], scope), BASELINE, k) for k in CURVE_MEASURES}
            paths.append(plot(out, s, by_stress[s.name], nm, scope))
    return paths
