"""The driving measures (metrics.json `driving`) on hand-made frames: collisions counted once per vehicle and
onset, near misses only without contact, hard and phantom braking by onsets, the junction cleared when the vehicle
first leaves it, and the trajectory PET only for crossing paths."""

from __future__ import annotations

import math
from pathlib import Path

from v2vsim.control.measures import DrivenFrame, driving_block, ssm_conflicts, trajectory_pet, vehicle_measures

DT = 0.1


def _frame(k: int, speed: float = 10.0, *, x: float | None = None, collisions: tuple[str, ...] = (),
           gap: float | None = 5.0, junction: bool = False, phantom: bool = False,
           others: tuple[tuple[str, float, float, float], ...] = ()) -> DrivenFrame:
    return DrivenFrame(frame=k, time=k * DT, x=k * 1.0 if x is None else x, y=0.0, yaw=0.0, speed=speed,
                       odometer_m=k * 1.0, in_junction=junction, collisions=collisions, ssm=(2.5, 1.0, None),
                       min_gap_m=gap, closest="veh1", commanded_speed=speed, reason="free", phantom=phantom,
                       others=others)


def test_collisions_near_misses_braking_and_clearing() -> None:
    frames = [_frame(0), _frame(1, collisions=("veh1",), gap=0.0), _frame(2, collisions=("veh1",), gap=0.0),
              _frame(3), _frame(4, collisions=("veh1", "veh2"), gap=0.0)]
    m = vehicle_measures(frames, DT, hard_brake=4.0, near_miss_gap=1.0, ssm_count=3)
    assert m["collisions"] == 3 and m["collided_with"] == ["veh1", "veh2"] and m["first_collision_frame"] == 1
    assert not m["near_miss"]  # contact is a collision, not a near miss
    close = [_frame(0, gap=3.0), _frame(1, gap=0.8), _frame(2, gap=2.0)]
    assert vehicle_measures(close, DT, 4.0, 1.0, 0)["near_miss"]
    assert not vehicle_measures(close, DT, 4.0, 0.5, 0)["near_miss"]
    # 10 -> 9.5 (-5 m/s^2) twice in a row is one onset; phantom frames 3-4 and 6 are two onsets
    speeds = [10.0, 9.5, 9.0, 9.0, 8.0, 8.0, 8.0]
    braking = [_frame(k, s, phantom=k in (3, 4, 6)) for k, s in enumerate(speeds)]
    b = vehicle_measures(braking, DT, 4.0, 1.0, None)
    assert b["hard_braking"] == 2 and b["phantom_braking"] == 2 and math.isclose(b["max_decel_mps2"], 10.0)
    assert b["ssm"] == {"conflicts": None, "min_ttc_s": 2.5, "max_drac_mps2": 1.0, "min_pet_s": None}
    through = [_frame(0), _frame(1, junction=True), _frame(2, junction=True), _frame(3), _frame(4, junction=True)]
    assert math.isclose(vehicle_measures(through, DT, 4.0, 1.0, 0)["time_to_clear_s"], 0.3)
    assert vehicle_measures(through[:3], DT, 4.0, 1.0, 0)["time_to_clear_s"] is None


def test_trajectory_pet_counts_crossing_paths_only() -> None:
    # the ego drives along +x through (5, 0) at t = 0.5 s; a crosser (heading +y) is there at t = 1.2 s. Within
    # 1.5 m of each other's spot the closest in time are the ego at (6, 0) at 0.6 s and the crosser at (5, -1) at
    # 1.1 s: PET 0.5 s
    crosser = [_frame(k, others=(("x1", 5.0, -12.0 + k * 1.0, math.pi / 2),)) for k in range(20)]
    assert math.isclose(trajectory_pet(crosser), 0.5, abs_tol=1e-9)  # type: ignore[arg-type]
    follower = [_frame(k, others=(("f1", k * 1.0 - 3.0, 0.0, 0.0),)) for k in range(15)]  # same path, 0.3 s behind
    assert trajectory_pet(follower) is None


def test_the_block_totals_and_the_ssm_log(tmp_path: Path) -> None:
    a = vehicle_measures([_frame(0), _frame(1, collisions=("veh1",), gap=0.0)], DT, 4.0, 1.0, 1)
    b = vehicle_measures([_frame(0, gap=0.5), _frame(1, gap=0.7)], DT, 4.0, 1.0, 2)
    d = driving_block({"cav0": a, "cav1": b}, {"method": "cobevt"})
    assert d["method"] == "cobevt" and d["total"]["collisions"] == 1 and d["total"]["near_misses"] == 1
    assert d["total"]["ssm_conflicts"] == 3 and d["total"]["min_gap_m"] == 0.0
    log = tmp_path / "ssm.xml"
    log.write_text('<SSMLog><conflict begin="1" end="2" ego="cav0" foe="veh1"/>'
                   '<conflict begin="3" end="4" ego="cav0" foe="veh2"/><conflict ego="cav1" foe="x"/></SSMLog>')
    assert ssm_conflicts(log) == {"cav0": 2, "cav1": 1}
    log.write_text("<SSMLog><conflict")  # cut short: nothing trustworthy
    assert ssm_conflicts(log) == {} and ssm_conflicts(None) == {}
