"""The critical-actor measure (issue 65; metrics.json `driving.vehicles.<id>`, keys `critical_*`): did the map the
vehicle drives on hold the one actor its drive depends on, early enough and well enough to plan on?

A family's critical actor is its hidden foe (`traffic.hidden_foe`: foe0) or its stopped car round the corner
(`traffic.hidden_stop`: stopped0); a scenario with neither has none, and every key is null. Per driven vehicle,
from the frames its ego logged (`DrivenFrame.critical`, `.critical_track`):

- **detected** at a frame: one of the planner's tracks *seen in that frame* (not coasting) has its centre within
  MATCH_M = 2 m of the actor's true centre. The planner's tracks, not the decoded boxes or map cells, because they
  are what the drive rests on: a box 3.5 m to the side, on the neighbouring lane, is a different vehicle to the
  planner, and a detection count would have called that map good.
- **conflict frame**: the frame of the vehicle's first contact with the actor, else of its closest approach to it
  (least footprint gap over the frames both are in the run). `critical_conflict_frame`.
- `critical_first_detected_frame`: the first detected frame at or before the conflict (null: a miss,
  `critical_missed` true); `critical_lead_time_s`: conflict time minus that frame's time.
- `critical_detected_share`: the share of frames from the first detection through the conflict in which it is
  detected (1: never lost again).
- **commit frame**: the first frame the vehicle is inside the junction (it has committed to crossing), or the
  conflict frame when it never enters before it. `critical_position_error_m` / `critical_speed_error_mps`: the mean
  distance between the matched track's centre and the truth, and the mean |track speed - true speed|, over the
  detected frames from the first detection up to the commit frame (null: none); a track's first frame has no
  speed yet (the tracker's age 1) and is left out of the speed error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from v2vsim.config import Scenario
from v2vsim.control.measures import DrivenFrame
from v2vsim.traffic.actor_ids import FOE_ID, HIDDEN_STOP_ID

MATCH_M = 2.0  # a track whose centre is this close to the actor's true centre detects it
KEYS = ("critical_actor", "critical_conflict_frame", "critical_first_detected_frame", "critical_lead_time_s",
        "critical_detected_share", "critical_missed", "critical_position_error_m", "critical_speed_error_mps")


def critical_actor(sc: Scenario) -> str | None:
    """The scenario's critical actor's id (module doc), or None."""
    if sc.traffic.hidden_foe is not None:
        return FOE_ID
    if sc.traffic.hidden_stop is not None:
        return HIDDEN_STOP_ID
    return None


def _track_error_m(f: DrivenFrame) -> float | None:
    """Distance from the nearest seen track to the actor's true centre (None: no actor or no track)."""
    if f.critical is None or f.critical_track is None:
        return None
    return math.hypot(f.critical_track[0] - f.critical[0], f.critical_track[1] - f.critical[1])


def _detected(f: DrivenFrame) -> bool:
    err = _track_error_m(f)
    return err is not None and err <= MATCH_M


def critical_measures(frames: Sequence[DrivenFrame], actor: str | None) -> dict[str, Any]:
    """The `critical_*` keys of one driven vehicle (module doc); all null without a critical actor or frames with
    it."""
    out: dict[str, Any] = dict.fromkeys(KEYS)
    present = [f for f in frames if f.critical is not None]
    if actor is None or not present:
        return out
    out["critical_actor"] = actor
    contact = next((f for f in present if actor in f.collisions), None)
    conflict = contact or min(present, key=lambda f: (f.critical[3], f.frame))
    upto = [f for f in present if f.frame <= conflict.frame]
    first = next((f for f in upto if _detected(f)), None)
    out["critical_conflict_frame"] = conflict.frame
    out["critical_missed"] = first is None
    if first is None:
        return out
    out["critical_first_detected_frame"] = first.frame
    out["critical_lead_time_s"] = round(conflict.time - first.time, 3)
    since = [f for f in upto if f.frame >= first.frame]
    out["critical_detected_share"] = round(sum(_detected(f) for f in since) / len(since), 4)
    commit = next((f.frame for f in since if f.in_junction), conflict.frame)
    judged = [f for f in since if f.frame <= commit and _detected(f)]
    pos = [_track_error_m(f) for f in judged]
    speed = [abs(f.critical_track[2] - f.critical[2]) for f in judged if f.critical_track[3] > 1]
    out["critical_position_error_m"] = round(sum(pos) / len(pos), 3) if pos else None
    out["critical_speed_error_mps"] = round(sum(speed) / len(speed), 3) if speed else None
    return out


def critical_total(vehicles: dict[str, dict[str, Any]], ego: str) -> dict[str, Any]:
    """`driving.total`'s critical keys: the ego's own (the family's critical actor is hidden from it; the other
    driven vehicles' are in `vehicles`). Null keys where it has none."""
    mine = vehicles.get(ego) or {}
    return {k: mine.get(k) for k in KEYS}
