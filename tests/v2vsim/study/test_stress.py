"""`v2vsim benchmark --stress` (v2vsim/study/stress.py): the breaking point on hand-made intervals, the catalogue's
stress section, the sweeps a stress study runs (references once, cooperative methods x levels, compensation where a
method has it) and its breaking points on fake runs whose outcome is known."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from v2vsim.study import runs as runs_mod
from v2vsim.study.benchmark import DRIVING_ONLY, BenchmarkArgs, benchmark, family_sweeps
from v2vsim.study.catalogue import load_catalogue
from v2vsim.study.plan import RunSpec
from v2vsim.study.stats import Interval
from v2vsim.study.stress import breaking_index, harm_index

from .test_benchmark import FakeJob, _catalogue


def _iv(lo: float | None, hi: float | None, mean: float = 0.1) -> Interval:
    return Interval(mean, lo, hi, 6, 6)


def test_the_breaking_point_is_the_first_level_whose_interval_no_longer_lies_above_0() -> None:
    assert breaking_index([_iv(0.2, 0.5), _iv(0.01, 0.3), _iv(-0.1, 0.3), _iv(0.1, 0.4)]) == 2
    assert breaking_index([_iv(0.2, 0.5), _iv(0.0, 0.3)]) == 1  # an interval touching 0 no longer shows a gain
    assert breaking_index([_iv(0.2, 0.5), None, _iv(-0.4, -0.1, -0.2)]) == 2  # turned negative; no data skipped
    assert breaking_index([_iv(0.2, 0.5), _iv(0.1, 0.3)]) is None  # held at every level
    assert breaking_index([_iv(None, None), _iv(0.1, 0.3)]) == 0  # one episode: nothing shown
    assert breaking_index([]) is None


def test_harm_is_the_first_level_whose_interval_lies_wholly_below_0() -> None:
    assert harm_index([_iv(0.2, 0.5), _iv(-0.3, 0.1), _iv(-0.5, -0.2, -0.4), _iv(0.1, 0.4)]) == 2
    assert harm_index([_iv(0.2, 0.5), _iv(-0.3, 0.0, -0.1)]) is None  # touching 0 is no shown harm
    assert harm_index([None, _iv(None, None, -1.0), _iv(-0.4, -0.1, -0.2)]) == 2  # one episode shows nothing
    assert harm_index([_iv(0.1, 0.3)]) is None


STRESS = {"latency": {"key": "comm.latency_ms.mean", "levels": [0, 200, 400], "unit": "ms", "compensation": True,
                      "set": ["comm.max_age_ms=1500"]},
          "pose": {"key": "comm.pose_noise", "levels": [{"xy_std_m": 0}, {"xy_std_m": 1}], "x": [0, 1], "unit": "m"}}


@pytest.mark.parametrize(("change", "expect"), [
    ({"latency": {"key": "comm.latency_ms.mean", "levels": [0], "unit": "ms"}}, "stress.latency.levels: expected a "
     "list of at least two levels"),
    ({"pose": {"key": "comm.pose_noise", "levels": [{"xy_std_m": 0}, {"xy_std_m": 1}], "unit": "m"}},
     "stress.pose.x: expected 2 numbers"),
    ({"latency": {"key": "comm.latency_ms.mean", "levels": [200, 0], "unit": "ms"}}, "stress.latency.x: expected "
     "increasing numbers"),
    ({"latency": {"key": "cavs.penetration", "levels": [0, 1], "unit": "share", "harsher": "down"}},
     "stress.latency.x: expected decreasing numbers, mildest level first"),
    ({"latency": {"key": "cavs.penetration", "levels": [1, 0], "unit": "share", "harsher": "sideways"}},
     "stress.latency.harsher: expected 'up' or 'down'"),
    ({"latency": {"key": "comm.latency_ms.mean", "levels": [0, 1], "unit": "ms", "set": ["nope"]}},
     "stress.latency.set: expected a list of KEY.PATH=VALUE"),
    ({"latency": {"key": "comm.latency_ms.mean", "levels": [0, 1], "unit": "ms", "speed": 1}},
     "stress.latency.speed: unknown key"),
])
def test_a_malformed_stress_is_one_line_naming_the_key(tmp_path: Path, change: dict, expect: str) -> None:
    from v2vsim.config import ConfigError

    with pytest.raises(ConfigError, match=expect.replace("[", r"\[").replace(".", r"\.")):
        load_catalogue(_catalogue(tmp_path, stress=change))


def _args(tmp_path: Path, stresses: tuple[str, ...] = ("latency",)) -> BenchmarkArgs:
    cat = _catalogue(tmp_path, stress=STRESS, methods=["oracle", "none", "late", "v2vnet", "cobevt"],
                     profiles={"quick": {"seeds": 3, "levels": [2]}})
    return BenchmarkArgs(out=tmp_path / "bench", catalogue=cat, bootstrap=300, stresses=stresses)


def test_a_stress_study_runs_the_references_once_and_compensation_only_where_a_method_has_it(tmp_path: Path) -> None:
    args = _args(tmp_path, stresses=("latency", "pose"))
    plan = dict(family_sweeps(args, load_catalogue(args.catalogue)))
    assert list(plan) == ["pullout/reference", "pullout/reference-latency", "pullout/latency",
                          "pullout/latency+comp", "pullout/pose"]
    ref, ref_lat, lat, comp, pose = plan.values()
    offsets = "traffic.hidden_foe.arrival_offset_s=[0, 0],[2, 2]"
    assert ref.grid == ("control.method=oracle,none", offsets) and ref.overrides == (DRIVING_ONLY,)
    # a stress with overrides of its own has references run with them (they may change the world: cavs.count)
    assert ref_lat.grid == ref.grid and ref_lat.overrides == (DRIVING_ONLY, "comm.max_age_ms=1500")
    assert pose.grid[-1].startswith("comm.pose_noise={xy_std_m: 0},{xy_std_m: 1}") and pose.overrides == (DRIVING_ONLY,)
    assert lat.grid == ("control.method=late,v2vnet,cobevt", offsets, "comm.latency_ms.mean=0,200,400")
    assert lat.overrides == (DRIVING_ONLY, "comm.max_age_ms=1500")
    # late fusion's compensation is model-free; the shipped LiDAR zoo has an extrapolation module for cobevt only
    assert comp.grid[0] == "control.method=late,cobevt"
    assert comp.overrides == (DRIVING_ONLY, "comm.max_age_ms=1500", "comm.compensation=true")
    assert ref.out == args.out / "families" / "pullout" / "reference"


def _score(method: str, latency: int, comp: bool) -> float:
    """none collides in every episode (0.3); late helps up to 200 ms, not at 400 (as none); cobevt helps at 0 only;
    compensated late helps at every level; compensated cobevt as cobevt."""
    if method == "oracle":
        return 1.0
    helps = {"none": -1, "late": 400 if comp else 200, "v2vnet": 400, "cobevt": 0}[method]
    return 1.0 if latency <= helps else 0.3


def _metrics(spec: RunSpec) -> dict:
    over = dict(o.split("=", 1) for o in spec.request["overrides"])
    method = over["control.method"]
    latency, comp = int(over.get("comm.latency_ms.mean", 0)), over.get("comm.compensation") == "true"
    score = _score(method, latency, comp)
    row = "none" if method == "oracle" else method
    ok = score == 1.0
    return {"status": "complete", "frames": 5,
            "methods": {row: {"iou_vehicle": 0.5 if ok and row != "none" else 0.2, "ap50": 0.6 if ok else 0.3}},
            "driving": {"method": method, "total": {
                "collisions": int(not ok), "driving_score": score, "success": ok, "route_completion": 1.0 if ok
                else 0.5, "finished_at_s": 10.0 if ok else None, "infractions": {"collision_vehicle": int(not ok)}}}}


class StressJob(FakeJob):
    def __init__(self, spec: RunSpec) -> None:
        (spec.out / runs_mod.LOG).write_text("v2vsim: done\n")
        spec.out.joinpath("metrics.json").write_text(json.dumps(_metrics(spec)))


def test_a_stress_study_finds_each_methods_breaking_point(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(runs_mod.time, "sleep", lambda s: None)
    args = _args(tmp_path)
    started: list[RunSpec] = []

    def start(spec: RunSpec) -> StressJob:
        started.append(spec)
        return StressJob(spec)

    assert benchmark(args, start=start, stream=io.StringIO()) == 0
    # references 2 methods x 2 configurations x 3 seeds; 3 methods x 3 levels x 6; late and cobevt compensated
    assert len(started) == 12 + 54 + 36
    doc = json.loads((args.out / "breaking_points.json").read_text())
    [lat] = doc["stresses"]
    assert lat["x"] == [0, 200, 400] and lat["key"] == "comm.latency_ms.mean"
    got = {(c["scope"], c["method"]): c for c in lat["curves"]}
    assert set(got) == {(s, m) for s in ("pullout", "overall") for m in ("late", "v2vnet", "cobevt", "late+comp",
                                                                          "cobevt+comp")}
    brk = {m: got[("overall", m)]["breaking"]["driving_score"]["x"] for m in ("late", "v2vnet", "cobevt",
                                                                               "late+comp", "cobevt+comp")}
    assert brk == {"late": 400, "v2vnet": None, "cobevt": 200, "late+comp": None, "cobevt+comp": 200}
    assert got[("overall", "late")]["breaking"]["iou_vehicle"]["x"] == 400  # perception breaks with the driving
    lv = got[("overall", "late")]["levels"]
    assert [v["driving_score"]["minus_none"]["mean"] for v in lv] == pytest.approx([0.7, 0.7, 0.0])
    assert all(v["driving_score"]["n"] == 6 for v in lv)
    md = (args.out / "breaking_points.md").read_text()
    assert "| overall | v2vnet | > 400 (never) |" in md and "| overall | cobevt | 200 |" in md
    assert (args.out / "stress_latency.png").stat().st_size > 5000
    assert not (args.out / "leaderboard.md").exists()


def test_a_stress_needs_a_cooperative_method_and_a_known_name(tmp_path: Path) -> None:
    from dataclasses import replace

    from v2vsim.config import ConfigError

    args = _args(tmp_path)
    cat = load_catalogue(args.catalogue)
    with pytest.raises(ConfigError, match="no cooperative method among --methods oracle,none"):
        family_sweeps(replace(args, methods=("oracle", "none")), cat)
    with pytest.raises(ConfigError, match="no stress 'jitter'; stresses: latency, pose"):
        family_sweeps(replace(args, stresses=("jitter",)), cat)


def test_the_shipped_attack_stresses_are_valid_scenarios_in_every_family() -> None:
    """`--stress attack,attack_defended` (issue 55): every lie is a valid `misbehaviour` of every family's scenario
    (its liars non-ego CAVs there), and the defended axis switches the defence on for each of them."""
    from v2vsim.config.load import load_scenario

    cat = load_catalogue(Path(__file__).resolve().parents[3] / "scenarios" / "benchmark" / "catalogue.yaml")
    plain, defended = cat.stress("attack"), cat.stress("attack_defended")
    assert plain.level.values == defended.level.values and plain.level.values[0] == []
    for family in cat.families:
        for text in defended.level.texts:
            sc = load_scenario(family.scenario, [f"{defended.level.key}={text}", *defended.sets])
            assert sc.defence.exclude and sc.defence.evidence and sc.defence.remember
            assert all(set(lie.cavs) <= {"cav1", "cav2"} for lie in sc.misbehaviour)
        assert not load_scenario(family.scenario, [f"misbehaviour={plain.level.texts[1]}"]).defence.on


def test_with_one_family_overall_is_that_family_to_the_last_digit() -> None:
    """One family's "overall" holds the same episodes, so it must show the same intervals and breaking points (it
    took other bootstrap draws, and a borderline level broke in one scope and not in the other)."""
    from types import SimpleNamespace

    from v2vsim.study.leaderboard import Episode
    from v2vsim.study.stress import curves

    rng = __import__("numpy").random.default_rng(0)

    def level(gain: float) -> dict:
        eps = {}
        for seed in range(6):
            base = float(rng.uniform(0.3, 0.6))
            eps[Episode("pullout", "offset=1", seed)] = {
                "none": {"driving_score": base, "iou_vehicle": base},
                "late": {"driving_score": base + gain + float(rng.normal(0, 0.05)), "iou_vehicle": base + gain}}
        return {"pullout": eps}

    cs = curves(SimpleNamespace(name="latency"), [level(0.2), level(0.03), level(-0.1)], boot=200)
    by = {c.scope: c for c in cs if c.method == "late"}
    assert set(by) == {"pullout", "overall"}
    assert by["overall"].diffs == by["pullout"].diffs and by["overall"].means == by["pullout"].means


def test_a_stress_harsher_as_x_falls_breaks_where_the_gain_stops_and_plots_each_family(tmp_path: Path) -> None:
    """Penetration (harsher: down): levels 1, 0.5, 0 mildest first; late fusion gains at 1 and 0.5 in both families
    and not at 0, so it breaks at 0; with two families each gets its own plot beside the overall one."""
    from v2vsim.study.catalogue import Axis, Stress
    from v2vsim.study.leaderboard import Episode
    from v2vsim.study.stress import write_stress

    s = Stress("penetration", Axis("cavs.penetration", ("1", "0.5", "0"), (1, 0.5, 0)), (1.0, 0.5, 0.0), "share",
               False, ())

    def level(gain: float) -> dict:
        return {f: {Episode(f, f"c{c}", seed): {"none": {"driving_score": 0.5, "iou_vehicle": 0.2},
                                                "late": {"driving_score": 0.5 + gain + 0.01 * (c - 1),
                                                         "iou_vehicle": 0.2 + gain}}
                    for c in range(3) for seed in range(2)} for f in ("a", "b")}

    levels = {"penetration": [level(0.3), level(0.2), level(0.0)]}
    meta = {"catalogue": "c.yaml", "profile": "stress", "split": "heldout", "seeds": "0-1", "families": ["a", "b"],
            "methods": ["none", "late"], "overrides": [], "stresses": ["penetration"]}
    paths = write_stress(tmp_path, [s], levels, meta, boot=200)
    assert {p.name for p in paths if p.suffix == ".png"} == {"stress_penetration.png", "stress_penetration_a.png",
                                                              "stress_penetration_b.png"}
    doc = json.loads((tmp_path / "breaking_points.json").read_text())
    got = {(c["scope"], c["method"]): c["breaking"]["driving_score"]["x"] for c in doc["stresses"][0]["curves"]}
    assert got == {("a", "late"): 0.0, ("b", "late"): 0.0, ("overall", "late"): 0.0}
    iou = {(c["scope"], c["method"]): c["breaking"]["iou_vehicle"]["x"] for c in doc["stresses"][0]["curves"]}
    assert iou[("overall", "late")] == 0.0  # the IoU gain (0 at the last level) stops there too
    from v2vsim.study.stress import BreakingPoint

    assert BreakingPoint("late", "penetration", "a", "iou_vehicle", None, None).text(s) == "< 0 (never)"
