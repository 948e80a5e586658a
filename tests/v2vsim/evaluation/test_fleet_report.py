"""The fleet's report (v2vsim/evaluation/fleet_report.py) on hand-made ego blocks: every driven vehicle in the
run's own metrics.json and report, fleet totals, and a contact between two driven vehicles counted once."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from v2vsim.control.measures import DrivenFrame, driving_block, vehicle_measures
from v2vsim.control.score import score_block, total_score
from v2vsim.evaluation.fleet_report import fleet_counts, merge_driving, merge_fleet
from v2vsim.evaluation.report_md import driving_md

DT = 0.1


def _block(me: str, touches: tuple[str, ...] = (), finish: bool = True) -> dict:
    """One ego's `driving` block for vehicle `me`, which touches `touches` from frame 10 to 12."""
    frames = [DrivenFrame(frame=k, time=k * DT, x=float(k), y=0.0, yaw=0.0, speed=10.0, odometer_m=float(k),
                          in_junction=False, collisions=touches if 10 <= k <= 12 else (), ssm=(None, None, None),
                          min_gap_m=3.0, closest=None, commanded_speed=None, reason="free", phantom=False,
                          route_m=30.0, route_done_m=float(min(k, 30)), finished=finish and k == 30)
              for k in range(31)]
    per = vehicle_measures(frames, DT, 4.0, 1.0, 0)
    per |= score_block(frames, per["collisions"], True)
    header = {"method": "cobevt", "planner": "idm", "driven": [me], "actuation_delay_frames": 1,
              "actuation_delay_ms": 100.0, "background_ignore_junction_foes": 0.0,
              "ssm_thresholds": {"ttc_s": 3.0, "drac_mps2": 3.0, "pet_s": 2.0}, "penalties": {"collision_vehicle": 0.6}}
    block = driving_block({me: per}, header)
    block["total"] |= total_score([per])
    return block


def _fleet() -> list[dict]:
    # cav0 and cav1 touch each other (each ego counts it), cav2 touches a background car, cav3 drives clean
    return [_block("cav0", ("cav1",)), _block("cav1", ("cav0",)), _block("cav2", ("bg.7",)), _block("cav3")]


def test_a_contact_between_two_driven_vehicles_is_one_fleet_collision() -> None:
    m = merge_driving(_fleet())
    assert list(m["vehicles"]) == ["cav0", "cav1", "cav2", "cav3"] and m["driven"] == ["cav0", "cav1", "cav2", "cav3"]
    assert m["total"]["collisions"] == 3  # per vehicle, added: cav0, cav1 and cav2 each counted one
    assert m["total"]["fleet"] == {"driven": 4, "collisions_between_driven": 1, "collisions_with_others": 1,
                                   "collisions": 2, "vehicles_in_collision": 3}
    assert m["total"]["successes"] == 1 and m["total"]["success"] is False
    assert m["total"]["driving_score"] == pytest.approx((0.6 * 3 + 1.0) / 4, abs=1e-4)
    assert m["total"]["infractions"]["collision_vehicle"] == 3


def test_a_clean_fleet_counts_nothing() -> None:
    assert fleet_counts({"cav0": {"frames": 5, "collided_with": []}, "cav1": {"frames": 0}}) == {
        "driven": 1, "collisions_between_driven": 0, "collisions_with_others": 0, "collisions": 0,
        "vehicles_in_collision": 0}


def _write(folder: Path, block: dict, report: bool) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "metrics.json").write_text(json.dumps({"status": "complete", "driving": block}))
    if report:
        (folder / "report.md").write_text("# Report\n" + "\n".join(driving_md(block)) + "\n\n## After\n")


def test_the_runs_own_outputs_hold_the_fleet_and_each_ego_keeps_its_own(tmp_path: Path) -> None:
    blocks = _fleet()
    egos = ["cav0", "cav1", "cav2", "cav3"]
    _write(tmp_path, blocks[0], True)
    for e, b in zip(egos[1:], blocks[1:], strict=True):
        _write(tmp_path / f"ego_{e}", b, True)
    own1 = (tmp_path / "ego_cav1" / "metrics.json").read_text()
    assert merge_fleet(tmp_path, egos) is True
    doc = json.loads((tmp_path / "metrics.json").read_text())
    assert set(doc["driving"]["vehicles"]) == set(egos) and doc["driving"]["total"]["fleet"]["collisions"] == 2
    assert doc["status"] == "complete"
    assert (tmp_path / "ego_cav1" / "metrics.json").read_text() == own1
    report = (tmp_path / "report.md").read_text()
    assert report.count("## Driving (closed loop)") == 1 and report.endswith("## After\n")
    for e in egos:
        assert f"| {e} | " in report
    assert "Fleet: 4 driven vehicles; 2 distinct contacts (1 between driven vehicles, 1 with others)" in report


def test_one_ego_or_an_ego_without_results_leaves_the_run_as_it_is(tmp_path: Path) -> None:
    _write(tmp_path, _fleet()[0], False)
    before = (tmp_path / "metrics.json").read_text()
    assert merge_fleet(tmp_path, ["cav0"]) is False
    assert merge_fleet(tmp_path, ["cav0", "cav1"]) is False  # cav1 wrote nothing
    assert (tmp_path / "metrics.json").read_text() == before
