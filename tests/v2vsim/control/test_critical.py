"""The critical-actor measure on hand-made frames: detected early, late, never, and lost again."""

from __future__ import annotations

import pytest

from v2vsim.config import load_scenario
from v2vsim.control.critical import KEYS, MATCH_M, critical_actor, critical_measures
from v2vsim.control.measures import DrivenFrame

DT = 0.1


def _frame(k: int, foe_x: float, track_x: float | None, *, gap: float, speed: float = 10.0,
           track_speed: float = 10.0, age: int = 5, in_junction: bool = False,
           collisions: tuple[str, ...] = ()) -> DrivenFrame:
    """The ego standing at the origin; the foe at (foe_x, 20) driving at `speed`; the nearest seen track at
    (track_x, 20) (None: no track seen)."""
    return DrivenFrame(frame=k, time=k * DT, x=0.0, y=0.0, yaw=0.0, speed=0.0, odometer_m=0.0,
                       in_junction=in_junction, collisions=collisions, ssm=(None, None, None), min_gap_m=gap,
                       closest="foe0", commanded_speed=0.0, reason="yield", phantom=False,
                       critical=(foe_x, 20.0, speed, gap),
                       critical_track=None if track_x is None else (track_x, 20.0, track_speed, age))


def _approach(n: int, seen: list[bool], offset_m: float = 0.5, commit: int | None = None) -> list[DrivenFrame]:
    """n frames, the foe closing in (gap n - k, least at the last frame), a track `offset_m` off it where `seen`."""
    return [_frame(k, float(k), float(k) + offset_m if seen[k] else None, gap=float(n - k),
                   in_junction=commit is not None and k >= commit) for k in range(n)]


def test_detected_early_and_held() -> None:
    m = critical_measures(_approach(10, [False, False] + [True] * 8), "foe0")
    assert m["critical_actor"] == "foe0"
    assert m["critical_conflict_frame"] == 9
    assert m["critical_first_detected_frame"] == 2
    assert m["critical_lead_time_s"] == pytest.approx(0.7)
    assert m["critical_detected_share"] == 1.0
    assert m["critical_missed"] is False
    assert m["critical_position_error_m"] == pytest.approx(0.5)
    assert m["critical_speed_error_mps"] == pytest.approx(0.0)


def test_detected_late_gives_a_short_lead() -> None:
    m = critical_measures(_approach(10, [False] * 8 + [True] * 2), "foe0")
    assert m["critical_first_detected_frame"] == 8
    assert m["critical_lead_time_s"] == pytest.approx(0.1)


def test_a_track_beside_the_foe_is_not_a_detection() -> None:
    """The left_turn_truck collision: tracks 3.5 m to the foe's side, on the neighbouring lane, all run."""
    m = critical_measures(_approach(10, [True] * 10, offset_m=3.5), "foe0")
    assert 3.5 > MATCH_M
    assert m["critical_missed"] is True
    assert m["critical_first_detected_frame"] is None and m["critical_lead_time_s"] is None
    assert m["critical_conflict_frame"] == 9


def test_never_detected_is_a_miss() -> None:
    m = critical_measures(_approach(6, [False] * 6), "foe0")
    assert m["critical_missed"] is True
    assert m["critical_detected_share"] is None and m["critical_position_error_m"] is None


def test_lost_again_lowers_the_share() -> None:
    seen = [True, True, False, False, False, True, False, False, False, True]
    m = critical_measures(_approach(10, seen), "foe0")
    assert m["critical_first_detected_frame"] == 0
    assert m["critical_detected_share"] == pytest.approx(0.4)


def test_contact_is_the_conflict_and_errors_stop_at_commit() -> None:
    frames = _approach(10, [True] * 10, commit=4)
    # a worse track after the ego has committed does not count in the error; the contact at frame 6 is the conflict
    frames[5] = _frame(5, 5.0, 6.9, gap=5.0, in_junction=True)
    frames[6] = _frame(6, 6.0, 6.5, gap=0.0, in_junction=True, collisions=("foe0",))
    m = critical_measures(frames, "foe0")
    assert m["critical_conflict_frame"] == 6
    assert m["critical_position_error_m"] == pytest.approx(0.5)  # frames 0-4 only
    assert m["critical_lead_time_s"] == pytest.approx(0.6)


def test_speed_error_leaves_out_a_new_track() -> None:
    frames = [_frame(0, 0.0, 0.0, gap=5.0, track_speed=0.0, age=1), _frame(1, 1.0, 1.0, gap=4.0, track_speed=7.0)]
    m = critical_measures(frames, "foe0")
    assert m["critical_speed_error_mps"] == pytest.approx(3.0)


def test_no_critical_actor_gives_null_keys() -> None:
    assert critical_measures(_approach(5, [True] * 5), None) == dict.fromkeys(KEYS)
    assert critical_measures([], "foe0") == dict.fromkeys(KEYS)


def test_the_families_name_their_critical_actor() -> None:
    assert critical_actor(load_scenario("scenarios/left_turn_truck.yaml")) == "foe0"
    assert critical_actor(load_scenario("scenarios/blind_corner_stop.yaml")) == "stopped0"
    assert critical_actor(load_scenario("scenarios/intersection.yaml")) is None
