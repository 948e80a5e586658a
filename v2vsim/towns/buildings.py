"""Buildings along a generated town's blocks, drawn from the built network (SUMO .poly.xml).

For every road edge, walk its kerb (the outer edge of its rightmost lane) from the end nearest the main junction
outwards and lay plots along it: each plot's frontage, depth and the gap after it drawn from the town's
`BuildingStyle`, its front face parallel to the kerb and set back from it; some plots stay empty (open lots). A
building is kept only where it clears every road (lane areas and junction outlines, grown by the set-back) and
every building kept before it, so corners, curves and side streets sort themselves out. Each polygon carries an
explicit `height` param (v2vsim/traffic/static_map.py reads it).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import sumolib
from shapely.geometry import LineString, Polygon
from shapely.ops import unary_union

from v2vsim.towns.plan import TownPlan

_MAX_RADIUS_M = 170.0  # no building farther than this from the main junction (past the sensors' 100 m anyway)
_MAX_BUILDINGS = 70  # the ray caster's cost grows with the footprints near a sensor


def road_area(net: sumolib.net.Net) -> Polygon:
    """Every lane (internal ones too) buffered by half its width, and every junction outline."""
    parts = []
    for edge in net.getEdges(withInternal=True):
        for lane in edge.getLanes():
            shape = [(p[0], p[1]) for p in lane.getShape()]
            if len(shape) >= 2:
                parts.append(LineString(shape).buffer(lane.getWidth() / 2, cap_style="flat"))
    for node in net.getNodes():
        shape = node.getShape()
        if len(shape) >= 3:
            parts.append(Polygon([(p[0], p[1]) for p in shape]).buffer(0))
    return unary_union(parts)


def _kerb(edge: sumolib.net.edge.Edge) -> LineString:
    """The edge's right-hand kerb, oriented from the end nearer the main junction (the origin) outwards."""
    lane = edge.getLane(0)
    line = LineString([(p[0], p[1]) for p in lane.getShape()]).offset_curve(-lane.getWidth() / 2)
    a, b = np.asarray(line.coords[0]), np.asarray(line.coords[-1])
    return line if np.hypot(*a) <= np.hypot(*b) else LineString(list(line.coords)[::-1])


def draw_buildings(plan: TownPlan, net: sumolib.net.Net, rng: np.random.Generator) -> list[Polygon]:
    """The town's building footprints (module doc), in the order they were laid."""
    style = plan.buildings
    roads = road_area(net)
    kept: list[Polygon] = []
    edges = sorted((e for e in net.getEdges() if e.getFunction() != "internal"), key=lambda e: e.getID())
    for edge in edges:
        kerb = _kerb(edge)
        # which side of the kerb is off the road: the right of the edge's travel direction, whatever the walk's
        right_of_travel = 1.0 if np.hypot(*edge.getShape()[0][:2]) <= np.hypot(*edge.getShape()[-1][:2]) else -1.0
        s = float(rng.uniform(0, style.gap_m[1] + 5))
        while s < kerb.length and len(kept) < _MAX_BUILDINGS:
            front = float(rng.uniform(*style.frontage_m))
            depth = float(rng.uniform(*style.depth_m))
            setback = float(rng.uniform(*style.setback_m))
            empty = rng.random() < style.open_lot_share
            start, e = s, min(s + front, kerb.length)
            s = e + float(rng.uniform(*style.gap_m))
            if empty:
                continue
            # a plot that runs into a crossing road (a corner) is shortened from its start, 3 m at a time, so the
            # corners of blocks get buildings too: they are what hides one arm from another
            while e - start >= 6.0:
                poly = _plot(kerb, start, e, right_of_travel, setback, depth)
                if poly is not None and math.hypot(*poly.centroid.coords[0]) <= _MAX_RADIUS_M \
                        and poly.distance(roads) >= setback - 0.05 and all(poly.distance(k) >= 1.0 for k in kept):
                    kept.append(poly)
                    break
                start += 3.0
    return kept


def _plot(kerb: LineString, start: float, end: float, right_of_travel: float, setback: float,
          depth: float) -> Polygon | None:
    """The footprint fronting the kerb from arc length `start` to `end`, `setback` off it, `depth` deep."""
    p0, p1 = np.asarray(kerb.interpolate(start).coords[0]), np.asarray(kerb.interpolate(end).coords[0])
    d = p1 - p0
    if np.linalg.norm(d) < 6.0:
        return None
    side = right_of_travel * np.array([d[1], -d[0]]) / np.linalg.norm(d)  # unit normal away from the road
    a, b = p0 + side * setback, p1 + side * setback
    return Polygon([a, b, b + side * depth, a + side * depth])


def write_poly(plan: TownPlan, net: sumolib.net.Net, path: Path) -> int:
    """Draw the buildings (seeded from the plan) and write them as a SUMO .poly.xml; the count written."""
    rng = np.random.default_rng([0x70A1, plan.seed, 1])
    style = plan.buildings
    polys = draw_buildings(plan, net, rng)
    hrng = np.random.default_rng([0x70A1, plan.seed, 2])
    root = ET.Element("additional")
    for i, poly in enumerate(polys):
        shape = " ".join(f"{x:.2f},{y:.2f}" for x, y in list(poly.exterior.coords)[:-1])
        el = ET.SubElement(root, "poly", {"id": f"bldg{i}", "type": "building", "color": "150,120,100",
                                          "fill": "true", "layer": "1", "shape": shape})
        ET.SubElement(el, "param", {"key": "height", "value": f"{hrng.uniform(*style.height_m):.1f}"})
    tree = ET.ElementTree(root)
    ET.indent(tree)
    tree.write(path, encoding="utf-8", xml_declaration=True)
    return len(polys)
