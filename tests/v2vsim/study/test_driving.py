"""A closed-loop sweep's driving comparison against `none` (v2vsim.study.driving), on hand-made rows: twins,
the paired difference and its interval, missing values, the sweep files it adds and the plot; an open-loop
sweep's files are left as they were."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from v2vsim.study import plots
from v2vsim.study.driving import (
    EITHER,
    MEASURES,
    DrivingStudy,
    Versus,
    driving_study,
    has_driving,
    measure,
    twins,
)
from v2vsim.study.grid import Axis, Point, parse_axes, points
from v2vsim.study.plan import RunSpec
from v2vsim.study.rows import Row, driving_columns
from v2vsim.study.runs import RunResult
from v2vsim.study.summary import STAT_METRICS, point_stats, sweep_json, sweep_md
from v2vsim.study.sweep import Design, SweepArgs, write_outputs

GRID = ("control.method=oracle,none,cobevt", "comm.latency_ms.mean=0,100,200")
SEEDS = range(6)
B = 300


def _totals(method: str, latency: float, seed: int) -> dict:
    """What a run's `driving.total` says. cobevt: 1 to 3 collisions fewer than none on every seed; the same
    hard braking as none on average (+1, -1, 0 by seed); none finds no TTC conflict on seeds 0 and 1, cobevt
    none on seed 2."""
    base = 3 + seed % 2 + int(latency > 100)
    collisions = {"none": base, "cobevt": base - 1 - seed % 3, "oracle": 0}[method]
    hard = 4 + {"none": 0, "cobevt": (1, -1, 0)[seed % 3], "oracle": -2}[method]
    ttc = None if (method, seed) in {("none", 0), ("none", 1), ("cobevt", 2)} else 1.0 + 0.1 * seed
    return {"collisions": collisions, "near_misses": int(method == "oracle" and seed == 0), "hard_braking": hard,
            "phantom_braking": 0, "min_gap_m": 2.0 + seed, "min_ttc_s": ttc, "max_drac_mps2": None, "min_pet_s": None,
            "pet_s": None, "ssm_conflicts": 2, "time_to_clear_s": 8.0, "progress_m": 40.0}


def _axis_value(axes: list[Axis], p: Point, key: str) -> str:
    return next(t for a, t in zip(axes, p.texts, strict=True) if a.key == key)


def _rows(axes: list[Axis], pts: list[Point], tmp: Path) -> list[Row]:
    """Each run's rows: two method rows with the same driving columns (what rows.collect gives)."""
    rows = []
    for p in pts:
        method = _axis_value(axes, p, "control.method")
        latency = float(_axis_value(axes, p, "comm.latency_ms.mean"))
        for s in SEEDS:
            drv = driving_columns({"method": method, "total": _totals(method, latency, s)})
            for m in ("none", "cobevt"):
                rows.append(Row(p, s, m, {"iou_vehicle": 0.5, **drv}, tmp))
    return rows


def _study(tmp: Path, grid: tuple[str, ...] = GRID) -> tuple[list[Axis], list[Point], list[Row], DrivingStudy]:
    axes = parse_axes(list(grid))
    pts = points(axes)
    rows = _rows(axes, pts, tmp)
    return axes, pts, rows, driving_study(rows, axes, pts, B)


def _versus(axes: list[Axis], study: DrivingStudy, method: str, latency: str) -> Versus:
    return next(v for v in study.versus if v.method == method
                and _axis_value(axes, v.point, "comm.latency_ms.mean") == latency)


@pytest.mark.parametrize("grid", [GRID, GRID[::-1]])
def test_every_method_is_matched_with_none_at_the_same_other_values(grid: tuple[str, ...]) -> None:
    axes = parse_axes(list(grid))
    pairs = twins(axes, points(axes))
    assert len(pairs) == 6  # oracle and cobevt at 3 latencies
    for p, twin in pairs:
        assert _axis_value(axes, twin, "control.method") == "none"
        assert _axis_value(axes, p, "control.method") in ("oracle", "cobevt")
        assert _axis_value(axes, p, "comm.latency_ms.mean") == _axis_value(axes, twin, "comm.latency_ms.mean")
    assert len({p.pid for p, _ in pairs}) == 6
    assert twins(parse_axes(["comm.latency_ms.mean=0,100"]), points(parse_axes(["comm.latency_ms.mean=0,100"]))) == []
    no_none = parse_axes(["control.method=oracle,cobevt"])
    assert twins(no_none, points(no_none)) == []


def test_fewer_collisions_on_every_seed_is_an_interval_below_zero_and_no_difference_one_around_it(
        tmp_path: Path) -> None:
    axes, _, _, study = _study(tmp_path)
    assert len(study.versus) == 6 and len(study.points) == 9
    v = _versus(axes, study, "cobevt", "200")
    col = v.measures["collisions"]
    assert col.n == 6 and col.mean == pytest.approx(4.5 - 2.0) and col.twin_mean == pytest.approx(4.5)
    assert col.diff.mean == pytest.approx(-2.0) and col.diff.seeds == 6  # one value per run, not per method row
    assert col.diff.hi < 0 and col.diff.excludes_zero
    hard = v.measures["hard_braking"]
    assert hard.diff.mean == pytest.approx(0.0) and hard.diff.lo < 0 < hard.diff.hi and not hard.diff.excludes_zero
    assert _versus(axes, study, "oracle", "0").measures["collisions"].diff.hi < 0
    again = driving_study(_rows(axes, points(axes), tmp_path), axes, points(axes), B)
    assert again == study  # a fixed RNG per comparison: the same intervals every time


def test_a_missing_value_leaves_that_seed_out_of_that_measure_only(tmp_path: Path) -> None:
    axes, _, _, study = _study(tmp_path)
    v = _versus(axes, study, "cobevt", "0")
    ttc = v.measures["min_ttc_s"]
    assert ttc.n == 3  # seeds 3, 4, 5: none has no TTC on 0 and 1, cobevt none on 2
    assert ttc.diff.mean == pytest.approx(0.0) and ttc.twin_mean == pytest.approx(1.4)
    assert v.measures["collisions"].n == 6
    alone = next(p for p in study.points if p.method == "none" and p.point == v.twin)
    assert alone.seeds == 6 and alone.measures["min_ttc_s"].seeds == 4
    assert measure({"driving_collisions": None, "driving_near_misses": 1}, EITHER) == 1.0
    assert measure({"driving_collisions": 0, "driving_near_misses": None}, EITHER) is None
    assert measure({"driving_collisions": 0, "driving_near_misses": 0}, EITHER) == 0.0
    assert measure({"driving_min_ttc_s": None}, "min_ttc_s") is None and measure({}, "collisions") is None
    oracle = _versus(axes, study, "oracle", "0").measures[EITHER]
    assert oracle.mean == pytest.approx(1 / 6) and oracle.twin_mean == 1.0  # a share of runs


def test_json_and_report_section(tmp_path: Path) -> None:
    axes, _, _, study = _study(tmp_path)
    doc = json.loads(json.dumps(study.to_json()))
    assert doc["method_axis"] == "control.method" and doc["bootstrap"]["b"] == B
    assert len(doc["points"]) == 9 and {p["method"] for p in doc["points"]} == {"oracle", "none", "cobevt"}
    vs = next(v for v in doc["vs_none"] if v["method"] == "cobevt" and v["point"] == {"comm.latency_ms.mean": 200})
    assert vs["none"] == "control.method=none_comm.latency_ms.mean=200"
    assert vs["measures"]["collisions"]["difference"]["excludes_zero"] is True
    assert vs["measures"]["collisions"]["none_mean"] == 4.5 and vs["measures"]["collisions"]["n"] == 6


def test_a_run_method_not_swept_is_described_but_not_compared(tmp_path: Path) -> None:
    axes = parse_axes(["comm.latency_ms.mean=0,100"])
    pts = points(axes)
    drv = driving_columns({"method": "cobevt", "total": _totals("cobevt", 0, 0)})
    rows = [Row(p, s, "cobevt", dict(drv), tmp_path) for p in pts for s in SEEDS]
    study = driving_study(rows, axes, pts, B)
    assert study.method_axis is None and study.versus == () and [p.method for p in study.points] == ["cobevt"] * 2
    md = _md(axes, rows, study)
    assert "## Driving against none (closed loop)" in md and "nothing to compare against none" in md


def _meta(points_: list[Point]) -> dict:
    return {"scenario": "s.yaml", "scenario_name": "s", "seeds": list(SEEDS), "frames": 5,
            "points": [p.pid for p in points_], "overrides": [], "runs": {"complete": 1, "reused": 0},
            "bootstrap": {"b": B, "rng_seed": 0}}


def _md(axes: list[Axis], rows: list[Row], study: DrivingStudy | None) -> str:
    pts = points(axes)
    stats = [s for m in STAT_METRICS for s in point_stats(rows, pts, m, B, 0)]
    return sweep_md(_meta(pts), axes, rows, stats, [], [], study)


def test_the_report_compares_each_method_with_none(tmp_path: Path) -> None:
    axes, _, rows, study = _study(tmp_path)
    md = _md(axes, rows, study)
    section = md[md.index("## Driving against none (closed loop)"):md.index("## Other metrics")]
    assert "paired by seed" in section and f"B = {B}" in section
    assert "### collisions per run" in section and "### share of runs with a collision or near miss" in section
    assert "| comm.latency_ms.mean=200 | cobevt | 2.500 | 4.500 | -2.000 [" in section
    assert section.count("| cobevt |") == 3 * len(MEASURES) and section.count("| oracle |") == 3 * len(MEASURES)


# ---- the sweep's files --------------------------------------------------------------------------------------


def _write_runs(tmp: Path, grid: tuple[str, ...], closed: bool) -> tuple[SweepArgs, Design, list[RunResult]]:
    """A finished sweep's runs on disk (what `v2vsim run` leaves), as write_outputs gets them."""
    axes = parse_axes(list(grid))
    pts = points(axes)
    out = tmp / "sweep"
    specs, results = [], []
    for p in pts:
        for s in SEEDS:
            spec = RunSpec(p, s, out / "runs" / p.pid / f"seed{s}", tuple(p.overrides(axes)), {})
            spec.out.mkdir(parents=True)
            doc = {"status": "complete", "methods": {m: {"iou_vehicle": 0.4 + 0.01 * s + 0.1 * i, "ap50": 0.5}
                                                     for i, m in enumerate(("none", "cobevt"))}}
            if closed:
                method = _axis_value(axes, p, "control.method")
                doc["driving"] = {"method": method, "vehicles": {}, "total": _totals(method, 0, s)}
            (spec.out / "metrics.json").write_text(json.dumps(doc))
            specs.append(spec)
            results.append(RunResult(spec, ok=True))
    args = SweepArgs(Path("s.yaml"), grid, "0-5", out, frames=5, bootstrap=B)
    return args, Design(Path("s.yaml"), "s", axes, pts, list(SEEDS), [], specs, None), results


def test_an_open_loop_sweep_writes_what_it_did_before(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    args, d, results = _write_runs(tmp_path, ("comm.latency_ms.mean=0,100",), closed=False)
    paths = write_outputs(args, d, results, False)
    doc = json.loads((args.out / "sweep.json").read_text())
    assert "driving" not in doc and doc["plots"] == []
    assert "Driving" not in (args.out / "sweep.md").read_text() and not list(args.out.glob("sweep_driving*"))
    assert [p.name for p in paths] == ["sweep.csv", "sweep.json", "sweep.md"]
    # without a driving study the functions give what they gave before it existed, to the byte
    rows = [Row(p, s, "none", {"iou_vehicle": 0.5}, args.out) for p in d.points for s in SEEDS]
    assert not has_driving(rows)
    stats = [s for m in STAT_METRICS for s in point_stats(rows, d.points, m, B, 0)]
    assert json.dumps(sweep_json(_meta(d.points), d.axes, rows, stats, args.out)) == json.dumps(
        sweep_json(_meta(d.points), d.axes, rows, stats, args.out, None))
    assert sweep_md(_meta(d.points), d.axes, rows, stats, [], []) == _md(d.axes, rows, None)


def test_a_closed_loop_sweep_adds_the_comparison_and_its_plot(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(plots, "plot_all", lambda *a, **k: [])
    args, d, results = _write_runs(tmp_path, GRID, closed=True)
    write_outputs(args, d, results, False)
    doc = json.loads((args.out / "sweep.json").read_text())
    assert len(doc["driving"]["vs_none"]) == 6 and len(doc["driving"]["points"]) == 9
    assert doc["plots"] == ["sweep_driving_comm.latency_ms.mean.png"]
    assert "## Driving against none (closed loop)" in (args.out / "sweep.md").read_text()
    assert (args.out / "sweep_driving_comm.latency_ms.mean.png").stat().st_size > 5000


def test_without_another_swept_key_the_plot_is_a_bar_chart_over_methods(tmp_path: Path) -> None:
    axes = parse_axes(["control.method=oracle,none,cobevt"])
    pts = points(axes)
    rows = [Row(p, s, "none", driving_columns({"method": p.texts[0], "total": _totals(p.texts[0], 0, s)}),
                tmp_path) for p in pts for s in SEEDS]
    (png,) = plots.plot_driving(tmp_path, driving_study(rows, axes, pts, B), "s")
    assert png.name == "sweep_driving_control.method.png" and png.stat().st_size > 5000


def test_efficiency_is_the_oracle_s_completion_time_over_the_run_s_on_the_same_seed(tmp_path: Path) -> None:
    """issue 53: oracle completes in 10 s + seed, cobevt in 12.5 s + seed, none never completes its route."""
    axes = parse_axes(["control.method=oracle,none,cobevt"])
    pts = points(axes)
    done = {"oracle": 10.0, "cobevt": 12.5, "none": None}
    rows = []
    for p in pts:
        method = p.texts[0]
        for s in SEEDS:
            t = done[method]
            total = {**_totals(method, 0, s), "finished_at_s": None if t is None else t + s}
            rows.append(Row(p, s, "none", driving_columns({"method": method, "total": total}), tmp_path))
    study = driving_study(rows, axes, pts, b=B)
    got = {pd.method: pd.measures["efficiency"] for pd in study.points}
    assert got["oracle"] is not None and got["oracle"].mean == pytest.approx(1.0)
    expected = sum((10.0 + s) / (12.5 + s) for s in SEEDS) / len(SEEDS)
    assert got["cobevt"] is not None and got["cobevt"].mean == pytest.approx(expected)
    assert got["none"] is None  # it never completed: no efficiency, rather than a made-up one
