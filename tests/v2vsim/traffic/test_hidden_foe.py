"""traffic.hidden_foe: foe0 on the main road, hidden from the ego, timed against the ego's arrival; off by default."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import shapely
import sumolib

from v2vsim.config import ConfigError, load_scenario
from v2vsim.traffic.static_map import load_buildings
from v2vsim.traffic.sumo import SumoBackend, _libsumo
from v2vsim.traffic.sumo_hidden_foe import FOE_ID, FOE_TYPE, draw_offset, foe_arm, side_of, sight_blocked
from v2vsim.traffic.sumo_network import analyse_network
from v2vsim.traffic.sumo_placement import CavPlan
from v2vsim.world.state import Building

SCENARIOS = Path(__file__).resolve().parents[3] / "scenarios"
OCCLUDED = SCENARIOS / "t_junction_occluded.yaml"
NETS = SCENARIOS / "nets"


def _scenario(*overrides: str):
    # the traffic alone, open loop, over the 14 s these tests were written for (the placement looks that far ahead)
    return load_scenario(OCCLUDED, ["control=null", "duration_s=14", *overrides])


def _signature(states) -> list:
    return [(s.frame, [(a.id, a.kind, a.cav, a.pose.as_tuple(), a.extent, a.speed) for a in s.actors]) for s in states]


def _run(sc, frames: int):
    with SumoBackend(sc) as tb:
        states = [tb.reset()] + [tb.step() for _ in range(frames - 1)]
        types = set(_libsumo().vehicletype.getIDList())
        return states, tb, types


def test_off_by_default_and_off_leaves_the_world_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the key there is no foe0, no foe vType in SUMO, and the worlds are those of a backend whose foe hook
    does nothing at all (the run is the one the backend gave before the hook existed)."""
    assert load_scenario(SCENARIOS / "t_junction.yaml").traffic.hidden_foe is None
    sc = _scenario("traffic.hidden_foe=null")
    off, tb, types = _run(sc, 40)
    assert tb.hidden_foe is None and FOE_TYPE not in types
    assert all(s.actor(FOE_ID) is None for s in off)
    calls = []
    monkeypatch.setattr("v2vsim.traffic.sumo.insert_hidden_foe", lambda *a, **k: calls.append(a) or None)
    bare, _, _ = _run(sc, 40)
    assert calls and _signature(bare) == _signature(off)


@pytest.mark.parametrize("seed", [1, 2])
def test_foe_on_the_main_road_reaches_the_junction_in_the_window(seed: int) -> None:
    sc = _scenario(f"seed={seed}")
    states, tb, _ = _run(sc, sc.frames)
    plan = tb.hidden_foe
    lo, hi = sc.traffic.hidden_foe.arrival_offset_s
    assert plan is not None and plan.side == "left" and plan.route.approach == "W2T" and plan.route.exit == "T2E"
    assert lo <= plan.offset_s <= hi and plan.ego == "cav0"
    first = next(k for k, s in enumerate(states) if s.actor(FOE_ID) is not None)
    assert first <= 2  # inserted with the CAVs, one step before frame 0
    foe = states[first].actor(FOE_ID)
    assert not foe.cav and foe.kind == "car"
    assert math.cos(foe.pose.yaw) > 0.99 and 243.0 < foe.pose.y < 250.0  # eastbound half of the main road
    assert foe.pose.x < 393.5  # before the junction
    # its front enters the junction outline within the offset window (+/- 1 s) of cav0's free-flow arrival
    net = sumolib.net.readNet(sc.traffic.net)
    junction = shapely.Polygon([p[:2] for p in net.getNode(tb.topology.junction).getShape()])

    def front(a) -> shapely.Point:
        half = a.extent[0] / 2
        return shapely.Point(a.pose.x + half * math.cos(a.pose.yaw), a.pose.y + half * math.sin(a.pose.yaw))

    enter = next(s.time for s in states if (a := s.actor(FOE_ID)) is not None and junction.covers(front(a)))
    assert lo - 1.0 <= enter - plan.ego_arrival_s <= hi + 1.0
    # at frame 0 buildings hide it from the ego, not from the CAV on its own arm
    s0 = states[0]
    ego, cav1 = s0.actor("cav0"), s0.actor("cav1")
    buildings = tb.static.buildings
    assert sight_blocked((front(ego).x, front(ego).y), (foe.pose.x, foe.pose.y), buildings)
    assert not sight_blocked((cav1.pose.x, cav1.pose.y), (foe.pose.x, foe.pose.y), buildings)


def test_deterministic_per_seed() -> None:
    a, tb_a, _ = _run(_scenario("seed=3"), 30)
    b, tb_b, _ = _run(_scenario("seed=3"), 30)
    assert tb_a.hidden_foe == tb_b.hidden_foe and _signature(a) == _signature(b)
    _, tb_c, _ = _run(_scenario("seed=4"), 2)
    assert tb_c.hidden_foe.offset_s != tb_a.hidden_foe.offset_s
    assert draw_offset(3, (0.5, 2.5)) == tb_a.hidden_foe.offset_s


def test_inattentive_foe_ignores_vehicles_in_the_junction() -> None:
    for attentive, value in ((False, "1"), (True, "")):
        with SumoBackend(_scenario(f"traffic.hidden_foe.attentive={str(attentive).lower()}")) as tb:
            tb.reset()
            ls = _libsumo()
            assert ls.vehicle.getTypeID(FOE_ID) == FOE_TYPE
            assert ls.vehicletype.getParameter(FOE_TYPE, "junctionModel.jmIgnoreJunctionFoeProb") == value
            assert ls.vehicletype.getImperfection(FOE_TYPE) == 0.0


def test_config_mapping_override_and_one_line_errors() -> None:
    sc = _scenario()
    assert sc.traffic.hidden_foe is not None and sc.traffic.hidden_foe.side == "auto"
    on = load_scenario(SCENARIOS / "t_junction.yaml", ["traffic.hidden_foe.arrival_offset_s=[0,1]"])
    assert on.traffic.hidden_foe.arrival_offset_s == (0.0, 1.0) and not on.traffic.hidden_foe.attentive
    for bad, key in (("traffic.hidden_foe.side=up", "traffic.hidden_foe.side"),
                     ("traffic.hidden_foe.arrival_offset_s=[2,1]", "traffic.hidden_foe.arrival_offset_s"),
                     ("traffic.hidden_foe.sides=left", "traffic.hidden_foe.sides"),
                     ("traffic.hidden_foe=3", "traffic.hidden_foe")):
        with pytest.raises(ConfigError) as e:
            _scenario(bad)
        msg = str(e.value)
        assert f": {key}:" in msg and "\n" not in msg, msg
    with pytest.raises(ConfigError, match="traffic.hidden_foe: needs traffic.backend 'sumo'"):
        _scenario("traffic.backend=highway-env")


def _stem_plan(net: sumolib.net.Net) -> CavPlan:
    topo = analyse_network(net)
    route = next(r for r in topo.routes if r.approach == "S2T")
    return CavPlan("cav0", route, route.edges, 0, 150.0, 38.65)


def test_side_auto_is_the_arm_the_buildings_hide() -> None:
    net = sumolib.net.readNet(str(NETS / "t_junction.net.xml"))
    topo = analyse_network(net)
    ego = _stem_plan(net)
    arms = {a.approach: a for a in topo.arms}
    assert side_of(arms["S2T"], arms["W2T"]) == "left" and side_of(arms["S2T"], arms["E2T"]) == "right"
    assert side_of(arms["W2T"], arms["E2T"]) is None  # straight on
    occluded = load_buildings(NETS / "t_junction_occluded.poly.xml", (8.0, 15.0), 0)
    assert foe_arm(net, topo, ego, occluded, "auto")[1].approach == "W2T"
    assert foe_arm(net, topo, ego, occluded, "right") == ("right", arms["E2T"])
    # a single block hiding only the east approach turns auto to the right
    east = (Building("east", np.array([[407.0, 200.0], [460.0, 200.0], [460.0, 241.0], [407.0, 241.0]]), 10.0),)
    assert foe_arm(net, topo, ego, east, "auto") == ("right", arms["E2T"])
    # an ego on the main road from the west has the stem on its right (no straight route out of it: no foe there)
    # and nothing on its left
    west = next(r for r in topo.routes if r.approach == "W2T" and r.movement == "straight")
    on_main = CavPlan("cav0", west, west.edges, 0, 150.0, 43.5)
    for side in ("auto", "left", "right"):
        with pytest.raises(ValueError, match="no arm with a straight route to the"):
            foe_arm(net, topo, on_main, occluded, side)


def test_a_side_the_net_lacks_is_a_one_line_config_error() -> None:
    # the ego cav1 comes from the west on the canonical plan: the stem on its right, nothing on its left
    sc = load_scenario(SCENARIOS / "t_junction.yaml",
                       ["traffic.hidden_foe={}", "cavs.meet.trials=1", "cavs.ego=[cav1]"])
    with SumoBackend(sc) as tb, pytest.raises(ConfigError) as e:
        tb.reset()
    assert "t_junction.yaml: traffic.hidden_foe: no arm with a straight route" in str(e.value)
    assert "\n" not in str(e.value)


def test_sight_blocked() -> None:
    box = (Building("b", np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]), 10.0),)
    assert sight_blocked((-1.0, 1.0), (3.0, 1.0), box)
    assert not sight_blocked((-1.0, 3.0), (3.0, 3.0), box)
    assert not sight_blocked((-1.0, 1.0), (3.0, 1.0), ())


@pytest.mark.parametrize("speed", [8.0, 16.0])
def test_speed_mps_sets_the_foes_free_flow_speed_below_and_above_the_lanes_limit(speed: float) -> None:
    """A benchmark grid's second factor (docs/benchmark.md): the foe drives at speed_mps, not the 13.89 m/s limit,
    and its insertion is timed for that speed."""
    sc = _scenario("seed=1", f"traffic.hidden_foe.speed_mps={speed}", "traffic.hidden_foe.arrival_offset_s=[2, 2]")
    states, tb, _ = _run(sc, 20)
    plan = tb.hidden_foe
    assert plan is not None and plan.speed == pytest.approx(speed)
    assert plan.arrival_s == pytest.approx(plan.ego_arrival_s + 2.0, abs=1.0)
    speeds = [s.actor(FOE_ID).speed for s in states[5:] if s.actor(FOE_ID) is not None]
    assert speeds and all(abs(v - speed) < 0.3 for v in speeds), speeds


def test_a_placement_horizon_keeps_the_cast_when_only_the_time_limit_changes() -> None:
    """cavs.meet.horizon_s: the look-ahead scores the first horizon_s seconds, so a 40 s run places its CAVs as the
    14 s run does; without it the 40 s look-ahead picks another cast (why the key exists)."""
    def cast(*overrides: str):
        with SumoBackend(_scenario("seed=3", *overrides)) as tb:
            tb.reset()
            return [(p.id, p.route.approach, p.route.exit, round(p.arrival_s, 3)) for p in tb.cav_plans], tb.placement

    short, placed = cast()
    held, held_placed = cast("duration_s=40", "cavs.meet.horizon_s=14")
    assert held == short and held_placed.frames == placed.frames == 140
    assert cast("duration_s=40")[0] != short
    with pytest.raises(ConfigError, match="horizon_s"):
        _scenario("cavs.meet.horizon_s=0")
