"""The benchmark's leaderboard: every method's driving score, success, collision rate and efficiency per family and
overall, each against `none` and between every pair of methods with paired 95 % intervals (docs/benchmark.md).

The unit is an episode: one (family, configuration, seed), which every method drove in the same traffic (the same
seed and configuration: a paired design). A method's figure is its mean over episodes; a comparison is the mean of
the per-episode differences, with the expanded percentile bootstrap interval over episodes that the sweep uses
(v2vsim.study.stats.interval, each episode a one-value cluster). Overall pools every family's episodes. A pair whose
interval holds 0 gets a power estimate: the episodes a two-sided paired test at 5 % would need to separate it with
80 % power, were the measured mean difference and its spread the true ones.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from statistics import NormalDist
from typing import Any

import numpy as np

from v2vsim.control.score import close_call, safety_score
from v2vsim.evaluation.status import as_configured
from v2vsim.study.stats import DEFAULT_B, DEFAULT_RNG_SEED, Interval, interval
from v2vsim.study.summary import cell

ORACLE, BASELINE = "oracle", "none"
# measure -> (label, what a run's sweep row holds); efficiency is derived from finished_at_s (below)
MEASURES = {"driving_score": "driving score", "success": "success rate", "collision": "collision rate",
            "route_completion": "route completion", "efficiency": "efficiency", "iou_vehicle": "vehicle IoU",
            # a serious conflict without contact, and the score with its penalty (v2vsim/control/score.py)
            "close_call": "close-call rate", "safety_score": "safety-weighted score",
            # the critical-actor measure (v2vsim/control/critical.py) of the ego: detected before the conflict (0/1),
            # its lead time with a miss counted as 0 s, and the share of frames it stayed detected (detected only)
            "critical_detected": "critical actor detected", "critical_lead_s": "critical lead time (s)",
            "critical_share": "critical actor held"}
# what may predict a run's success (predictors_md): the map-wide measures beside the critical actor's
PREDICTORS = ("iou_vehicle", "ap50", "critical_detected", "critical_lead_s", "critical_share")
# the measures compared pairwise
RANKED = ("driving_score", "success", "collision", "efficiency", "close_call", "safety_score")
ALL = "overall"


@dataclass(frozen=True)
class Episode:
    family: str
    config: str  # the family's grid values, e.g. "arrival_offset_s=[1, 1], speed_mps=11"
    seed: int


def episodes_of(family: str, doc: dict[str, Any]) -> dict[Episode, dict[str, dict[str, float | None]]]:
    """episode -> method -> measure -> value from a family sweep's sweep.json (runs that went as configured only,
    as the sweep counts them); the oracle's efficiency is 1, another method's the oracle's finish time over its own."""
    keys = [g["key"] for g in doc["grid"] if g["key"] != "control.method"]
    out: dict[Episode, dict[str, dict[str, float | None]]] = {}
    for row in doc["rows"]:
        m = row.get("driving_method")
        if m is None or not as_configured(row.get("status")):
            continue
        ep = Episode(family, ", ".join(f"{k.rsplit('.', 1)[-1]}={_text(row.get(k))}" for k in keys), int(row["seed"]))
        coll = row.get("driving_collisions")
        out.setdefault(ep, {})[m] = {
            "driving_score": _num(row.get("driving_driving_score")),
            "success": _num(row.get("driving_success")),
            "collision": None if coll is None else float(coll > 0),
            "route_completion": _num(row.get("driving_route_completion")),
            "finished_at_s": _num(row.get("driving_finished_at_s")),
            # the map it drove on (oracle drove on ground truth; its row scores `none`, which it did not use)
            "iou_vehicle": None if m == ORACLE else _num(row.get("iou_vehicle")),
            "ap50": None if m == ORACLE else _num(row.get("ap50")),
            **_critical(row),
            **_safety(row),
        }
    for runs in out.values():
        ref = (runs.get(ORACLE) or {}).get("finished_at_s")
        for m, v in runs.items():
            mine = v["finished_at_s"]
            v["efficiency"] = (ref / mine if ref is not None and mine else None) if m != ORACLE else (
                1.0 if mine is not None else None)
    return out


def _safety(row: dict[str, Any]) -> dict[str, float | None]:
    """A run's close call (0/1) and safety-weighted score from its sweep row. A run from before metrics.json had
    them (the fields absent) gets them from the same row's SSM and gap figures by the same definition, exact for
    one driven vehicle (the row's figures are the fleet's extremes)."""
    score, coll = _num(row.get("driving_driving_score")), _num(row.get("driving_collisions"))
    if "driving_close_calls" in row:
        calls = _num(row.get("driving_close_calls"))
        return {"close_call": None if calls is None else float(calls > 0),
                "safety_score": _num(row.get("driving_safety_score"))}
    if coll is None:
        return {"close_call": None, "safety_score": None}
    close = close_call(int(coll), (_num(row.get("driving_near_misses")) or 0) > 0, _num(row.get("driving_min_ttc_s")),
                       (_num(row.get("driving_min_pet_s")), _num(row.get("driving_pet_s"))))
    return {"close_call": float(close), "safety_score": safety_score(score, close)}


def _critical(row: dict[str, Any]) -> dict[str, float | None]:
    """The ego's critical-actor figures from a sweep row (None where the family has no critical actor)."""
    missed = row.get("driving_critical_missed")
    if missed is None or (isinstance(missed, float) and math.isnan(missed)):
        return {"critical_detected": None, "critical_lead_s": None, "critical_share": None}
    detected = not bool(missed)
    return {"critical_detected": float(detected),
            "critical_lead_s": (_num(row.get("driving_critical_lead_time_s")) or 0.0) if detected else 0.0,
            "critical_share": _num(row.get("driving_critical_detected_share")) if detected else None}


def auc(values: Sequence[float], success: Sequence[bool]) -> float | None:
    """The probability that a successful run's value exceeds a failed run's (ties count half): 0.5 is no better
    than chance, 1 a perfect predictor (the Mann-Whitney U statistic over the two groups' sizes)."""
    won = [v for v, s in zip(values, success, strict=True) if s]
    lost = [v for v, s in zip(values, success, strict=True) if not s]
    if not won or not lost:
        return None
    a, b = np.asarray(won)[:, None], np.asarray(lost)[None, :]
    return float(((a > b).sum() + 0.5 * (a == b).sum()) / (len(won) * len(lost)))


def predictors_md(eps: dict[Episode, dict[str, dict[str, float | None]]]) -> list[str]:
    """How well each perception measure of the map a method drove on predicts the run's success, over every
    (episode, method) run but the oracle's: AUC, and the runs it is measured on."""
    lines = ["| measure | runs | AUC for success |", "|---|---|---|"]
    for k in PREDICTORS:
        pairs = [(v[k], bool(v["success"])) for runs in eps.values() for m, v in runs.items()
                 if m != ORACLE and v.get(k) is not None and v.get("success") is not None]
        score = auc([p[0] for p in pairs], [p[1] for p in pairs]) if pairs else None
        lines.append(f"| {MEASURES.get(k, k)} | {len(pairs)} | {'-' if score is None else f'{score:.3f}'} |")
    return lines


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not (isinstance(v, float) and math.isnan(v)) else None


def _text(v: Any) -> str:
    return json.dumps(v) if isinstance(v, list) else str(v)


@dataclass(frozen=True)
class Versus:
    a: str
    b: str
    measure: str
    n: int
    diff: Interval | None
    needed: int | None  # episodes a paired test would need (None: separated, or no difference to find)


def values_of(eps: dict[Episode, dict[str, dict[str, float | None]]], method: str, measure: str
              ) -> dict[Episode, float]:
    return {e: v for e, runs in eps.items() if (v := (runs.get(method) or {}).get(measure)) is not None}


def mean_of(eps: dict[Episode, dict[str, dict[str, float | None]]], method: str, measure: str) -> float | None:
    """The method's mean of the measure over the episodes it has it for (None: none)."""
    vals = list(values_of(eps, method, measure).values())
    return float(np.mean(vals)) if vals else None


def needed_episodes(diffs: Sequence[float], level: float = 0.95, power: float = 0.8) -> int | None:
    """Episodes a two-sided paired test at 1 - level would need for `power` against the measured mean difference,
    with the measured spread: n = ((z_a + z_b) sd / |mean|)^2; None when the mean difference is 0."""
    if len(diffs) < 2:
        return None
    mean, sd = float(np.mean(diffs)), float(np.std(diffs, ddof=1))
    if mean == 0.0:
        return None
    z = NormalDist().inv_cdf(1 - (1 - level) / 2) + NormalDist().inv_cdf(power)
    return max(2, math.ceil((z * sd / abs(mean)) ** 2))


def compare(eps: dict[Episode, dict[str, dict[str, float | None]]], a: str, b: str, measure: str, scope: str,
            boot: int = DEFAULT_B) -> Versus:
    """a - b on the episodes both have the measure for."""
    va, vb = values_of(eps, a, measure), values_of(eps, b, measure)
    common = sorted(set(va) & set(vb), key=lambda e: (e.family, e.config, e.seed))
    diffs = [va[e] - vb[e] for e in common]
    iv = interval([[d] for d in diffs], boot, f"leaderboard|{scope}|{measure}|{a}-{b}", DEFAULT_RNG_SEED)
    needed = None if iv is None or iv.excludes_zero else needed_episodes(diffs)
    return Versus(a, b, measure, len(common), iv, needed)


@dataclass(frozen=True)
class Board:
    scope: str  # a family's name, or "overall"
    episodes: int
    alone: dict[str, dict[str, Interval | None]]  # method -> measure -> mean over its episodes
    versus_none: dict[str, dict[str, Versus]]  # method -> measure -> method - none
    pairs: tuple[Versus, ...]  # every pair of methods, a ranked above b by driving score; RANKED measures


def board(scope: str, eps: dict[Episode, dict[str, dict[str, float | None]]], methods: Sequence[str],
          boot: int = DEFAULT_B) -> Board:
    present = [m for m in methods if any(m in runs for runs in eps.values())]
    alone = {m: {k: interval([[v] for v in values_of(eps, m, k).values()], boot, f"leaderboard|{scope}|{k}|{m}",
                             DEFAULT_RNG_SEED) for k in MEASURES} for m in present}
    versus = {m: {k: compare(eps, m, BASELINE, k, scope, boot) for k in MEASURES} for m in present if m != BASELINE}
    ranked = sorted(present, key=lambda m: -(alone[m]["driving_score"].mean if alone[m]["driving_score"] else -1.0))
    pairs = tuple(compare(eps, a, b, k, scope, boot) for i, a in enumerate(ranked) for b in ranked[i + 1:]
                  for k in RANKED)
    return Board(scope, len(eps), alone, versus, pairs)


def boards(per_family: dict[str, dict[Episode, dict[str, dict[str, float | None]]]], methods: Sequence[str],
           boot: int = DEFAULT_B) -> list[Board]:
    """One board per family, then the overall one (every episode pooled)."""
    out = [board(f, eps, methods, boot) for f, eps in per_family.items()]
    return out + [board(ALL, pooled(per_family), methods, boot)]


def pooled(per_family: dict[str, dict[Episode, dict[str, dict[str, float | None]]]]
           ) -> dict[Episode, dict[str, dict[str, float | None]]]:
    """Every family's episodes in one mapping (the overall scope)."""
    return {e: runs for eps in per_family.values() for e, runs in eps.items()}


def config_table(eps: dict[Episode, dict[str, dict[str, float | None]]], methods: Sequence[str]) -> list[str]:
    """Per configuration of a family: each method's success and collision rates over its seeds (success /
    collision), the grid a calibration reads (docs/benchmark.md "Calibration")."""
    present = [m for m in methods if any(m in runs for runs in eps.values())]
    configs = list(dict.fromkeys(e.config for e in eps))  # the grid's order, as the sweep's rows come
    lines = ["| configuration | seeds | " + " | ".join(present) + " |", "|---|---|" + "---|" * len(present)]
    for c in configs:
        mine = {e: runs for e, runs in eps.items() if e.config == c}
        cells = []
        for m in present:
            s = [v for runs in mine.values() if (v := (runs.get(m) or {}).get("success")) is not None]
            k = [v for runs in mine.values() if (v := (runs.get(m) or {}).get("collision")) is not None]
            cells.append(f"{np.mean(s):.2f} / {np.mean(k):.2f}" if s and k else "-")
        lines.append(f"| {c} | {len(mine)} | " + " | ".join(cells) + " |")
    return lines


def driven_note(meta: dict[str, Any]) -> str:
    """A sentence for a study's header when more than the ego drove (--driven, v2vsim.study.benchmark): what its
    scores then measure; "" for the ego alone."""
    who = {"sees": "the ego and each family's CAVs that see the hidden actor", "all": "every CAV"}.get(
        meta.get("driven", ""))
    return (f" Driven: {who}; every score is the fleet's (the mean over the driven vehicles; a success only when "
            "every one succeeded).") if who else ""


def leaderboard_md(bs: Sequence[Board], meta: dict[str, Any],
                   per_family: dict[str, dict[Episode, dict[str, dict[str, float | None]]]] | None = None) -> str:
    lines = ["# v2vsim closed-loop benchmark: leaderboard", "",
             f"Catalogue `{meta['catalogue']}`, profile `{meta['profile']}`, {meta['split']} seeds "
             f"{meta['seeds']}; methods ranked by mean driving score (overall). An episode is one (family, "
             "configuration, seed); every method drove the same episodes. Intervals: 95 % paired bootstrap over "
             "episodes (expanded percentile); * marks a difference whose interval excludes 0. A close call: no "
             "collision, yet SSM's min TTC under 1.5 s, a post-encroachment time under 1 s or the footprints within "
             "the near-miss gap; the safety-weighted score is the driving score x 0.775 for one "
             "(v2vsim/control/score.py)."
             + driven_note(meta), ""]
    for b in sorted(bs, key=lambda b: b.scope == ALL, reverse=True):
        order = sorted(b.alone, key=lambda m: -(b.alone[m]["driving_score"].mean
                                                 if b.alone[m]["driving_score"] else -1.0))
        lines += [f"## {'Overall' if b.scope == ALL else 'Family ' + b.scope} ({b.episodes} episodes)", "",
                  "| method | driving score | success | collision rate | close-call rate | safety score | efficiency |"
                  " vehicle IoU | critical detected | critical lead (s) | score - none | success - none |"
                  " collisions - none | close calls - none | safety - none |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for m in order:
            a, v = b.alone[m], b.versus_none.get(m, {})
            lines.append(f"| {m} | {cell(a['driving_score'])} | {cell(a['success'])} | {cell(a['collision'])} | "
                         f"{cell(a['close_call'])} | {cell(a['safety_score'])} | "
                         f"{cell(a['efficiency'])} | {cell(a['iou_vehicle'])} | {cell(a['critical_detected'])} | "
                         f"{cell(a['critical_lead_s'])} | "
                         + " | ".join(cell(v[k].diff, True) if k in v else "-"
                                      for k in ("driving_score", "success", "collision", "close_call",
                                                "safety_score")) + " |")
        lines.append("")
        if per_family and b.scope in per_family:
            lines += ["Per configuration, success / collision rate over the seeds:", "",
                      *config_table(per_family[b.scope], list(b.alone)), ""]
        if b.scope == ALL and per_family:
            lines += ["### What predicts success", "",
                      "Over every run but the oracle's: the chance that a successful run's figure beats a failed "
                      "one's (AUC; 0.5 = chance). Critical detected: the planner held a track within 2 m of the "
                      "family's critical actor at some frame before the conflict; lead time counts a miss as 0 s "
                      "(v2vsim/control/critical.py).", "", *predictors_md(pooled(per_family)), ""]
        if b.scope == ALL:
            lines += ["### Every pair (driving score, a - b)", "",
                      "| a | b | n | a - b | separated | episodes needed (80 % power) |", "|---|---|---|---|---|---|"]
            for p in b.pairs:
                if p.measure != "driving_score":
                    continue
                sep = "yes" if p.diff is not None and p.diff.excludes_zero else "no"
                lines.append(f"| {p.a} | {p.b} | {p.n} | {cell(p.diff, True)} | {sep} | "
                             f"{'-' if p.needed is None else p.needed} |")
            lines.append("")
    return "\n".join(lines)


def write_csv(path: Path, bs: Sequence[Board]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        head = ["scope", "method", "episodes"]
        for k in MEASURES:
            head += [k, f"{k}_lo", f"{k}_hi", f"{k}_minus_none", f"{k}_minus_none_lo", f"{k}_minus_none_hi"]
        w.writerow(head)
        for b in bs:
            for m, a in b.alone.items():
                row: list[Any] = [b.scope, m, b.episodes]
                for k in MEASURES:
                    iv, d = a[k], (b.versus_none.get(m, {}).get(k))
                    row += _triple(iv) + _triple(d.diff if d else None)
                w.writerow(row)


def _triple(iv: Interval | None) -> list[Any]:
    if iv is None:
        return ["", "", ""]
    return [round(iv.mean, 6), "" if iv.lo is None else round(iv.lo, 6), "" if iv.hi is None else round(iv.hi, 6)]


def to_json(bs: Sequence[Board], meta: dict[str, Any]) -> dict[str, Any]:
    def vs(v: Versus) -> dict[str, Any]:
        return {"a": v.a, "b": v.b, "measure": v.measure, "n": v.n, "needed_episodes": v.needed,
                **(v.diff.to_json() if v.diff else {"mean": None})}

    return {**meta, "boards": [{"scope": b.scope, "episodes": b.episodes,
                                "methods": {m: {k: iv.to_json() if iv else None for k, iv in a.items()}
                                            for m, a in b.alone.items()},
                                "versus_none": {m: {k: vs(v) for k, v in d.items()} for m, d in b.versus_none.items()},
                                "pairs": [vs(p) for p in b.pairs]} for b in bs]}


def plot(out: Path, bs: Sequence[Board]) -> list[Path]:
    """leaderboard_score.png: overall driving score per method with its interval; leaderboard_families.png: the
    mean driving score per family and method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    overall = next(b for b in bs if b.scope == ALL)
    methods = sorted(overall.alone, key=lambda m: -(overall.alone[m]["driving_score"].mean
                                                     if overall.alone[m]["driving_score"] else -1.0))
    paths = []
    fig, ax = plt.subplots(figsize=(1.0 + 0.8 * len(methods), 3.6))
    ivs = [overall.alone[m]["driving_score"] for m in methods]
    means = [iv.mean if iv else np.nan for iv in ivs]
    lo = [iv.mean - iv.lo if iv and iv.lo is not None else 0.0 for iv in ivs]
    hi = [iv.hi - iv.mean if iv and iv.hi is not None else 0.0 for iv in ivs]
    ax.bar(range(len(methods)), means, yerr=[lo, hi], capsize=4, color="#4c78a8")
    ax.set_xticks(range(len(methods)), methods, rotation=30)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("driving score (95 % CI)")
    ax.set_title(f"closed-loop benchmark: {overall.episodes} episodes")
    fig.tight_layout()
    paths.append(out / "leaderboard_score.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    fams = [b for b in bs if b.scope != ALL]
    grid = np.array([[b.alone[m]["driving_score"].mean if m in b.alone and b.alone[m]["driving_score"] else np.nan
                      for m in methods] for b in fams])
    # at least 2.4 in high: the colour bar's label must fit beside one or two families
    fig, ax = plt.subplots(figsize=(1.5 + 0.8 * len(methods), max(2.4, 1.2 + 0.5 * len(fams))))
    im = ax.imshow(grid, vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
    ax.set_xticks(range(len(methods)), methods, rotation=30)
    ax.set_yticks(range(len(fams)), [b.scope for b in fams])
    for i in range(len(fams)):
        for j in range(len(methods)):
            if not np.isnan(grid[i, j]):
                ax.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=8)
    fig.colorbar(im, ax=ax, label="driving score")
    fig.tight_layout()
    paths.append(out / "leaderboard_families.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def write_leaderboard(out: Path, per_family: dict[str, dict[Episode, dict[str, dict[str, float | None]]]],
                      methods: Sequence[str], meta: dict[str, Any], boot: int = DEFAULT_B) -> list[Path]:
    bs = boards(per_family, methods, boot)
    paths = [out / "leaderboard.md", out / "leaderboard.csv", out / "leaderboard.json"]
    paths[0].write_text(leaderboard_md(bs, meta, per_family))
    write_csv(paths[1], bs)
    paths[2].write_text(json.dumps(to_json(bs, meta), indent=1))
    return paths + plot(out, bs)
