"""Network analysis for the SUMO backend: read the net's topology (sumolib), simulate nothing.

The main junction is the node with the most incoming edges; every shortest path from a fringe
source edge to a fringe sink edge that crosses it is a route; the edge entering the junction names
the route's *arm*; the turn at the junction gives its movement (straight / left / right).
Only this topology is used by the rest of the backend (v2vsim/traffic/sumo.py and
v2vsim/traffic/sumo_placement.py), so it works on any net.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import sumolib

from v2vsim.world.geometry import wrap_angle


@dataclass(frozen=True)
class Route:
    """A route through the main junction."""

    id: str
    edges: tuple[str, ...]
    approach: str  # the edge entering the main junction: names the arm
    exit: str  # the edge leaving it
    movement: str  # "straight" | "left" | "right"


@dataclass(frozen=True)
class Arm:
    """One approach to the main junction."""

    approach: str
    bearing: float  # direction from the junction out along the arm, rad CCW from +x
    priority: int  # SUMO edge priority of the approach (minor roads yield)
    routes: tuple[Route, ...]


@dataclass(frozen=True)
class Topology:
    junction: str
    arms: tuple[Arm, ...]

    @property
    def routes(self) -> tuple[Route, ...]:
        return tuple(r for a in self.arms for r in a.routes)


def _heading(p: tuple[float, ...], q: tuple[float, ...]) -> float:
    return math.atan2(q[1] - p[1], q[0] - p[0])


def _is_reverse(a: sumolib.net.edge.Edge, b: sumolib.net.edge.Edge) -> bool:
    return a.getFromNode() is b.getToNode() and a.getToNode() is b.getFromNode()


def analyse_network(net: sumolib.net.Net) -> Topology:
    """Find the main junction, its arms and every fringe-to-fringe route through it."""
    nodes = [n for n in net.getNodes() if n.getType() not in ("dead_end", "internal")]
    xmin, ymin, xmax, ymax = net.getBoundary()
    cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2

    def rank(n: sumolib.net.node.Node) -> tuple[float, ...]:
        x, y = n.getCoord()[:2]
        return (-len(n.getIncoming()), -len(n.getConnections()), math.hypot(x - cx, y - cy), 0.0)

    junction = min(nodes, key=lambda n: (rank(n), n.getID()))
    edges = [e for e in net.getEdges() if e.getFunction() != "internal" and e.allows("passenger")]
    sources = [e for e in edges
               if all(_is_reverse(e, i) for i in e.getFromNode().getIncoming())]
    sinks = [e for e in edges
             if all(_is_reverse(e, o) for o in e.getToNode().getOutgoing())]
    by_arm: dict[str, list[Route]] = {}
    seen: set[tuple[str, ...]] = set()
    for src in sorted(sources, key=lambda e: e.getID()):
        for dst in sorted(sinks, key=lambda e: e.getID()):
            if _is_reverse(src, dst) or src is dst:
                continue
            path, _ = net.getShortestPath(src, dst, vClass="passenger")
            if not path:
                continue
            ids = tuple(e.getID() for e in path)
            if ids in seen:
                continue
            k = next((i for i, e in enumerate(path[:-1]) if e.getToNode() is junction), None)
            if k is None:
                continue
            seen.add(ids)
            a, b = path[k], path[k + 1]
            sa, sb = a.getShape(), b.getShape()
            turn = float(wrap_angle(_heading(sb[0], sb[1]) - _heading(sa[-2], sa[-1])))
            move = "straight" if abs(turn) < math.radians(35) else ("left" if turn > 0 else "right")
            by_arm.setdefault(a.getID(), []).append(
                Route(f"r{len(seen) - 1}", ids, a.getID(), b.getID(), move))
    if not by_arm:
        raise ValueError("no route crosses the main junction: is the network a junction with arms?")
    arms = []
    for approach, routes in sorted(by_arm.items()):
        shape = net.getEdge(approach).getShape()
        arms.append(Arm(approach, _heading(shape[-1], shape[-2]), net.getEdge(approach).getPriority(),
                        tuple(routes)))
    return Topology(junction.getID(), tuple(arms))


def order_arms(arms: tuple[Arm, ...]) -> tuple[Arm, ...]:
    """cav0's arm first, then the most opposite arm, then the side arms (counter-clockwise).

    cav0 takes a minor-road arm if there is one (it must yield, so it lingers at the junction and
    stays in range of the others), else the arm pointing most to the west (it drives east).
    """
    first = min(arms, key=lambda a: (a.priority, round(abs(float(wrap_angle(a.bearing - math.pi))), 3),
                                     a.approach))
    rest = [a for a in arms if a is not first]

    def key(a: Arm) -> tuple[float, float, str]:
        diff = float(wrap_angle(a.bearing - first.bearing))
        return (-round(abs(diff), 3), diff % (2 * math.pi), a.approach)

    return (first, *sorted(rest, key=key))
