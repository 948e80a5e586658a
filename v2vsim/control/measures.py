"""What a closed-loop run did to the driving (metrics.json `driving`, docs/scenario.md "control"): per driven
vehicle, from the frames its ego logged (`DrivenFrame`) and what SUMO's SSM device wrote.

Definitions (each figure is per driven vehicle; `total` adds counts and takes the extreme of the others):
- collisions: contacts SUMO detected (on lanes and in junctions), counted once per other vehicle and onset.
- near miss: no collision, and the closest gap between its footprint and any other vehicle's <= near_miss_gap_m.
- ssm: SUMO's SSM device (min TTC, max DRAC, min PET over its encounters; `conflicts`: the encounters its log holds
  with a measure past a threshold). SUMO treats conflict areas as orthogonal lanes and ignores lateral conflicts.
- pet_s: post-encroachment time measured from the trajectories: the least time between this vehicle and another
  one crossing its path (heading differing by more than 30 degrees) occupying the same spot (centres within
  1.5 m), over the run. A check on SSM's PET, which can miss crossing encounters.
- hard braking: onsets of frames decelerating at hard_brake_mps2 or more.
- phantom braking: onsets of frames where the planner braked (decelerating at more than its comfortable rate)
  for an obstacle that no vehicle is within phantom_match_m of: a false positive that cost something.
- time_to_clear_s: when it first left the junction it had entered (null: it never did); progress_m: the
  distance it drove.
- peak_jerk_mps3: the largest change of its acceleration between two steps, per second (comfort).
The driving score, route completion, success and infractions beside these: v2vsim/control/score.py.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

CROSSING_DEG = 30.0  # paths whose headings differ by more than this cross (PET); less: one follows the other
SAME_SPOT_M = 1.5  # two centres this close occupy the same spot (PET)


@dataclass(frozen=True)
class DrivenFrame:
    """One frame of one driven vehicle as its ego saw it (world truth + its own plan)."""

    frame: int
    time: float
    x: float
    y: float
    yaw: float
    speed: float
    odometer_m: float
    in_junction: bool
    collisions: tuple[str, ...]
    ssm: tuple[float | None, float | None, float | None]
    min_gap_m: float | None  # closest footprint gap to any other vehicle (None: no other vehicle)
    closest: str | None
    commanded_speed: float | None  # the plan made on this frame's perception
    reason: str | None  # free | leader | yield | stop_line
    phantom: bool  # braking for an obstacle no vehicle is near
    others: tuple[tuple[str, float, float, float], ...] = ()  # (id, x, y, yaw) of vehicles within 40 m
    red_m: float | None = None  # a red or amber light's stop line ahead (v2vsim.control.score: red-light entries)
    route_m: float | None = None  # its route (control.route_m) and how much of it is behind it (the driving score)
    route_done_m: float = 0.0
    finished: bool = False  # it completed its route at this frame
    # the scenario's critical actor (v2vsim/control/critical.py): its truth (x, y, speed, footprint gap to this
    # vehicle) and the planner's track seen this frame nearest to it (x, y, speed, age); None: absent / no track
    critical: tuple[float, float, float, float] | None = None
    critical_track: tuple[float, float, float, int] | None = None


def _onsets(flags: Sequence[bool]) -> int:
    return sum(1 for i, f in enumerate(flags) if f and (i == 0 or not flags[i - 1]))


def _collisions(frames: Sequence[DrivenFrame]) -> tuple[int, list[str], int | None]:
    count, first, seen = 0, None, set()
    before: set[str] = set()
    for f in frames:
        now = set(f.collisions)
        new = now - before
        count += len(new)
        seen |= now
        if new and first is None:
            first = f.frame
        before = now
    return count, sorted(seen), first


def trajectory_pet(frames: Sequence[DrivenFrame]) -> float | None:
    """The least time between this vehicle and a crossing one at the same spot (see the module doc)."""
    if not frames:
        return None
    own = np.array([(f.time, f.x, f.y, f.yaw) for f in frames])
    tracks: dict[str, list[tuple[float, float, float, float]]] = {}
    for f in frames:
        for oid, x, y, yaw in f.others:
            tracks.setdefault(oid, []).append((f.time, x, y, yaw))
    best: float | None = None
    for rows in tracks.values():
        o = np.asarray(rows)
        d = np.hypot(own[:, None, 1] - o[None, :, 1], own[:, None, 2] - o[None, :, 2])  # [own, other]
        dyaw = np.abs((own[:, None, 3] - o[None, :, 3] + math.pi) % (2 * math.pi) - math.pi)
        hit = (d <= SAME_SPOT_M) & (dyaw > math.radians(CROSSING_DEG))
        if hit.any():
            dt = np.abs(own[:, None, 0] - o[None, :, 0])[hit].min()
            best = float(dt) if best is None else min(best, float(dt))
    return best


def ssm_conflicts(path: Path | None) -> dict[str, int]:
    """Per vehicle, the conflicts SUMO's SSM log holds for it as the equipped vehicle (empty: no log)."""
    if path is None or not path.is_file():
        return {}
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError:  # cut short (SUMO killed): nothing trustworthy in it
        return {}
    out: dict[str, int] = {}
    for c in root.iter("conflict"):
        ego = c.get("ego")
        if ego:
            out[ego] = out.get(ego, 0) + 1
    return out


def vehicle_measures(frames: Sequence[DrivenFrame], dt: float, hard_brake: float, near_miss_gap: float,
                     ssm_count: int | None) -> dict[str, Any]:
    """The driving measures of one driven vehicle over its frames (module doc)."""
    if not frames:
        return {"frames": 0}
    collisions, victims, first = _collisions(frames)
    gaps = [f.min_gap_m for f in frames if f.min_gap_m is not None]
    min_gap = min(gaps) if gaps else None
    speeds = np.array([f.speed for f in frames])
    accel = np.r_[0.0, np.diff(speeds) / dt]
    entered = cleared = None
    for f in frames:
        if f.in_junction and entered is None:
            entered = f.time
        if entered is not None and not f.in_junction:
            cleared = f.time
            break
    ttc, drac, pet = frames[-1].ssm
    return {
        "frames": len(frames),
        "collisions": collisions,
        "collided_with": victims,
        "first_collision_frame": first,
        "near_miss": collisions == 0 and min_gap is not None and min_gap <= near_miss_gap,
        "min_gap_m": None if min_gap is None else round(min_gap, 3),
        "ssm": {"conflicts": ssm_count, "min_ttc_s": ttc, "max_drac_mps2": drac, "min_pet_s": pet},
        "pet_s": trajectory_pet(frames),
        "hard_braking": _onsets([bool(a <= -hard_brake) for a in accel]),
        "phantom_braking": _onsets([f.phantom for f in frames]),
        "max_decel_mps2": round(float(max(0.0, -accel.min())), 3),
        "peak_jerk_mps3": round(float(np.abs(np.diff(accel[1:])).max() / dt), 3) if len(accel) > 2 else 0.0,
        "time_to_clear_s": cleared,
        "progress_m": round(frames[-1].odometer_m - frames[0].odometer_m, 3),
        "mean_speed_mps": round(float(speeds.mean()), 3),
        "yielding_frames": sum(1 for f in frames if f.reason == "yield"),
    }


def _least(values: list[Any]) -> Any:
    vals = [v for v in values if v is not None]
    return min(vals) if vals else None


def driving_block(per_vehicle: dict[str, dict[str, Any]], header: dict[str, Any]) -> dict[str, Any]:
    """metrics.json `driving`: the run's control settings (`header`), each driven vehicle, and the total."""
    vs = [v for v in per_vehicle.values() if v.get("frames")]
    total = {
        "collisions": sum(v["collisions"] for v in vs),
        "near_misses": sum(1 for v in vs if v["near_miss"]),
        "hard_braking": sum(v["hard_braking"] for v in vs),
        "phantom_braking": sum(v["phantom_braking"] for v in vs),
        "min_gap_m": _least([v["min_gap_m"] for v in vs]),
        "min_ttc_s": _least([v["ssm"]["min_ttc_s"] for v in vs]),
        "max_drac_mps2": max((v["ssm"]["max_drac_mps2"] for v in vs if v["ssm"]["max_drac_mps2"] is not None),
                             default=None),
        "min_pet_s": _least([v["ssm"]["min_pet_s"] for v in vs]),
        "pet_s": _least([v["pet_s"] for v in vs]),
        "ssm_conflicts": (None if any(v["ssm"]["conflicts"] is None for v in vs)
                          else sum(v["ssm"]["conflicts"] for v in vs)),
        "time_to_clear_s": (None if not vs or any(v["time_to_clear_s"] is None for v in vs)
                            else max(v["time_to_clear_s"] for v in vs)),
        "progress_m": round(sum(v["progress_m"] for v in vs), 3),
    }
    return {**header, "vehicles": per_vehicle, "total": total}
