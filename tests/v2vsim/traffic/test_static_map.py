"""SUMO net + polygons -> StaticMap: drivable area, markings, buildings, bounds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Point, Polygon
from shapely.ops import unary_union

from v2vsim.traffic.static_map import load_buildings, load_sumo_map

NETS = Path(__file__).resolve().parents[3] / "scenarios" / "nets"


def _drivable(static) -> Polygon:
    return unary_union([Polygon(r) for r in static.roads])


@pytest.fixture(scope="module")
def intersection():
    return load_sumo_map(NETS / "intersection.net.xml", NETS / "intersection.poly.xml", (8.0, 15.0), seed=0)


def test_roads_cover_junction_and_arms_but_not_corners(intersection) -> None:
    area = _drivable(intersection)
    for x, y in [(0, 0), (5, 5), (-100, -3), (100, 3), (3, 150), (-3, -150), (-9, 0)]:
        assert area.contains(Point(x, y)), (x, y)
    for x, y in [(25, 25), (-25, 25), (12, 12), (0, 250)]:
        assert not area.contains(Point(x, y)), (x, y)
    # two 3.5 m lanes each way: the arm is 14 m wide
    assert area.contains(Point(-100, 6.9)) and not area.contains(Point(-100, 7.2))


def test_markings_dashed_between_lanes_solid_at_edges(intersection) -> None:
    st = intersection
    assert len(st.lane_markings) == len(st.dashed) > 0
    assert any(st.dashed) and not all(st.dashed)
    # On the west arm (x=-100): dashed lines at y=+-3.5 (between lanes), solid at 0 and +-7.
    ys_dashed, ys_solid = set(), set()
    for line, dashed in zip(st.lane_markings, st.dashed, strict=True):
        xs = line[:, 0]
        if xs.min() < -100 < xs.max() and np.ptp(line[:, 1]) < 1e-6:
            (ys_dashed if dashed else ys_solid).add(round(float(line[0, 1]), 2))
    assert ys_dashed == {-3.5, 3.5}
    assert ys_solid == {-7.0, 0.0, 7.0}


def test_buildings_loaded_heights_drawn_deterministically(intersection) -> None:
    st = intersection
    assert len(st.buildings) == 12
    assert all(8.0 <= b.height <= 15.0 for b in st.buildings)
    assert all(b.polygon.shape == (4, 2) for b in st.buildings)
    again = load_sumo_map(NETS / "intersection.net.xml", NETS / "intersection.poly.xml", (8.0, 15.0), seed=0)
    assert [b.height for b in again.buildings] == [b.height for b in st.buildings]
    other = load_buildings(NETS / "intersection.poly.xml", (8.0, 15.0), seed=1)
    assert [b.height for b in other] != [b.height for b in st.buildings]
    # buildings stay off the road
    area = _drivable(st)
    assert all(not area.intersects(Polygon(b.polygon)) for b in st.buildings)
    assert st.bounds == (-200.0, -200.0, 200.0, 200.0)


def test_height_param_and_other_net() -> None:
    st = load_sumo_map(NETS / "t_junction.net.xml", NETS / "t_junction.poly.xml", (8.0, 15.0), seed=3)
    heights = {b.id: b.height for b in st.buildings}
    assert heights["bldg_n_0"] == 18.0 and heights["bldg_n_1"] == 9.0 and heights["bldg_n_2"] == 12.0
    assert 8.0 <= heights["bldg_sw_0"] <= 15.0
    area = _drivable(st)
    assert area.contains(Point(400, 250)) and area.contains(Point(250, 248)) and area.contains(Point(420, 120))
    x0, y0, x1, y1 = st.bounds
    assert x0 <= 200 and x1 >= 600 and y0 <= 52 and y1 >= 292


def test_poly_file_filters_and_refuses_geo(tmp_path: Path) -> None:
    f = tmp_path / "p.poly.xml"
    f.write_text('<additional>'
                 '<poly id="park" type="park" shape="0,0 1,0 1,1"/>'
                 '<poly id="b" type="building.yes" shape="0,0 10,0 10,10 0,10 0,0">'
                 '<param key="height" value="4.5"/></poly></additional>')
    (b,) = load_buildings(f, (8.0, 15.0), seed=0)
    assert b.id == "b" and b.height == 4.5 and b.polygon.shape == (4, 2)  # closing point dropped
    f.write_text('<additional><poly id="g" type="building" geo="1" shape="13.4,52.5 13.5,52.5 13.5,52.6"/>'
                 '</additional>')
    with pytest.raises(ValueError, match="geo"):
        load_buildings(f, (8.0, 15.0), seed=0)
