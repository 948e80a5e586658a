"""A closed-loop sweep's driving comparison: every control.method against `none`, paired by seed.

A closed-loop run drives one method (the scenario's `control.method`, swept as a grid axis), and its
driving totals are copied onto each of its method rows (v2vsim.study.rows.driving_columns). Here a run is
one value per (grid point, seed). Each point whose control.method is not `none` has a twin: the point with
control.method=none and the same value on every other axis. Both ran the same seeds, so the same traffic
realisation, and the comparison is the mean over seeds of (point - twin), with a bootstrap interval that
resamples seeds (the per-seed differences as one-value clusters of v2vsim.study.stats.interval: the
expanded percentile interval the rest of the sweep uses). A measure a run has no value for (None: no
conflict met, the junction never cleared) leaves that seed out of that measure only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from v2vsim.study.grid import Axis, Point
from v2vsim.study.rows import Row
from v2vsim.study.stats import DEFAULT_B, DEFAULT_RNG_SEED, LEVEL, Interval, interval

METHOD_KEY = "control.method"
BASELINE = "none"
METHOD_COLUMN = "driving_method"  # present on every row of a closed-loop run, absent from open-loop ones
EITHER = "collisions_or_near_misses"  # 0/1 per run: a collision or a near miss happened
EFFICIENCY = "efficiency"  # the oracle's completion time over the run's, same configuration (v2vsim/control/score.py)
ORACLE = "oracle"
MEASURES = ("driving_score", "success", "route_completion", EFFICIENCY, "collisions", "near_misses", EITHER,
            "min_ttc_s", "min_gap_m", "time_to_clear_s", "hard_braking", "phantom_braking",
            "safety_score", "close_calls")  # the last two: v2vsim/control/score.py (issue 67)
LABELS = {"driving_score": "driving score (0-1)", "success": "share of runs that succeeded",
          "route_completion": "route completion (0-1)",
          EFFICIENCY: "efficiency (the oracle's completion time over the run's)",
          "collisions": "collisions per run", "near_misses": "near misses per run (driven vehicles with one)",
          EITHER: "share of runs with a collision or near miss", "min_ttc_s": "min TTC (s)",
          "min_gap_m": "min gap (m)", "time_to_clear_s": "time to clear the junction (s)",
          "hard_braking": "hard-braking onsets per run", "phantom_braking": "phantom-braking onsets per run",
          "safety_score": "safety-weighted driving score (0-1)",
          "close_calls": "close calls per run (driven vehicles with one)"}


@dataclass(frozen=True)
class PointDriving:
    """One grid point's driving measures alone: mean over its seeds with an interval (None: no value)."""

    point: Point
    method: str
    seeds: int
    measures: dict[str, Interval | None]


@dataclass(frozen=True)
class Paired:
    """One measure at a point against its twin, over the seeds both have a value for."""

    mean: float | None  # the point's mean over those seeds
    twin_mean: float | None  # none's mean over the same seeds
    n: int  # those seeds
    diff: Interval | None  # point - twin, paired by seed

    def to_json(self) -> dict[str, Any]:
        return {"mean": _round(self.mean), "none_mean": _round(self.twin_mean), "n": self.n,
                "difference": self.diff.to_json() if self.diff else None}


@dataclass(frozen=True)
class Versus:
    """A point whose control.method is not none, against its none twin."""

    point: Point
    twin: Point
    method: str
    measures: dict[str, Paired]


@dataclass(frozen=True)
class DrivingStudy:
    axes: tuple[Axis, ...]
    method_axis: int | None  # the index of control.method among the axes; None when it is not swept
    b: int
    rng_seed: int
    points: tuple[PointDriving, ...]
    versus: tuple[Versus, ...]

    def where(self, p: Point) -> dict[str, Any]:
        """The point's values on every axis but control.method (what a twin shares)."""
        return {a.key: a.values[i] for k, (a, i) in enumerate(zip(self.axes, p.indices, strict=True))
                if k != self.method_axis}

    def to_json(self) -> dict[str, Any]:
        return {
            "method_axis": None if self.method_axis is None else METHOD_KEY, "baseline": BASELINE,
            "measures": list(MEASURES),
            "bootstrap": {"b": self.b, "rng_seed": self.rng_seed, "level": LEVEL,
                          "method": "paired by seed: bootstrap over seeds, expanded percentile intervals"},
            "points": [{"point": self.where(p.point), "pid": p.point.pid, "method": p.method, "seeds": p.seeds,
                        "measures": {k: iv.to_json() if iv else None for k, iv in p.measures.items()}}
                       for p in self.points],
            "vs_none": [{"point": self.where(v.point), "pid": v.point.pid, "method": v.method, "none": v.twin.pid,
                         "measures": {k: pr.to_json() for k, pr in v.measures.items()}} for v in self.versus],
        }


def _round(v: float | None) -> float | None:
    return None if v is None else round(v, 6)


def has_driving(rows: Sequence[Row]) -> bool:
    """Whether any row is from a closed-loop run (an open-loop sweep's outputs do not change)."""
    return any(METHOD_COLUMN in r.metrics for r in rows)


def measure(metrics: dict[str, Any], name: str) -> float | None:
    """A run's value of one measure from its driving columns; None when the run has none."""
    if name == EITHER:
        c, n = (metrics.get(f"driving_{k}") for k in ("collisions", "near_misses"))
        if (c or 0) > 0 or (n or 0) > 0:
            return 1.0  # one of them is known to have happened, whatever the other says
        return None if c is None or n is None else 0.0
    v = metrics.get(f"driving_{name}")
    return float(v) if isinstance(v, (int, float)) else None


def runs_by_point(rows: Sequence[Row]) -> dict[str, dict[int, dict[str, Any]]]:
    """pid -> seed -> the run's metrics: its first row (every method row of a run carries the same driving
    columns), closed-loop rows only."""
    out: dict[str, dict[int, dict[str, Any]]] = {}
    for r in rows:
        if METHOD_COLUMN in r.metrics:
            out.setdefault(r.point.pid, {}).setdefault(r.seed, r.metrics)
    return out


def with_efficiency(runs: dict[str, dict[int, dict[str, Any]]], axes: Sequence[Axis], pts: Sequence[Point]
                    ) -> dict[str, dict[int, dict[str, Any]]]:
    """`runs` with driving_efficiency on every run whose oracle twin (same seed, same other axes) and itself both
    completed their routes: the oracle's completion time over the run's (the oracle's own runs: 1)."""
    twin_of = {p.pid: o.pid for p, o in twins(axes, pts, ORACLE)}
    out: dict[str, dict[int, dict[str, Any]]] = {}
    for pid, by_seed in runs.items():
        oracle = runs.get(twin_of.get(pid, ""), {})
        out[pid] = {}
        for seed, m in by_seed.items():
            mine = m.get("driving_finished_at_s")
            theirs = m.get("driving_finished_at_s") if m.get(METHOD_COLUMN) == ORACLE else (
                oracle.get(seed, {}).get("driving_finished_at_s"))
            eff = theirs / mine if isinstance(mine, (int, float)) and isinstance(theirs, (int, float)) and mine > 0 \
                else None
            out[pid][seed] = m if eff is None else {**m, f"driving_{EFFICIENCY}": eff}
    return out


def twins(axes: Sequence[Axis], pts: Sequence[Point], baseline: str = BASELINE) -> list[tuple[Point, Point]]:
    """(point, its twin) for every point whose control.method is not `baseline` (none; the oracle for efficiency),
    the twin being the point with the baseline and the same other values; [] when control.method is not swept or
    the baseline is not among its values."""
    k = next((j for j, a in enumerate(axes) if a.key == METHOD_KEY), None)
    if k is None:
        return []
    base = next((i for i, v in enumerate(axes[k].values) if str(v) == baseline), None)
    if base is None:
        return []
    by = {p.indices: p for p in pts}
    out = []
    for p in pts:
        if p.indices[k] == base:
            continue
        twin = by.get(p.indices[:k] + (base,) + p.indices[k + 1:])
        if twin is not None:
            out.append((p, twin))
    return out


def _method(axes: Sequence[Axis], k: int | None, p: Point, runs: dict[int, dict[str, Any]]) -> str:
    if k is not None:
        return str(axes[k].values[p.indices[k]])
    first = next(iter(runs.values()), {})  # not swept: what the runs say they drove
    return str(first.get(METHOD_COLUMN))


def _alone(values: dict[int, float | None], b: int, label: str, rng_seed: int) -> Interval | None:
    return interval([[v] for v in values.values() if v is not None], b, label, rng_seed)


def paired(a: dict[int, dict[str, Any]], t: dict[int, dict[str, Any]], name: str, b: int, label: str,
           rng_seed: int) -> Paired:
    """One measure of point runs `a` against twin runs `t` (seed -> metrics), over the seeds both have it."""
    seeds = [s for s in sorted(set(a) & set(t)) if measure(a[s], name) is not None
             and measure(t[s], name) is not None]
    if not seeds:
        return Paired(None, None, 0, None)
    xa = [measure(a[s], name) or 0.0 for s in seeds]
    xt = [measure(t[s], name) or 0.0 for s in seeds]
    diff = interval([[x - y] for x, y in zip(xa, xt, strict=True)], b, label, rng_seed)
    return Paired(sum(xa) / len(xa), sum(xt) / len(xt), len(seeds), diff)


def driving_study(rows: Sequence[Row], axes: Sequence[Axis], pts: Sequence[Point], b: int = DEFAULT_B,
                  rng_seed: int = DEFAULT_RNG_SEED) -> DrivingStudy:
    """Each point's measures alone, and every non-none control.method against its none twin (module doc)."""
    runs = with_efficiency(runs_by_point(rows), axes, pts)
    k = next((j for j, a in enumerate(axes) if a.key == METHOD_KEY), None)
    alone = []
    for p in pts:
        mine = runs.get(p.pid)
        if not mine:
            continue
        ivs = {m: _alone({s: measure(x, m) for s, x in mine.items()}, b, f"driving|{p.pid}|{m}", rng_seed)
               for m in MEASURES}
        alone.append(PointDriving(p, _method(axes, k, p, mine), len(mine), ivs))
    versus = []
    for p, twin in twins(axes, pts):
        mine = runs.get(p.pid)
        if not mine:
            continue
        theirs = runs.get(twin.pid, {})
        prs = {m: paired(mine, theirs, m, b, f"driving|{p.pid}|{m}|-{twin.pid}", rng_seed) for m in MEASURES}
        versus.append(Versus(p, twin, _method(axes, k, p, mine), prs))
    return DrivingStudy(tuple(axes), k, b, rng_seed, tuple(alone), tuple(versus))
