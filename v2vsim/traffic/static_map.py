"""SUMO network (+ polygon file) -> StaticMap: drivable area, lane markings, buildings, bounds.

Why a separate module: sensors and ground truth only ever see `StaticMap`; reading SUMO files
is the one place that knows SUMO's geometry conventions. The result is plain numpy/shapely-free
data, built fresh on every call (nothing is cached globally, so two scenarios in one process
never share state).

Geometry rules (DESIGN.md "Domain notes"):
- drivable area = every lane's centre line (normal and internal/junction lanes) buffered by
  half its width, plus every junction outline;
- lane markings = the line between neighbouring lanes of one edge (dashed) and the outer
  boundaries of each edge (solid; for a two-way road without median the two directions' left
  boundaries coincide and form the centre line);
- buildings = `<poly type="building...">` prisms; height from a `height` param when present,
  otherwise drawn deterministically from (seed, polygon id) in `building_height_m`.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
import zlib
from pathlib import Path

import numpy as np
import sumolib
from shapely.geometry import LineString, Polygon

from v2vsim.world.state import Building, StaticMap

_BUFFER_RES = 4  # segments per quarter circle for round joins: enough for 3.5 m lanes


def _ring(poly: Polygon) -> np.ndarray:
    """Exterior ring of a polygon as (K, 2) float64 without the repeated closing point."""
    xy = np.asarray(poly.exterior.coords, dtype=np.float64)
    return xy[:-1] if len(xy) > 1 and np.allclose(xy[0], xy[-1]) else xy


def _lane_polygon(shape: list[tuple[float, ...]], width: float) -> np.ndarray | None:
    """Centre line buffered by width/2 with flat ends (junction outlines close the gaps)."""
    pts = [(p[0], p[1]) for p in shape]
    line = LineString(pts)
    if line.length < 1e-3 or width <= 0:
        return None
    area = line.buffer(width / 2.0, cap_style="flat", join_style="round", quad_segs=_BUFFER_RES)
    if area.is_empty:
        return None
    if area.geom_type == "MultiPolygon":  # degenerate self-overlap: keep the largest piece
        area = max(area.geoms, key=lambda g: g.area)
    return _ring(area)


def _offset(shape: list[tuple[float, ...]], distance: float) -> np.ndarray | None:
    """Polyline parallel to a lane's centre line; positive distance = to the left of travel."""
    line = LineString([(p[0], p[1]) for p in shape])
    if line.length < 1e-3:
        return None
    off = line.offset_curve(distance, quad_segs=_BUFFER_RES, join_style="mitre", mitre_limit=4.0)
    if off.is_empty:
        return None
    if off.geom_type == "MultiLineString":
        off = max(off.geoms, key=lambda g: g.length)
    return np.asarray(off.coords, dtype=np.float64)


def _building_height(poly_id: str, params: dict[str, str], height_range: tuple[float, float],
                     seed: int) -> float:
    """`height` param if the file gives one, else a draw keyed by (seed, id) so order never matters."""
    if "height" in params:
        return float(params["height"])
    lo, hi = height_range
    rng = np.random.default_rng([int(seed), zlib.crc32(poly_id.encode())])
    return float(rng.uniform(lo, hi))


def load_buildings(poly_path: str | Path, building_height_m: tuple[float, float],
                   seed: int) -> tuple[Building, ...]:
    """Read `<poly type="building...">` entries of a SUMO additional/polygon file.

    Coordinates must be in the network's (cartesian) frame, as polyconvert writes them for a
    given net; geo-referenced shapes (`geo="1"`) are refused rather than silently misplaced.
    """
    root = ET.parse(str(poly_path)).getroot()
    out: list[Building] = []
    for el in root.iter("poly"):
        ptype = el.get("type", "")
        if not ptype.startswith("building"):
            continue
        pid = el.get("id", f"poly{len(out)}")
        if el.get("geo", "0").lower() in ("1", "true"):
            raise ValueError(f"{poly_path}: poly {pid!r} uses geo coordinates; convert it to the net frame")
        pts = [tuple(float(v) for v in p.split(",")[:2]) for p in el.get("shape", "").split()]
        if len(pts) < 3:
            continue
        xy = np.asarray(pts, dtype=np.float64)
        if np.allclose(xy[0], xy[-1]):
            xy = xy[:-1]
        params = {p.get("key", ""): p.get("value", "") for p in el.iter("param")}
        out.append(Building(id=pid, polygon=xy, height=_building_height(pid, params, building_height_m, seed)))
    return tuple(out)


def load_sumo_map(net_path: str | Path, poly_path: str | Path | None,
                  building_height_m: tuple[float, float] = (8.0, 15.0), seed: int = 0) -> StaticMap:
    """Build the StaticMap of a SUMO network and optional building polygon file."""
    net = sumolib.net.readNet(str(net_path), withInternal=True)
    roads: list[np.ndarray] = []
    markings: list[np.ndarray] = []
    dashed: list[bool] = []
    for edge in net.getEdges():
        lanes = sorted(edge.getLanes(), key=lambda ln: ln.getIndex())  # 0 = rightmost
        for lane in lanes:
            poly = _lane_polygon(lane.getShape(), lane.getWidth())
            if poly is not None:
                roads.append(poly)
        if edge.getFunction() == "internal":
            continue  # no paint inside junctions
        for k, lane in enumerate(lanes):
            half = lane.getWidth() / 2.0
            if k == 0:
                right = _offset(lane.getShape(), -half)
                if right is not None:
                    markings.append(right)
                    dashed.append(False)
            left = _offset(lane.getShape(), half)
            if left is not None:
                markings.append(left)
                dashed.append(k < len(lanes) - 1)  # between lanes: dashed; leftmost: solid
    for node in net.getNodes():
        shape = node.getShape()
        if len(shape) >= 3:
            outline = Polygon([(p[0], p[1]) for p in shape]).buffer(0)
            if outline.geom_type == "MultiPolygon":
                outline = max(outline.geoms, key=lambda g: g.area)
            if not outline.is_empty and outline.area > 1e-3:
                roads.append(_ring(outline))
    buildings = load_buildings(poly_path, building_height_m, seed) if poly_path else ()
    (xmin, ymin), (xmax, ymax) = net.getBBoxXY()
    for b in buildings:
        bx0, by0 = b.polygon.min(axis=0)
        bx1, by1 = b.polygon.max(axis=0)
        xmin, ymin, xmax, ymax = min(xmin, bx0), min(ymin, by0), max(xmax, bx1), max(ymax, by1)
    return StaticMap(
        roads=tuple(roads),
        lane_markings=tuple(markings),
        dashed=tuple(dashed),
        buildings=buildings,
        bounds=(float(xmin), float(ymin), float(xmax), float(ymax)),
    )
