"""What the later benchmark families add to the SUMO backend: vehicles standing in a lane all run
(traffic.standing), a CAV's movement fixed by the scenario (cavs.movements), an oncoming hidden foe
(traffic.hidden_foe.side opposite) and one that runs its red light (runs_red)."""

from __future__ import annotations

from pathlib import Path

import pytest

from v2vsim.config import ConfigError, load_scenario
from v2vsim.traffic import make_backend
from v2vsim.traffic.sumo import SumoBackend, _libsumo
from v2vsim.traffic.sumo_hidden_foe import FOE_ID

SCENARIOS = Path(__file__).resolve().parents[3] / "scenarios"
LEFT_TURN = SCENARIOS / "left_turn_truck.yaml"
RED_LIGHT = SCENARIOS / "red_light_runner.yaml"


def _open_loop(path: Path, *overrides: str):
    return load_scenario(path, ["control=null", "duration_s=20", *overrides])


def test_a_standing_truck_stands_where_the_scenario_puts_it_and_hides_like_any_vehicle() -> None:
    sc = _open_loop(LEFT_TURN, "seed=100")
    with SumoBackend(sc) as tb:
        states = [tb.reset()] + [tb.step() for _ in range(49)]
        end = _libsumo().lane.getLength("E2C_1")
        front = _libsumo().vehicle.getLanePosition("standing0")
    trucks = [next(a for a in s.actors if a.id == "standing0") for s in states]
    assert all(t.kind == "truck" and t.extent == (8.5, 2.5, 3.4) and t.speed == 0.0 for t in trucks)
    assert {t.pose.as_tuple() for t in trucks} == {trucks[0].pose.as_tuple()}  # it never moves
    assert abs(end - front - 0.5) < 0.05  # its front 0.5 m before the stop line (to_end_m)
    # cav1, wanting to turn left from the same lane (westbound: behind is east), queues behind it and slows
    cav1 = [next(a for a in s.actors if a.id == "cav1") for s in states]
    assert all(c.pose.x - trucks[0].pose.x > (8.5 + 4.5) / 2 and c.pose.y == trucks[0].pose.y for c in cav1)
    assert cav1[-1].speed < cav1[0].speed / 3


@pytest.mark.parametrize(("override", "said"), [
    ("traffic.standing=[{edge: X2C}]", "traffic.standing[0].edge: 'X2C' is not an edge of"),
    ("traffic.standing=[{edge: E2C, lane: 2}]", "traffic.standing[0].lane: 2; edge E2C has lanes 0..1"),
    ("traffic.standing=[{edge: E2C, to_end_m: 500}]", "traffic.standing[0].to_end_m: 500 m; lane E2C_0 is"),
    ("cavs.movements=[right, right]", None),  # cav1's arm (east) offers right: fine
    ("cavs.movements=[left, left, left, left, left]", "cavs.movements: 5 movements for 4 CAVs"),
])
def test_bad_standing_and_movements_are_one_line_config_errors(override: str, said: str | None) -> None:
    if said is None:
        with SumoBackend(_open_loop(LEFT_TURN, override)) as tb:
            tb.reset()
            assert [p.route.movement for p in tb.cav_plans[:2]] == ["right", "right"]
        return
    with pytest.raises(ConfigError) as e:
        SumoBackend(_open_loop(LEFT_TURN, override)).close()
    assert said in str(e.value) and "\n" not in str(e.value)


def test_a_movement_the_arm_lacks_is_a_config_error_naming_what_it_offers() -> None:
    sc = _open_loop(SCENARIOS / "ramp_merge.yaml", "cavs.movements=[left]")  # the ramp only joins eastbound
    with pytest.raises(ConfigError, match=r"cavs.movements\[0\]: 'left' is not a movement of cav0's arm R2M; "
                                          r"allowed there: right"):
        with SumoBackend(sc) as tb:
            tb.reset()


def test_the_ego_turns_left_and_the_oncoming_foe_takes_the_lane_the_truck_leaves_free() -> None:
    sc = _open_loop(LEFT_TURN, "seed=101", "traffic.hidden_foe.arrival_offset_s=[2, 2]")
    with SumoBackend(sc) as tb:
        tb.reset()
        ego, plan = tb.cav_plans[0], tb.hidden_foe
    assert ego.route.approach == "W2C" and ego.route.movement == "left"
    assert plan is not None and plan.side == "opposite" and plan.route.approach == "E2C"
    assert plan.lane == 0  # the inner lane, nearer the ego, holds the truck: a leader the foe would catch up with
    assert abs(plan.arrival_s - (plan.ego_arrival_s + 2.0)) < 1.0


def test_a_red_light_runner_drives_through_its_red_at_its_speed() -> None:
    sc = _open_loop(RED_LIGHT, "seed=100", "traffic.hidden_foe.arrival_offset_s=[0.5, 0.5]",
                    "traffic.hidden_foe.speed_mps=14")
    with SumoBackend(sc) as tb:
        tb.reset()
        ls = _libsumo()
        speeds, crossed_on_red = [], False
        for _ in range(80):
            tb.step()
            if FOE_ID in ls.vehicle.getIDList():
                speeds.append(ls.vehicle.getSpeed(FOE_ID))
                lane = ls.vehicle.getLaneID(FOE_ID)
                state = ls.trafficlight.getRedYellowGreenState("C")
                crossed_on_red |= lane.startswith(":C_11") and state[11] == "r"
    assert crossed_on_red
    assert min(speeds) > 13.5  # it never braked for its light or the ego
    # without runs_red the same foe stops at its line
    sc = _open_loop(RED_LIGHT, "seed=100", "traffic.hidden_foe.arrival_offset_s=[0.5, 0.5]",
                    "traffic.hidden_foe.speed_mps=14", "traffic.hidden_foe.runs_red=false")
    with SumoBackend(sc) as tb:
        tb.reset()
        ls = _libsumo()
        lowest = min(ls.vehicle.getSpeed(FOE_ID) for _ in range(80) if tb.step() is not None)
    assert lowest < 0.1


def test_a_hidden_stop_stands_in_the_ego_s_exit_lane_until_its_time() -> None:
    sc = _open_loop(SCENARIOS / "blind_corner_stop.yaml", "seed=100", "traffic.hidden_stop.distance_m=12",
                    "traffic.hidden_stop.until_s=3")
    with SumoBackend(sc) as tb:
        tb.reset()
        ls = _libsumo()
        assert tb.hidden_stop == "stopped0" and tb.cav_plans[0].route.exit == "C2S"
        assert ls.vehicle.getLaneID("stopped0") == "C2S_0"
        rear = ls.vehicle.getLanePosition("stopped0") - ls.vehicle.getLength("stopped0")
        assert abs(rear - 12.0) < 0.05
        speeds = []
        for _ in range(60):
            tb.step()
            speeds.append(ls.vehicle.getSpeed("stopped0"))
    assert max(speeds[:25]) == 0.0 and max(speeds[40:]) > 2.0  # it stands 3 s, then drives off
    assert tb.missing_actors() == ()  # the driver logs each critical actor a run goes without
    far = _open_loop(SCENARIOS / "blind_corner_stop.yaml", "seed=100", "traffic.hidden_stop.distance_m=500")
    with pytest.raises(ConfigError, match=r"traffic.hidden_stop.distance_m: 500 m; the ego's exit lane C2S_0 is"):
        with SumoBackend(far) as tb:
            tb.reset()


def test_a_driven_vehicle_crossing_the_junction_sees_its_path_beyond_it() -> None:
    """SUMO lists no next links on an internal lane: the path must still reach into the exit edge, or the planner
    loses a vehicle standing just past the junction."""
    sc = load_scenario(SCENARIOS / "blind_corner_stop.yaml", ["seed=100", "duration_s=12", "control.method=oracle"])
    with make_backend(sc, closed_loop=True) as tb:
        w = tb.reset()
        inside = []
        for _ in range(80):
            tb.command({"cav0": 0.0})  # keep its speed: it crosses the junction
            w = tb.step()
            d = w.driven[0] if w.driven else None
            if d is not None and d.in_junction:
                inside.append(d.path)
    assert inside
    for path in inside:  # from the internal lane south into C2S (x ~ 397.25), well past the junction's edge
        assert path[-1][1] < 239.0 - 30.0 and abs(path[-1][0] - 397.25) < 0.5
