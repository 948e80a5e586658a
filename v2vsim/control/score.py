"""The driving score of a closed-loop run (metrics.json `driving.vehicles.<id>` and `driving.total`), defined as
the CARLA leaderboard defines it, on the frames one driven vehicle's ego logged (`DrivenFrame`).

- route_completion (0-1): the share of its route (control.route_m from where it was at frame 0, or to the end of its
  SUMO route) behind it when its part of the run ended.
- infractions, counted by kind, each with the leaderboard's multiplicative penalty (CARLA Leaderboard, "Evaluation
  and metrics", leaderboard.carla.org/evaluation_v2_0/; the same coefficients in v1.0):
    collision_vehicle 0.60 for each other vehicle it came into contact with (onsets, as `collisions`);
    red_light 0.70 for entering a junction while the light ahead of it showed red or amber;
    timeout 0.70 (the leaderboard 2.0's "scenario timeout") when the run reached its time limit (the scenario's
      duration) before the route was complete: a vehicle that waits for ever is not safe driving, it is no driving.
  The leaderboard's pedestrian (0.50), static-object (0.65) and stop-sign (0.80) infractions have no counterpart in
  these scenarios (no pedestrians, no static obstacles on the road, SUMO priority junctions without stop signs).
- driving_score = route_completion x the product of the penalties (one factor per infraction).
- success: the route completed and no infraction.
- efficiency (a sweep's, v2vsim/study/driving.py): the oracle's completion time on the same configuration (grid point
  but control.method, seed) over the run's, when both completed their routes: 1 drives as fast as the oracle.

The safety-weighted score (issue 67) beside it, which the CARLA-style score leaves as it is:
- close_call: no collision, yet a serious conflict: SUMO's SSM minimum TTC under CLOSE_CALL["ttc_s"] (1.5 s, the
  conflict threshold of FHWA's Surrogate Safety Assessment Model, Gettman et al., FHWA-HRT-08-051, 2008), or a
  post-encroachment time (SSM's or the trajectories', v2vsim/control/measures.py) under CLOSE_CALL["pet_s"] (1 s,
  the "serious conflict" bound of the PET literature, e.g. Peesapati et al., TRB 2013), or the footprints within
  control.near_miss_gap_m (the gap near miss). The thresholds are fixed here, not per scenario: control.ssm's are
  the SSM device's logging thresholds (SUMO's defaults, TTC 3 s, PET 2 s), looser by design.
- safety_score = driving_score x CLOSE_CALL_PENALTY per close call (at most one per vehicle and run: SSM keeps the
  run's extremes, not each conflict). CLOSE_CALL_PENALTY = sqrt(0.60) = 0.775: a close call costs half a collision
  in the score's log, since it is a collision that did not happen by a margin the driver did not choose. So a drive
  that completes its route by cutting in front of a foe scores below one that completes it cleanly, and a run whose
  only infraction is a collision keeps its CARLA score.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from v2vsim.control.measures import DrivenFrame

PENALTY = {"collision_vehicle": 0.60, "red_light": 0.70, "timeout": 0.70}
CLOSE_CALL = {"ttc_s": 1.5, "pet_s": 1.0}  # a conflict under either bound, without contact, is a close call
CLOSE_CALL_PENALTY = math.sqrt(PENALTY["collision_vehicle"])  # 0.775: half a collision (module doc)
RED_LIGHT_SLACK_M = 1.0  # a red stop line at most this past what the vehicle drove in a step was the one it crossed


def route_completion(frames: Sequence[DrivenFrame]) -> float | None:
    """The share of its route behind it at its last frame (None: no route known, e.g. frames from before routes)."""
    if not frames or frames[-1].route_m is None or frames[-1].route_m <= 0:
        return None
    last = frames[-1]
    return 1.0 if last.finished else min(1.0, max(0.0, last.route_done_m / last.route_m))  # type: ignore[operator]


def red_light_entries(frames: Sequence[DrivenFrame]) -> int:
    """Junctions entered on red or amber: a frame inside a junction after one outside it that had a red or amber
    stop line ahead no farther than it then drove (plus RED_LIGHT_SLACK_M)."""
    n = 0
    for before, now in zip(frames, frames[1:], strict=False):
        if now.in_junction and not before.in_junction and before.red_m is not None:
            if before.red_m <= (now.odometer_m - before.odometer_m) + RED_LIGHT_SLACK_M:
                n += 1
    return n


def infractions(frames: Sequence[DrivenFrame], collisions: int, time_limit_reached: bool) -> dict[str, int]:
    """Counts by kind (every kind of PENALTY, zeros included). `collisions`: the vehicle's collision onsets;
    `time_limit_reached`: the run went on to its last frame (not stopped early by Ctrl-C or a failure)."""
    completion = route_completion(frames)
    timed_out = time_limit_reached and completion is not None and completion < 1.0
    return {"collision_vehicle": collisions, "red_light": red_light_entries(frames), "timeout": int(timed_out)}


def driving_score(completion: float | None, counts: dict[str, int]) -> float | None:
    """route completion x the product of each infraction's penalty (None without a route)."""
    if completion is None:
        return None
    return completion * math.prod(PENALTY[k] ** n for k, n in counts.items())


def score_block(frames: Sequence[DrivenFrame], collisions: int, time_limit_reached: bool) -> dict[str, Any]:
    """The score fields of one vehicle's `driving` entry."""
    completion = route_completion(frames)
    counts = infractions(frames, collisions, time_limit_reached)
    score = driving_score(completion, counts)
    finished = bool(frames) and frames[-1].finished
    return {"driving_score": None if score is None else round(score, 4),
            "route_completion": None if completion is None else round(completion, 4),
            "route_m": frames[-1].route_m if frames else None,
            "success": finished and not any(counts.values()),
            "finished_at_s": round(frames[-1].time, 3) if finished else None,
            "infractions": counts}


def close_call(collisions: int, gap_near_miss: bool, min_ttc_s: float | None,
               pet_s: Sequence[float | None]) -> bool:
    """A serious conflict without contact (module doc): min TTC or any of the PETs (`pet_s`: SSM's, the
    trajectories') under CLOSE_CALL, or the gap near miss. None values are measures SSM did not log."""
    if collisions > 0:
        return False
    if gap_near_miss or (min_ttc_s is not None and min_ttc_s < CLOSE_CALL["ttc_s"]):
        return True
    return any(p is not None and p < CLOSE_CALL["pet_s"] for p in pet_s)


def safety_score(score: float | None, close: bool) -> float | None:
    """The driving score with the close-call penalty (None without a driving score)."""
    return None if score is None else score * (CLOSE_CALL_PENALTY if close else 1.0)


def safety_block(vehicle: dict[str, Any]) -> dict[str, Any]:
    """The safety fields of one vehicle's `driving` entry, from its measures and score block."""
    close = close_call(vehicle["collisions"], bool(vehicle.get("near_miss")), vehicle["ssm"]["min_ttc_s"],
                       (vehicle["ssm"]["min_pet_s"], vehicle.get("pet_s")))
    safety = safety_score(vehicle.get("driving_score"), close)
    return {"close_call": close, "safety_score": None if safety is None else round(safety, 4)}


def total_score(vehicles: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The fleet's: mean driving score and route completion, successes out of vehicles, infractions summed."""
    scored = [v for v in vehicles if v.get("driving_score") is not None]
    counts: dict[str, int] = {k: 0 for k in PENALTY}
    for v in vehicles:
        for k, n in v.get("infractions", {}).items():
            counts[k] = counts.get(k, 0) + n
    safe = [v["safety_score"] for v in scored if v.get("safety_score") is not None]
    return {"driving_score": round(sum(v["driving_score"] for v in scored) / len(scored), 4) if scored else None,
            "safety_score": round(sum(safe) / len(safe), 4) if safe and len(safe) == len(scored) else None,
            "close_calls": sum(1 for v in vehicles if v.get("close_call")),
            "route_completion": (round(sum(v["route_completion"] for v in scored) / len(scored), 4)
                                 if scored else None),
            "success": bool(vehicles) and all(v.get("success") for v in vehicles),
            "successes": sum(1 for v in vehicles if v.get("success")),
            # when the last driven vehicle completed its route (null: one did not); the sweep's efficiency reads it
            "finished_at_s": (max(v["finished_at_s"] for v in vehicles)
                              if vehicles and all(v.get("finished_at_s") is not None for v in vehicles) else None),
            "infractions": counts}
