"""The ego's side of the closed loop (docs/run.md "The closed loop"): on each fused frame, the driven vehicle's
planner reads what `control.method` perceived (or the ground truth, for `oracle`), tracks it, plans a speed, and
logs the frame for the driving measures. The command goes back to the driver with the ego's ack.

What the planner knows: its own pose and speed (perfect localisation), its route ahead (map knowledge, from the
world message) and the method's decoded output in the ego frame at the frame's fusion time: boxes where the
method has a detection head (LiDAR), else the blobs of its BEV vehicle map. Nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from v2vsim.config import Scenario
from v2vsim.control.critical import critical_actor
from v2vsim.control.measures import DrivenFrame
from v2vsim.control.perceived import Obstacle, obstacles_from_bev, obstacles_from_boxes, obstacles_from_truth
from v2vsim.control.planner import Plan, PlannerConfig, RouteAhead, plan
from v2vsim.control.tracking import Track, track
from v2vsim.perception.fuse import Prediction
from v2vsim.world.geometry import BevGrid
from v2vsim.world.state import Actor, WorldState

SELF_M = 2.5  # a perceived obstacle centred this close to the vehicle's own centre is the vehicle itself
NEAR_M = 40.0  # other vehicles this close are kept per frame for the trajectory PET


def planner_config(sc: Scenario) -> PlannerConfig:
    assert sc.control is not None
    i = sc.control.idm
    return PlannerConfig(desired_speed=i.desired_speed_mps, time_headway_s=i.time_headway_s, min_gap_m=i.min_gap_m,
                         max_accel=i.max_accel_mps2, comfort_decel=i.comfort_decel_mps2,
                         max_decel=i.max_decel_mps2, gap_acceptance_s=i.gap_acceptance_s,
                         yield_to_violators=i.yield_to_violators, violator_decel=i.violator_decel_mps2)


@dataclass(frozen=True)
class PilotStep:
    """One frame of the loop, for the recording: the plan, the tracks it rested on, and the logged frame."""

    plan: Plan
    tracks: tuple[Track, ...]
    logged: DrivenFrame


def _footprint(a: Actor) -> shapely.Polygon:
    return shapely.Polygon(a.footprint())


def _closest(me: Actor, others: list[Actor]) -> tuple[float | None, str | None]:
    if not others:
        return None, None
    mine = _footprint(me)
    gaps = [(float(mine.distance(_footprint(o))), o.id) for o in others]
    gap, oid = min(gaps)
    return gap, oid


class Pilot:
    """The planner of one driven vehicle (the ego's own) and its frame log."""

    def __init__(self, sc: Scenario, me: str) -> None:
        assert sc.control is not None
        self.control = sc.control
        self.me = me
        self.dt = sc.dt
        self.grid = BevGrid(sc.bev.size_m, sc.bev.cells)
        self.cfg = planner_config(sc)
        self.tracks: tuple[Track, ...] = ()
        self._next_id = 0
        self.frames: list[DrivenFrame] = []
        self.critical = critical_actor(sc)  # the actor the critical-actor measure follows (None: none)

    def perceived(self, world: WorldState, pred: Prediction | None) -> tuple[Obstacle, ...]:
        """What the method saw, in the world frame (oracle: every other vehicle)."""
        me = world.actor(self.me)
        assert me is not None
        if self.control.method == "oracle" or pred is None:
            return obstacles_from_truth(world.actors, self.me) if self.control.method == "oracle" else ()
        if pred.boxes is not None:
            return obstacles_from_boxes(pred.boxes, me.pose)
        return obstacles_from_bev(pred.probs["vehicle"], self.grid, me.pose)

    def step(self, world: WorldState, pred: Prediction | None) -> PilotStep | None:
        """Plan on this frame; None when the vehicle is not driven here (absent, or not in the world's list)."""
        me = world.actor(self.me)
        state = next((d for d in world.driven if d.id == self.me), None)
        if me is None or state is None:
            return None
        # its own vehicle, as a neighbour's late output or a blob of the map shows it, is no obstacle
        seen = tuple(o for o in self.perceived(world, pred)
                     if np.hypot(o.x - me.pose.x, o.y - me.pose.y) > max(SELF_M, me.extent[0] / 2))
        self.tracks, self._next_id = track(self.tracks, seen, self.dt, self._next_id)
        route = RouteAhead(path=state.path, speed_limit=state.speed_limit, stop_m=state.stop_m,
                           conflict_zone=state.conflict_zone, red_m=state.red_m)
        p = plan(me.pose, me.speed, me.extent[0], route, self.tracks, self.cfg, self.dt)
        others = [a for a in world.actors if a.id != self.me]
        phantom = False
        if p.obstacle is not None and p.accel < -self.cfg.comfort_decel:
            ob = np.array([p.obstacle.x, p.obstacle.y])
            phantom = not any(float(np.hypot(*(np.array([a.pose.x, a.pose.y]) - ob))) <= self.control.phantom_match_m
                              for a in others)
        gap, closest = _closest(me, others)
        near = tuple((a.id, a.pose.x, a.pose.y, a.pose.yaw) for a in others
                     if np.hypot(a.pose.x - me.pose.x, a.pose.y - me.pose.y) <= NEAR_M)
        crit, crit_track = self._critical(world, me)
        logged = DrivenFrame(frame=world.frame, time=world.time, x=me.pose.x, y=me.pose.y, yaw=me.pose.yaw,
                             speed=me.speed, odometer_m=state.odometer_m, in_junction=state.in_junction,
                             collisions=state.collisions, ssm=state.ssm, min_gap_m=gap, closest=closest,
                             commanded_speed=p.speed, reason=p.reason, phantom=phantom, others=near,
                             red_m=state.red_m, route_m=state.route_m, route_done_m=state.route_done_m,
                             finished=state.finished, critical=crit, critical_track=crit_track)
        self.frames.append(logged)
        return PilotStep(plan=p, tracks=self.tracks, logged=logged)

    def _critical(self, world: WorldState, me: Actor) -> tuple[tuple[float, float, float, float] | None,
                                                              tuple[float, float, float, int] | None]:
        """The critical actor's truth and the nearest track seen this frame (DrivenFrame.critical*)."""
        actor = world.actor(self.critical) if self.critical is not None else None
        if actor is None:
            return None, None
        truth = (actor.pose.x, actor.pose.y, actor.speed, float(_footprint(me).distance(_footprint(actor))))
        seen = [t for t in self.tracks if t.missed == 0]
        if not seen:
            return truth, None
        t = min(seen, key=lambda t: (np.hypot(t.x - actor.pose.x, t.y - actor.pose.y), t.id))
        return truth, (t.x, t.y, float(np.hypot(t.vx, t.vy)), t.age)
