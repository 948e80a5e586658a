"""Vehicles that stand in a lane for the whole run (`traffic.standing`, SUMO backend): a truck queued to turn
left, a parked van, a broken-down car.

Why: the benchmark's families need vehicles as occluders, where they are and for as long as the encounter lasts
(Coopernaut's unprotected left turn: the oncoming car hidden behind a truck waiting to turn opposite). A vehicle
of the background stream would be there by chance; one of these is there by the scenario.

How: each is added at time 0, before the warm-up, with its front `to_end_m` before the end of its lane, standing
(depart speed 0), with a SUMO stop at that spot that outlasts any run; its route is its edge alone. Traffic behind
it queues or changes lane as SUMO's drivers do. It is an actor like any other (`standing0`, `standing1`, ...,
kind car / van / truck), so sensors see it, and it hides what is behind it, with its type's extents.
"""

from __future__ import annotations

from types import ModuleType

import sumolib

from v2vsim.config import ConfigError, Scenario

STANDING_PREFIX = "standing"
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
        ls.vehicle.setStop(vid, s.edge, pos=pos, laneIndex=s.lane, duration=_FOREVER_S)
        ids.append(vid)
    return tuple(ids)
