"""The scenario schema's `control` section (docs/scenario.md "control"): the closed loop, its planner (IDM), SUMO's
SSM device and the thresholds of the driving measures."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from v2vsim.config.schema_fields import _f, _nonneg, _pos, _prob


@dataclass(frozen=True)
class IdmConfig:
    """The planner's car-following law (IDM, Treiber, Hennecke & Helbing 2000) and its limits (v2vsim/control)."""

    desired_speed_mps: float | None = _f(None, "> 0 (m/s) or null (the lane's speed limit)", _pos)
    time_headway_s: float = _f(1.5, "> 0 (s)", _pos)
    min_gap_m: float = _f(2.0, ">= 0 (m, standstill gap)", _nonneg)
    max_accel_mps2: float = _f(2.0, "> 0 (m/s^2)", _pos)
    comfort_decel_mps2: float = _f(3.0, "> 0 (m/s^2)", _pos)
    max_decel_mps2: float = _f(8.0, "> 0 (m/s^2, the hardest braking any command asks)", _pos)
    gap_acceptance_s: float = _f(5.0, "> 0 (s: a crossing vehicle arriving sooner blocks the junction)", _pos)
    # with priority, give way to a crossing vehicle that would need more than violator_decel_mps2 to stop before the
    # junction and meets the ego there (a red-light runner), while the ego can still stop (planner find_violator)
    yield_to_violators: bool = True
    violator_decel_mps2: float = _f(6.0, "> 0 (m/s^2)", _pos)


@dataclass(frozen=True)
class SsmConfig:
    """SUMO's SSM device on each driven vehicle (docs/scenario.md "control"): thresholds below (above, for DRAC)
    which an encounter counts as a conflict, and how far it looks. Defaults are SUMO's."""

    ttc_s: float = _f(3.0, "> 0 (s)", _pos)
    drac_mps2: float = _f(3.0, "> 0 (m/s^2)", _pos)
    pet_s: float = _f(2.0, "> 0 (s)", _pos)
    range_m: float = _f(50.0, "> 0 (m)", _pos)


@dataclass(frozen=True)
class ControlConfig:
    """Closed loop (docs/run.md "The closed loop"): each ego's vehicle is driven by a planner that sees only what
    `method` perceived; absent, the run is open loop exactly as before. The plan of frame k is applied at the
    step after frame k + actuation_delay_frames (lockstep: at least transport.pipeline, the frames the driver may
    run ahead of the ego)."""

    method: str = _f("oracle", "'oracle' (ground truth), or one of perception.methods (e.g. none, late, cobevt)")
    drive: Literal["egos"] = "egos"  # every ego's own vehicle; cavs.ego: all drives every CAV
    planner: Literal["idm"] = "idm"
    actuation_delay_frames: int | None = _f(None, "an integer >= transport.pipeline, or null (the least the "
                                            "pipeline allows)", _nonneg)
    idm: IdmConfig = field(default_factory=IdmConfig)
    ssm: SsmConfig = field(default_factory=SsmConfig)
    hard_brake_mps2: float = _f(4.0, "> 0 (m/s^2: a deceleration at least this hard is a hard-braking event)", _pos)
    near_miss_gap_m: float = _f(1.0, ">= 0 (m: a closest footprint gap at most this, without contact, is a near "
                                "miss)", _nonneg)
    phantom_match_m: float = _f(3.0, "> 0 (m: braking for an obstacle with no vehicle this close to it is "
                                "phantom braking)", _pos)
    # jmIgnoreJunctionFoeProb of the background drivers: 0 = SUMO's attentive drivers, who brake for any vehicle
    # already in the junction (so a driven vehicle that pulls out blindly is rarely hit); 1 = they keep their
    # right of way. A modelling choice: the run's report states it.
    background_ignore_junction_foes: float = _f(0.0, "0..1 (probability)", _prob)
    # The route a driven vehicle must complete (its driving score, v2vsim/control/score.py): this many metres along
    # its SUMO route from where it is at frame 0, or null: to the end of that route. A vehicle that completes it
    # leaves the simulation (it arrived); the run's duration is the time limit.
    route_m: float | None = _f(None, "> 0 (m) or null (to the end of the vehicle's SUMO route)", _pos)
    # What the ego computes: `all` of perception.methods (each scored beside the one it drives on), or only what
    # it `driving` on (perception.methods becomes [method]; oracle: [none], the cheapest map that still scores):
    # a benchmark point pays for one method, not eight (docs/benchmark.md).
    perceive: Literal["all", "driving"] = "all"
