"""The driving score (v2vsim/control/score.py) on hand-made frames: route completion, the leaderboard's penalties
multiplied per infraction, a timeout only when the run reached its time limit, red-light entries, success; the
close call and the safety-weighted score on hand-made SSM figures."""

from __future__ import annotations

from dataclasses import replace

import pytest

from v2vsim.control.measures import DrivenFrame, vehicle_measures
from v2vsim.control.score import (
    CLOSE_CALL_PENALTY,
    PENALTY,
    driving_score,
    red_light_entries,
    safety_block,
    score_block,
    total_score,
)

DT = 0.1


def _frames(n: int, route_m: float = 50.0, step_m: float = 1.0, finish: bool = False,
            red: dict[int, float] | None = None, junction_from: int | None = None) -> list[DrivenFrame]:
    """n frames driving step_m a frame along a route of route_m; `finish`: the last frame completes it."""
    out = []
    for k in range(n):
        done = min(route_m, k * step_m)
        out.append(DrivenFrame(frame=k, time=k * DT, x=k * step_m, y=0.0, yaw=0.0, speed=step_m / DT,
                               odometer_m=k * step_m, in_junction=junction_from is not None and k >= junction_from,
                               collisions=(), ssm=(None, None, None), min_gap_m=5.0, closest=None,
                               commanded_speed=None, reason="free", phantom=False, red_m=(red or {}).get(k),
                               route_m=route_m, route_done_m=done, finished=finish and k == n - 1))
    return out


def test_a_completed_route_without_infractions_scores_one_and_succeeds() -> None:
    b = score_block(_frames(51, finish=True), collisions=0, time_limit_reached=True)
    assert b["driving_score"] == 1.0 and b["route_completion"] == 1.0 and b["success"] is True
    assert b["infractions"] == {"collision_vehicle": 0, "red_light": 0, "timeout": 0}
    assert b["finished_at_s"] == pytest.approx(5.0)


def test_each_collision_multiplies_by_0_6() -> None:
    b = score_block(_frames(51, finish=True), collisions=2, time_limit_reached=True)
    assert b["driving_score"] == pytest.approx(0.36) and b["success"] is False
    assert b["infractions"]["collision_vehicle"] == 2


def test_a_route_unfinished_at_the_time_limit_is_a_timeout() -> None:
    b = score_block(_frames(21), collisions=0, time_limit_reached=True)  # 20 of 50 m when the run ended
    assert b["route_completion"] == pytest.approx(0.4) and b["infractions"]["timeout"] == 1
    assert b["driving_score"] == pytest.approx(0.4 * PENALTY["timeout"]) and b["success"] is False


def test_a_run_stopped_early_is_no_timeout() -> None:
    b = score_block(_frames(21), collisions=0, time_limit_reached=False)  # Ctrl-C: it did not run out of time
    assert b["infractions"]["timeout"] == 0 and b["driving_score"] == pytest.approx(0.4)
    assert b["success"] is False  # not completed


def test_collision_and_timeout_multiply() -> None:
    b = score_block(_frames(11), collisions=1, time_limit_reached=True)
    assert b["driving_score"] == pytest.approx(0.2 * 0.6 * 0.7)


def test_entering_a_junction_on_red_is_an_infraction_and_a_far_red_light_is_not() -> None:
    # frame 4 has a red stop line 0.5 m ahead, frame 5 is inside the junction: it ran the light
    assert red_light_entries(_frames(10, red={4: 0.5}, junction_from=5)) == 1
    # the red light is 30 m further on (a later junction): entering this one is no infraction
    assert red_light_entries(_frames(10, red={4: 30.0}, junction_from=5)) == 0
    b = score_block(_frames(51, finish=True, red={4: 0.5}, junction_from=5), collisions=0, time_limit_reached=True)
    assert b["driving_score"] == pytest.approx(0.7) and not b["success"]


def test_no_route_no_score() -> None:
    assert driving_score(None, {"timeout": 0}) is None
    frames = [f.__class__(**{**f.__dict__, "route_m": None}) for f in _frames(3)]
    assert score_block(frames, collisions=0, time_limit_reached=True)["driving_score"] is None


def test_the_fleet_total_averages_scores_and_counts_successes() -> None:
    a = score_block(_frames(51, finish=True), collisions=0, time_limit_reached=True)
    b = score_block(_frames(21), collisions=1, time_limit_reached=True)
    t = total_score([a, b])
    assert t["driving_score"] == pytest.approx((1.0 + 0.4 * 0.6 * 0.7) / 2, abs=1e-4)
    assert t["successes"] == 1 and t["success"] is False
    assert t["infractions"] == {"collision_vehicle": 1, "red_light": 0, "timeout": 1}


def _scored(frames: list[DrivenFrame], collisions: int = 0) -> dict:
    """One vehicle's `driving` entry as the ego writes it (agents/ego_finish.py): measures, score, safety."""
    per = vehicle_measures(frames, DT, hard_brake=4.0, near_miss_gap=1.0, ssm_count=0)
    per |= score_block(frames, collisions, time_limit_reached=True)
    return per | safety_block(per)


def _with_ssm(frames: list[DrivenFrame], ttc: float | None, pet: float | None,
              gap: float = 5.0) -> list[DrivenFrame]:
    """SUMO's SSM device as the driver reads it each frame: the run's min TTC, max DRAC, min PET so far."""
    return [replace(f, ssm=(ttc, 1.0, pet), min_gap_m=gap) for f in frames]


def test_a_clean_drive_has_no_close_call_and_keeps_its_score() -> None:
    b = _scored(_with_ssm(_frames(51, finish=True), ttc=2.5, pet=1.6))  # conflicts, but not serious ones
    assert b["close_call"] is False and b["safety_score"] == b["driving_score"] == 1.0


@pytest.mark.parametrize(("ttc", "pet", "gap"), [(1.2, None, 5.0), (None, 0.6, 5.0), (2.5, 1.6, 0.5)])
def test_a_serious_conflict_without_contact_is_a_close_call(ttc: float | None, pet: float | None,
                                                             gap: float) -> None:
    b = _scored(_with_ssm(_frames(51, finish=True), ttc=ttc, pet=pet, gap=gap))
    assert b["success"] is True and b["driving_score"] == 1.0  # the CARLA-style score does not see it
    assert b["close_call"] is True and b["safety_score"] == pytest.approx(CLOSE_CALL_PENALTY, abs=1e-4)
    assert CLOSE_CALL_PENALTY == pytest.approx(PENALTY["collision_vehicle"] ** 0.5)


def test_a_collision_is_no_close_call_and_is_penalised_once() -> None:
    frames = _with_ssm(_frames(51, finish=True), ttc=0.0, pet=0.0, gap=0.0)
    frames[30] = replace(frames[30], collisions=("foe",))  # SUMO's contact, as the driver reports it
    b = _scored(frames, collisions=1)
    assert b["collisions"] == 1
    assert b["close_call"] is False and b["safety_score"] == b["driving_score"] == pytest.approx(0.6)


def test_a_completed_drive_through_a_close_call_scores_below_a_clean_wait_in_safety_only() -> None:
    # the lie study's case (issue 67): a lie that makes the ego cross just behind the foe completes the route,
    # while the honest ego is still waiting when the run ends (a timeout on 40 % of the route)
    lie = _scored(_with_ssm(_frames(51, finish=True), ttc=None, pet=0.4))
    honest = _scored(_with_ssm(_frames(21), ttc=None, pet=None))
    assert lie["driving_score"] > honest["driving_score"]
    assert lie["safety_score"] == pytest.approx(0.775, abs=1e-3) and honest["safety_score"] == pytest.approx(0.28)
    t = total_score([lie, honest])
    assert t["close_calls"] == 1 and t["safety_score"] == pytest.approx((0.7746 + 0.28) / 2, abs=1e-3)
