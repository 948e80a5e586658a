"""Vehicles that stand in a lane (SUMO backend): for the whole run (`traffic.standing`: a truck queued to turn
left, a parked van, a broken-down car), or in the ego's exit lane past the main junction until a given time
(`traffic.hidden_stop`: a lead vehicle stopped around a blind corner).

Why: the benchmark's families need vehicles as occluders, where they are and for as long as the encounter lasts
(Coopernaut's unprotected left turn: the oncoming car hidden behind a truck waiting to turn opposite). A vehicle
of the background stream would be there by chance; one of these is there by the scenario.

How: each is added at time 0, before the warm-up, with its front `to_end_m` before the end of its lane, standing
(depart speed 0), with a SUMO stop at that spot that outlasts any run; its route is its edge alone. Traffic behind
it queues or changes lane as SUMO's drivers do. It is an actor like any other (`standing0`, `standing1`, ...,
kind car / van / truck), so sensors see it, and it hides what is behind it, with its type's extents.

The hidden stop, `stopped0`, is added in the step that inserts the CAVs, on the lane the ego (the first ego)
leaves the junction by (the exit lane its approach lane connects to), its rear `distance_m` from that lane's start,
standing until `until_s` after frame 0; then it drives to the end of its edge. Not free (a vehicle there): it is
moved forward 1 m at a time, at most 20 m, and left out when no spot is free.
"""

from __future__ import annotations

from types import ModuleType

import sumolib

from v2vsim.config import ConfigError, Scenario
from v2vsim.traffic.actor_ids import HIDDEN_STOP_ID, STANDING_PREFIX
from v2vsim.traffic.sumo_placement import CavPlan, meet_ref

_FOREVER_S = 1e6  # the stop's duration: longer than any run


def standing_id(i: int) -> str:
    return f"{STANDING_PREFIX}{i}"


def check_standing(net: sumolib.net.Net, scenario: Scenario) -> None:
    """Every traffic.standing entry names an edge of the net, a lane it has, and a spot on that lane (ConfigError
    with the entry's path and what is allowed)."""
    for i, s in enumerate(scenario.traffic.standing):
        where = f"{scenario.source}: traffic.standing[{i}]"
        if not net.hasEdge(s.edge) or s.edge.startswith(":"):
            raise ConfigError(f"{where}.edge: {s.edge!r} is not an edge of {scenario.traffic.net}")
        edge = net.getEdge(s.edge)
        if s.lane >= edge.getLaneNumber():
            raise ConfigError(f"{where}.lane: {s.lane}; edge {s.edge} has lanes 0..{edge.getLaneNumber() - 1}")
        length = edge.getLane(s.lane).getLength()
        if s.to_end_m >= length - 10.0:
            raise ConfigError(f"{where}.to_end_m: {s.to_end_m:g} m; lane {s.edge}_{s.lane} is {length:.1f} m long: "
                              f"allowed below {length - 10.0:.1f} m")


def insert_standing(ls: ModuleType, net: sumolib.net.Net, scenario: Scenario) -> tuple[str, ...]:
    """Add the standing vehicles (see module doc); their ids in entry order."""
    ids = []
    for i, s in enumerate(scenario.traffic.standing):
        vid = standing_id(i)
        pos = net.getEdge(s.edge).getLane(s.lane).getLength() - s.to_end_m
        rid = f"route_{vid}"
        ls.route.add(rid, [s.edge])
        ls.vehicle.add(vid, rid, typeID=s.type, depart="0", departLane=str(s.lane), departPos=f"{pos:.2f}",
                       departSpeed="0")
        try:
            ls.vehicle.setStop(vid, s.edge, pos=pos, laneIndex=s.lane, duration=_FOREVER_S)
        except ls.TraCIException:
            # libsumo 1.28 refuses some stops on a lane before the vehicle is in ("not downstream the current
            # route"; seen on generated towns' lanes at 47-70 % of their length): hold it where it is inserted
            ls.vehicle.setSpeedMode(vid, 0)
            ls.vehicle.setLaneChangeMode(vid, 0)
            ls.vehicle.setSpeed(vid, 0.0)
        ids.append(vid)
    return tuple(ids)


def _exit_lane(net: sumolib.net.Net, plan: CavPlan) -> tuple[str, int]:
    """(exit edge, lane index) the CAV's approach lane leads to on its route's exit."""
    approach = net.getEdge(plan.route.approach)
    lane = approach.getLane(min(plan.lane, approach.getLaneNumber() - 1))
    for c in lane.getOutgoing():
        if c.getTo().getID() == plan.route.exit:
            return plan.route.exit, c.getToLane().getIndex()
    return plan.route.exit, 0


def insert_hidden_stop(ls: ModuleType, net: sumolib.net.Net, scenario: Scenario, cav_plans: tuple[CavPlan, ...],
                       dt: float) -> str | None:
    """Add stopped0 in the ego's exit lane (see module doc); its id, or None without traffic.hidden_stop or when
    its lane has no free spot."""
    cfg = scenario.traffic.hidden_stop
    if cfg is None:
        return None
    ego_id = meet_ref(scenario, tuple(p.id for p in cav_plans))
    ego = next(p for p in cav_plans if p.id == ego_id)
    edge_id, lane_n = _exit_lane(net, ego)
    lane_id = f"{edge_id}_{lane_n}"
    length_v = ls.vehicletype.getLength(cfg.type)
    lane_len = ls.lane.getLength(lane_id)
    if cfg.distance_m + length_v > lane_len - 1.0:
        raise ConfigError(f"{scenario.source}: traffic.hidden_stop.distance_m: {cfg.distance_m:g} m; the ego's exit "
                          f"lane {lane_id} is {lane_len:.1f} m long: allowed up to {lane_len - 1.0 - length_v:.1f} m")
    taken = [(ls.vehicle.getLanePosition(v) - ls.vehicle.getLength(v), ls.vehicle.getLanePosition(v))
             for v in ls.lane.getLastStepVehicleIDs(lane_id)]
    for shift in range(21):
        front = cfg.distance_m + shift + length_v
        if front > lane_len - 1.0:
            break
        if all(front + 2.5 <= rear or front - length_v - 2.5 >= fr for rear, fr in taken):
            rid = f"route_{HIDDEN_STOP_ID}"
            ls.route.add(rid, [edge_id])
            ls.vehicle.add(HIDDEN_STOP_ID, rid, typeID=cfg.type, depart="now", departLane=str(lane_n),
                           departPos=f"{front:.2f}", departSpeed="0")
            ls.vehicle.setStop(HIDDEN_STOP_ID, edge_id, pos=front, laneIndex=lane_n, duration=cfg.until_s + dt)
            return HIDDEN_STOP_ID
    return None
