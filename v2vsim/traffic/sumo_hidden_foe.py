"""The hidden foe for the SUMO backend (`traffic.hidden_foe`): one main-road vehicle, `foe0`, that buildings
hide from the ego while it approaches its stop line, timed to arrive just after the ego does.

Why: at a priority junction the ego (cav0, on the minor road: sumo_placement puts it there) must yield. A foe it
cannot see, but the CAVs on the main road can, is the encounter where planning on cooperative perception and
planning on the ego's own perception part ways.

What is placed, and how (deterministic per seed; nothing here touches the background stream's generator):
1. Side: `left` / `right` is the main-road arm on that side of the ego's heading into the junction, `opposite` the
   arm straight ahead of it (oncoming traffic, for an ego that turns left across it). `auto` is the
   one whose approach buildings hide best from the ego's approach: 2D sight lines from points on the ego's lane
   (its stop line and up to 20 m before it) to points on that arm's near lane (15-90 m before the junction) are
   tested against the building footprints, and the arm with the larger blocked share wins (a tie: the arm whose
   near lane the ego reaches first, the one every movement out of the minor road crosses or joins).
2. Lane and route: the foe drives straight through the junction in the lane of that arm nearest the ego's stop
   line (the first lane the ego crosses or joins).
3. Timing: at free-flow speed its front reaches the junction outline (the end of its approach lane, where the
   junction's conflict area begins; sumolib `net.getNode(junction).getShape()`) `offset` seconds after the ego's
   free-flow arrival at its stop line (the ego's plan from insert_cavs: distance / free-flow speed), `offset` drawn
   once per seed in `arrival_offset_s`. Like the CAVs (sumo_placement.insert_cavs) it is inserted one step before
   frame 0 at `v * t` before the junction, at a spot SUMO will accept (a follower that can brake in time) and where
   no leader in its lane, background or CAV (those inserted in the same step included), would hold it up: one
   going straight must reach the junction `_HEADWAY_S` before it, one turning off there `_TURNING_HEADWAY_S`
   before it (it slows for the turn). Spots by preference: the near lane within `_TIMING_SLACK_S` of driving of
   the wanted spot, then the arm's other straight lanes within it, then the spot nearest the wanted timing in any
   of them. It keeps its lane (lane-change mode 0), so nothing but traffic ahead shifts its timing. The ego's
   free-flow arrival does not know about traffic queued ahead of the ego: behind a yielding leader the ego is late
   and the foe passes before it reaches its stop line.
4. Type: a copy of the background car with no driver imperfection and no speed spread (its timing must follow the
   plan); `speed_mps` sets its free-flow speed (else the lane's limit). `attentive: false` (the default) sets
   `junctionModel.jmIgnoreJunctionFoeProb=1` on it: SUMO's priority-road drivers otherwise brake for any vehicle
   already inside the junction, so a minor-road vehicle that pulls out in front of them never ends in a collision
   (measured with libsumo 1.28 on the T-junction; the bare key `jmIgnoreJunctionFoeProb` is stored but has no effect,
   only the `junctionModel.` form does). It is a modelling choice: a driver who does not react to a car pulling out.
   `jmIgnoreFoeProb` is not set: it concerns foes that have right of way, which the foe never meets on the priority
   road. `runs_red: true` sets `junctionModel.jmDriveAfterRedTime` to an hour: it drives through its red light as
   if it were green (a red-light runner; the ego, on the cross street, has green and the priority).

The backend calls `insert_hidden_foe` in every launch, look-ahead runs included, so the CAV placement is chosen in
the traffic the run will have.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Literal

import numpy as np
import shapely
import sumolib

from v2vsim.config import ConfigError, Scenario
from v2vsim.traffic.actor_ids import FOE_ID
from v2vsim.traffic.sumo_network import Arm, Route, Topology
from v2vsim.traffic.sumo_placement import _FOLLOWER_DECEL, CavPlan, _lanes_for, meet_ref
from v2vsim.world.geometry import wrap_angle
from v2vsim.world.state import Building

Side = Literal["left", "right", "opposite"]

FOE_TYPE = "foe"
_TIMING_SLACK_S = 1.0  # the foe's spot may move by this much driving time when the exact one is taken
# A leader in the foe's lane must reach the junction this much earlier, or the foe catches up with it; one that
# turns there slows to about half the foe's speed first, and must be further ahead.
_HEADWAY_S = 2.0
_TURNING_HEADWAY_S = 3.5
_ENTRY_CLEARANCE_M = 40.0  # as for the CAVs: background vehicles enter an edge's start at full speed
_SIDE_ARC = math.radians(35.0)  # arms within this of straight ahead (or behind) are on neither side
_VIEW_BACK_M = (0.0, 5.0, 10.0, 15.0, 20.0)  # ego viewpoints before its stop line, for side auto
_TARGET_BACK_M = tuple(float(d) for d in range(15, 91, 5))  # foe positions before the junction, for side auto


@dataclass(frozen=True)
class FoePlan:
    """Where and when foe0 was inserted, and why there."""

    side: Side
    route: Route
    lane: int  # lane index on route.edges[0]
    depart_pos: float  # front-bumper position on route.edges[0], m
    to_junction_m: float  # distance from its front to the junction outline at insertion
    speed: float  # its free-flow speed, m/s
    ego: str  # the ego it is timed against
    ego_arrival_s: float  # the ego's free-flow time to its stop line
    offset_s: float  # drawn in arrival_offset_s
    arrival_s: float  # its own free-flow time to the junction (ego_arrival_s + offset_s unless the spot moved)


def draw_offset(seed: int, window: tuple[float, float]) -> float:
    """The seed's arrival offset in `window`, from a generator of its own (the background stream stays untouched)."""
    lo, hi = window
    return float(np.random.default_rng([int(seed), 0xF0E]).uniform(lo, hi))


def sight_blocked(a: tuple[float, float], b: tuple[float, float], buildings: tuple[Building, ...]) -> bool:
    """True when the 2D segment a-b crosses or touches a building footprint (buildings are tall prisms: a sensor
    or driver at car height never sees over them)."""
    line = shapely.LineString([a, b])
    return any(line.intersects(shapely.Polygon(bd.polygon)) for bd in buildings)


def side_of(ego_arm: Arm, arm: Arm) -> Side | None:
    """Which side of the ego's heading into the junction `arm` leaves on; None straight ahead or behind."""
    heading = ego_arm.bearing + math.pi
    rel = float(wrap_angle(arm.bearing - heading))
    if abs(rel) < _SIDE_ARC or abs(rel) > math.pi - _SIDE_ARC:
        return None
    return "left" if rel > 0 else "right"


def _point_before_end(shape: list[tuple[float, ...]], back: float) -> tuple[float, float]:
    """The point `back` metres before the end of a lane's centre line (its start if the lane is shorter)."""
    line = shapely.LineString([(p[0], p[1]) for p in shape])
    p = line.interpolate(max(0.0, line.length - back))
    return float(p.x), float(p.y)


def _straight(arm: Arm) -> Route:
    for r in arm.routes:
        if r.movement == "straight":
            return r
    raise ValueError(f"traffic.hidden_foe: arm {arm.approach} has no straight route through the junction")


def _near_lanes(net: sumolib.net.Net, route: Route, stop: tuple[float, float]) -> list[int]:
    """The lanes of the route's approach that lead to its exit, the one ending nearest `stop` first."""
    approach = net.getEdge(route.approach)

    def dist(i: int) -> float:
        end = approach.getLane(i).getShape()[-1]
        return math.hypot(end[0] - stop[0], end[1] - stop[1])

    return sorted(_lanes_for(net, route), key=lambda i: (dist(i), i))


def _ego_lane_shape(net: sumolib.net.Net, plan: CavPlan) -> list[tuple[float, ...]]:
    approach = net.getEdge(plan.route.approach)
    return approach.getLane(min(plan.lane, approach.getLaneNumber() - 1)).getShape()


def foe_arm(net: sumolib.net.Net, topology: Topology, ego: CavPlan, buildings: tuple[Building, ...],
            side: str) -> tuple[Side, Arm]:
    """The arm the foe comes from (see module doc, 1): `side` is auto, left, right or opposite. Only arms with a
    straight route through the junction count; with several on one side, the one nearest a right angle to the
    ego's heading; opposite: the one nearest straight ahead, within _SIDE_ARC."""
    ego_arm = next(a for a in topology.arms if a.approach == ego.route.approach)
    heading = ego_arm.bearing + math.pi
    if side == "opposite":
        ahead = [a for a in topology.arms if a is not ego_arm and any(r.movement == "straight" for r in a.routes)
                 and abs(float(wrap_angle(a.bearing - heading))) < _SIDE_ARC]
        if not ahead:
            raise ValueError(f"traffic.hidden_foe.side: no arm with a straight route opposite the ego's approach "
                             f"{ego_arm.approach}")
        return "opposite", min(ahead, key=lambda a: abs(float(wrap_angle(a.bearing - heading))))
    sides: dict[Side, Arm] = {}
    for a in sorted(topology.arms, key=lambda a: abs(abs(float(wrap_angle(a.bearing - heading))) - math.pi / 2)):
        s = side_of(ego_arm, a) if a is not ego_arm else None
        if s is not None and any(r.movement == "straight" for r in a.routes):
            sides.setdefault(s, a)
    lateral: tuple[Side, ...] = ("left", "right")
    for s in lateral:
        if side == s:
            if s not in sides:
                raise ValueError(f"traffic.hidden_foe.side: no arm with a straight route to the {s} of the ego's "
                                 f"approach {ego_arm.approach}")
            return s, sides[s]
    if not sides:
        raise ValueError(f"traffic.hidden_foe: no arm with a straight route to the left or right of the ego's "
                         f"approach {ego_arm.approach}")
    ego_shape = _ego_lane_shape(net, ego)
    stop = (float(ego_shape[-1][0]), float(ego_shape[-1][1]))
    views = [_point_before_end(ego_shape, d) for d in _VIEW_BACK_M]
    polys = shapely.polygons([np.asarray(b.polygon, dtype=float) for b in buildings]) if buildings else None

    def score(item: tuple[Side, Arm]) -> tuple[float, float]:
        route = _straight(item[1])
        lane = _near_lanes(net, route, stop)[0]
        shape = net.getEdge(route.approach).getLane(lane).getShape()
        targets = [_point_before_end(shape, d) for d in _TARGET_BACK_M]
        lines = shapely.linestrings([[v, t] for v in views for t in targets])
        blocked = 0.0
        if polys is not None:
            blocked = float(shapely.intersects(lines[:, None], polys[None, :]).any(axis=1).mean())
        end = shape[-1]
        return blocked, -math.hypot(end[0] - stop[0], end[1] - stop[1])

    return max(sides.items(), key=score)


def _define_foe_type(ls: ModuleType, base_type: str, attentive: bool, speed_mps: float | None = None,
                     runs_red: bool = False) -> None:
    """The foe's vType: the background car without imperfection or speed spread (see module doc, 4); with
    `speed_mps` its maximum speed, and a speed factor that lets it reach that speed above the lane's limit too;
    `runs_red`: it drives through any light that has been red for less than an hour, at full speed."""
    ls.vehicletype.copy(base_type, FOE_TYPE)
    ls.vehicletype.setImperfection(FOE_TYPE, 0.0)
    ls.vehicletype.setSpeedDeviation(FOE_TYPE, 0.0)
    if speed_mps is not None:  # free-flow speed = min(lane limit x factor, max speed) = speed_mps (limit >= 10 m/s)
        ls.vehicletype.setMaxSpeed(FOE_TYPE, speed_mps)
        ls.vehicletype.setSpeedFactor(FOE_TYPE, 4.0)
    if not attentive:
        ls.vehicletype.setParameter(FOE_TYPE, "junctionModel.jmIgnoreJunctionFoeProb", "1")
    if runs_red:
        ls.vehicletype.setParameter(FOE_TYPE, "junctionModel.jmDriveAfterRedTime", "3600")
        ls.vehicletype.setParameter(FOE_TYPE, "junctionModel.jmIgnoreFoeProb", "1")
        ls.vehicletype.setParameter(FOE_TYPE, "junctionModel.jmIgnoreFoeSpeed", "100")


def _occupants(ls: ModuleType, lane_id: str, to_end: float, route: Route,
               cavs: list[tuple[CavPlan, float]]) -> list[tuple[float, float, float]]:
    """(rear, front, headway needed) of every vehicle on a lane, the headway given as the second the foe may reach
    the junction at the earliest behind it (its arrival at its current speed plus `_HEADWAY_S`, or
    `_TURNING_HEADWAY_S` when it leaves the junction by another exit than the foe's `route`). `to_end`: from the
    lane's end to the junction. `cavs` (plan, free-flow speed) are the CAVs inserted in this step on this lane: SUMO
    lists them on the lane only from the next step."""
    length = ls.lane.getLength(lane_id)
    out = []
    for v in ls.lane.getLastStepVehicleIDs(lane_id):
        front, speed = ls.vehicle.getLanePosition(v), ls.vehicle.getSpeed(v)
        turns = route.exit not in ls.vehicle.getRoute(v)
        earliest = (length - front + to_end) / max(speed, 0.1) + (_TURNING_HEADWAY_S if turns else _HEADWAY_S)
        out.append((front - ls.vehicle.getLength(v), front, earliest))
    for plan, speed in cavs:
        turns = plan.route.exit != route.exit
        earliest = plan.to_stop_line_m / speed + (_TURNING_HEADWAY_S if turns else _HEADWAY_S)
        out.append((plan.depart_pos - ls.vehicle.getLength(plan.id), plan.depart_pos, earliest))
    return out


def _free_speed(ls: ModuleType, vid: str, lane_speed: float) -> float:
    """A vehicle's free-flow speed on a lane (its speed factor is drawn when it is added)."""
    return min(lane_speed * ls.vehicle.getSpeedFactor(vid), ls.vehicle.getMaxSpeed(vid))


def insert_hidden_foe(ls: ModuleType, net: sumolib.net.Net, topology: Topology, scenario: Scenario,
                      cav_plans: tuple[CavPlan, ...], buildings: tuple[Building, ...], base_type: str = "car",
                      margin: float = 1.5) -> FoePlan | None:
    """Add foe0 (depart now, in the step that inserts the CAVs; see module doc). None without traffic.hidden_foe,
    or when no lane of its arm has room for it (it is then left out of the run)."""
    cfg = scenario.traffic.hidden_foe
    if cfg is None:
        return None
    ego_id = meet_ref(scenario, tuple(p.id for p in cav_plans))
    ego = next(p for p in cav_plans if p.id == ego_id)
    try:
        side, arm = foe_arm(net, topology, ego, buildings, cfg.side)
        route = _straight(arm)
    except ValueError as e:  # the net has no such arm: a scenario problem, said in one line
        raise ConfigError(f"{scenario.source}: {e}") from None
    _define_foe_type(ls, base_type, cfg.attentive, cfg.speed_mps, cfg.runs_red)
    ego_shape = _ego_lane_shape(net, ego)
    ego_lane = net.getEdge(ego.edges[0]).getLane(ego.lane)
    ego_arrival = ego.to_stop_line_m / _free_speed(ls, ego_id, ego_lane.getSpeed())
    offset = draw_offset(scenario.seed, cfg.arrival_offset_s)
    length_v = ls.vehicletype.getLength(FOE_TYPE)
    gap_v = ls.vehicletype.getMinGap(FOE_TYPE)
    decel = ls.vehicletype.getDecel(FOE_TYPE)
    lanes = _near_lanes(net, route, (float(ego_shape[-1][0]), float(ego_shape[-1][1])))
    speed = min(net.getEdge(route.approach).getLane(lanes[0]).getSpeed() * ls.vehicletype.getSpeedFactor(FOE_TYPE),
                ls.vehicletype.getMaxSpeed(FOE_TYPE))
    # Walk back from the junction to the edge holding the wanted spot (as insert_cavs does).
    k = route.edges.index(route.approach)
    start, remaining = k, speed * max(ego_arrival + offset, 0.0)
    while remaining > net.getEdge(route.edges[start]).getLength() and start > 0:
        remaining -= net.getEdge(route.edges[start]).getLength()
        start -= 1
    edge = net.getEdge(route.edges[start])
    length = edge.getLength()
    beyond = sum(net.getEdge(e).getLength() for e in route.edges[start + 1:k + 1])
    lo_pos = min(length_v + _ENTRY_CLEARANCE_M, length / 2)
    target = float(np.clip(length - remaining, lo_pos, length - 1.0))

    def fits(p: float, occ: list[tuple[float, float, float]], v_f: float) -> bool:
        """Room at front position p, no leader that would hold the foe up, a follower (taken at the lane's speed
        limit `v_f`, the cautious case) that can brake in time."""
        t_foe = (length - p + beyond) / speed
        for rear, front, earliest in occ:
            if rear < p + gap_v and front > p - length_v - gap_v:
                return False  # overlaps someone (or is within the standstill gap)
            if rear >= p and earliest > t_foe:
                return False  # a leader it would catch up with before the junction
            if front <= p - length_v:
                need = v_f + max(0.0, v_f ** 2 / (2 * _FOLLOWER_DECEL) - speed ** 2 / (2 * decel))
                if p - length_v - front - gap_v < margin * need + 1.0:
                    return False
        return lo_pos <= p <= length - 1.0

    # Spots by preference: the near lane within the timing slack, then the other lanes within it, then whichever
    # lane has the spot nearest the wanted timing (the near lane first on a tie).
    slack = speed * _TIMING_SLACK_S
    deltas = [0.0, *[sg * d for d in np.arange(1.0, length, 1.0) for sg in (-1.0, 1.0)]]
    found: dict[int, float] = {}
    for lane in lanes:
        lane_n = min(lane, edge.getLaneNumber() - 1)
        lane_id = f"{edge.getID()}_{lane_n}"
        mine = [(p, _free_speed(ls, p.id, ls.lane.getMaxSpeed(lane_id)))
                for p in cav_plans if p.edges[0] == edge.getID() and p.lane == lane_n]
        occ = _occupants(ls, lane_id, beyond, route, mine)
        v_limit = ls.lane.getMaxSpeed(lane_id)
        d = next((d for d in deltas if fits(target + d, occ, v_limit)), None)
        if d is not None:
            found.setdefault(lane_n, d)
    if not found:
        return None
    within = [ln for ln, d in found.items() if abs(d) <= slack]
    lane_n = within[0] if within else min(found, key=lambda ln: abs(found[ln]))
    pos = target + found[lane_n]
    rid = f"route_{FOE_ID}"
    ls.route.add(rid, list(route.edges[start:]))
    ls.vehicle.add(FOE_ID, rid, typeID=FOE_TYPE, depart="now", departLane=str(lane_n), departPos=f"{pos:.2f}",
                   departSpeed="max")
    ls.vehicle.setLaneChangeMode(FOE_ID, 0)  # it keeps its lane: no overtaking that would shift its timing
    to_junction = length - pos + beyond
    return FoePlan(side=side, route=route, lane=lane_n, depart_pos=float(pos), to_junction_m=float(to_junction),
                   speed=speed, ego=ego_id, ego_arrival_s=float(ego_arrival), offset_s=offset,
                   arrival_s=float(to_junction / speed))
