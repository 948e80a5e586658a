"""The planner in closed loop on synthetic perception: it follows a perceived leader at IDM's equilibrium gap,
stops behind a standing obstacle, yields at a stop line to a crossing vehicle whose gap is too short (and only
then), and ignores what is beside its path."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from v2vsim.control.geometry import point_in_polygon, project_onto_polyline, ray_to_grown_polygon
from v2vsim.control.perceived import Obstacle
from v2vsim.control.planner import Plan, PlannerConfig, RouteAhead, find_leader, plan
from v2vsim.control.tracking import Track, track
from v2vsim.world.geometry import Pose

DT = 0.1
EGO_LEN = 4.5
LINE_X = 22.25  # the stop line: 20 m ahead of the front bumper of an ego at x = 0
ZONE = np.array([[LINE_X, -5.0], [LINE_X + 10.0, -5.0], [LINE_X + 10.0, 5.0], [LINE_X, 5.0]])


def _route(ego_x: float, speed_limit: float = 13.9, junction: bool = False, priority: bool = False) -> RouteAhead:
    """A straight route along +x from the front bumper of an ego at (ego_x, 0) facing east; with `priority` the
    junction has no stop line for it (a green light, the main road)."""
    front = ego_x + EGO_LEN / 2
    path = np.array([[front, 0.0], [front + 300.0, 0.0]])
    if junction and priority:
        return RouteAhead(path, speed_limit, None, ZONE if front < LINE_X + 12.0 else None)
    if junction and front < LINE_X:
        return RouteAhead(path, speed_limit, LINE_X - front, ZONE)
    return RouteAhead(path, speed_limit, None, None)


@dataclass(frozen=True)
class _Step:
    ego_x: float
    speed: float
    plan: Plan
    others: tuple[tuple[float, float], ...]


def _drive(ego_v: float, others: list[tuple[float, float, float, float, float]], seconds: float,
           cfg: PlannerConfig, junction: bool = False, priority: bool = False,
           stop_y: float | None = None) -> list[_Step]:
    """Closed loop: truth -> obstacles -> `track` -> `plan` -> the ego moves at the commanded speed.
    `others` are (x, y, yaw, vx, vy) moving at constant velocity; with `stop_y` they brake at 4.5 m/s^2 (a SUMO
    car's deceleration) so as to stand with their centre at y = stop_y."""
    ego_x, v = 0.0, ego_v
    tracks: tuple[Track, ...] = ()
    nid = 0
    out = []
    for k in range(round(seconds / DT)):
        t = k * DT
        now = tuple((x + vx * t, y + vy * t) if stop_y is None else _braking(x, y, vy, stop_y, t)
                    for x, y, _, vx, vy in others)
        obs = tuple(Obstacle(px, py, o[2], 4.5, 1.8) for (px, py), o in zip(now, others, strict=True))
        tracks, nid = track(tracks, obs, DT, nid)
        route = _route(ego_x, junction=junction, priority=priority)
        p = plan(Pose(ego_x, 0.0, 0.0, 0.0), v, EGO_LEN, route, tracks, cfg, DT)
        out.append(_Step(ego_x, v, p, now))
        ego_x += p.speed * DT
        v = p.speed
    return out


def _braking(x: float, y: float, vy: float, stop_y: float, t: float) -> tuple[float, float]:
    """Northbound at vy until it must brake at 4.5 m/s^2 to stand at stop_y, then braking to it."""
    brake_at = stop_y - vy * vy / (2 * 4.5) - y  # distance driven at constant speed
    t_brake = brake_at / vy
    if t <= t_brake:
        return x, y + vy * t
    tau = min(t - t_brake, vy / 4.5)
    return x, y + brake_at + vy * tau - 4.5 * tau * tau / 2


_REACH = PlannerConfig().corridor_half_width_m + 4.5 / 2  # a foe this close to the ego's path is on it


def _gap(step: _Step, i: int = 0) -> float:
    """Bumper-to-bumper gap from the ego to other vehicle i ahead of it on the x axis."""
    return step.others[i][0] - 4.5 / 2 - (step.ego_x + EGO_LEN / 2)


def test_follows_a_perceived_leader_at_the_idm_equilibrium_gap() -> None:
    cfg = PlannerConfig(desired_speed=25.0)
    steps = _drive(15.0, [(EGO_LEN / 2 + 30.0, 0.0, 0.0, 10.0, 0.0)], 20.0, cfg)
    assert steps[0].plan.reason == "leader" and steps[0].plan.accel < 0
    assert all(s.plan.reason == "leader" for s in steps)
    assert min(_gap(s) for s in steps) > 0  # never collides
    end = steps[-1]
    assert abs(end.speed - 10.0) < 0.3
    # Equilibrium of Eq. 2 with dv = 0: s = s* / sqrt(1 - (v/v0)^delta), s* = s0 + v T = 17 m, here 17.2 m.
    assert abs(_gap(end) - (cfg.min_gap_m + 10.0 * cfg.time_headway_s)) < 1.5


def test_stops_behind_a_perceived_standing_obstacle() -> None:
    cfg = PlannerConfig()
    steps = _drive(14.0, [(EGO_LEN / 2 + 40.0, 0.0, 0.0, 0.0, 0.0)], 30.0, cfg)
    assert all(s.plan.speed >= 0.0 for s in steps)
    assert all(s.plan.accel >= -cfg.max_decel - 1e-9 for s in steps)
    assert steps[-1].speed < 0.05
    assert min(_gap(s) for s in steps) > 0
    assert 1.0 < _gap(steps[-1]) < 5.0


def test_yields_to_a_crossing_vehicle_whose_gap_is_too_short() -> None:
    """12 m/s from 30 m below the zone (2.2 s to within reach of the ego's path < 5 s): the ego brakes for the
    line, is still short of it when the crossing vehicle has left its path, then goes."""
    cfg = PlannerConfig()
    foe = (LINE_X + 5.0, -5.0 - 30.0, math.pi / 2, 0.0, 12.0)
    steps = _drive(10.0, [foe], 10.0, cfg, junction=True)
    assert steps[0].plan.reason == "yield" and steps[0].plan.obstacle is not None
    clear_t = (_REACH - foe[1]) / 12.0  # the foe's centre is out of reach of the ego's path (y = 0) again
    waiting = [s for k, s in enumerate(steps) if k * DT < clear_t]
    assert max(s.ego_x + EGO_LEN / 2 for s in waiting) < LINE_X  # never past the line while the foe is in the way
    assert all(s.plan.reason == "yield" for s in waiting[1:])
    assert steps[-1].ego_x + EGO_LEN / 2 > LINE_X  # and went once the junction was clear


def test_stops_at_the_line_for_a_stream_of_crossing_vehicles() -> None:
    """Six vehicles 20 m apart at 12 m/s (1.7 s gaps) keep the junction blocked for 12 s: the ego comes to rest
    about s0 before the stop line, waits there, and goes after the last one."""
    cfg = PlannerConfig()
    stream = [(LINE_X + 5.0, -35.0 - 20.0 * j, math.pi / 2, 0.0, 12.0) for j in range(6)]
    steps = _drive(10.0, stream, 16.0, cfg, junction=True)
    last_clear_t = (_REACH - stream[-1][1]) / 12.0
    waiting = [s for k, s in enumerate(steps) if k * DT < last_clear_t]
    assert all(s.plan.speed >= 0.0 and s.plan.accel >= -cfg.max_decel - 1e-9 for s in steps)
    assert max(s.ego_x + EGO_LEN / 2 for s in waiting) < LINE_X
    at_rest = waiting[-1]
    assert at_rest.speed < 0.05 and at_rest.plan.reason == "yield"
    assert 0.5 < LINE_X - (at_rest.ego_x + EGO_LEN / 2) < 4.0
    assert steps[-1].ego_x + EGO_LEN / 2 > LINE_X


def test_proceeds_when_the_crossing_vehicle_is_far() -> None:
    """The same vehicle 100 m away (8.2 s to the grown zone) leaves an acceptable gap: no yielding at all."""
    cfg = PlannerConfig()
    steps = _drive(10.0, [(LINE_X + 5.0, -5.0 - 100.0, math.pi / 2, 0.0, 12.0)], 4.0, cfg, junction=True)
    assert all(s.plan.reason != "yield" for s in steps)
    assert steps[-1].ego_x + EGO_LEN / 2 > LINE_X
    assert all(s.plan.accel > 0 for s in steps)


def _new_track(x: float, y: float, yaw: float) -> Track:
    return Track(0, x, y, yaw, 4.5, 1.8, 0.0, 0.0, 1)


def test_a_new_track_of_unknown_speed_pointing_at_the_zone_is_yielded_to() -> None:
    cfg = PlannerConfig()
    route = _route(0.0, junction=True)
    ego = Pose(0.0, 0.0, 0.0, 0.0)
    for yaw in (math.pi / 2, -math.pi / 2):  # pointing at the zone, or away from it: a blob's yaw has no front
        p = plan(ego, 10.0, EGO_LEN, route, (_new_track(LINE_X + 5.0, -5.0 - 40.0, yaw),), cfg, DT)
        assert p.reason == "yield" and p.obstacle is not None and p.speed < 10.0
    # Driving past the zone (its heading misses it either way) and far away (98 m / 13.9 m/s = 7 s): no conflict.
    assert plan(ego, 10.0, EGO_LEN, route, (_new_track(LINE_X + 5.0, -30.0, 0.0),), cfg, DT).reason == "free"
    assert plan(ego, 10.0, EGO_LEN, route, (_new_track(LINE_X + 5.0, -105.0, math.pi / 2),), cfg, DT).reason == "free"


def test_own_lane_traffic_is_not_a_crossing_foe() -> None:
    """A follower closing in behind and a vehicle ahead driving through the junction the ego's way are car
    following, not gap acceptance; a track on the ego itself is ignored."""
    cfg = PlannerConfig()
    route = _route(0.0, junction=True)
    ego = Pose(0.0, 0.0, 0.0, 0.0)
    follower = Track(1, -10.0, 0.0, 0.0, 4.5, 1.8, 12.0, 0.0, 5)
    through = Track(2, LINE_X + 5.0, 0.2, 0.0, 4.5, 1.8, 10.0, 0.0, 5)  # inside the zone, going east
    itself = Track(3, 0.3, 0.1, 0.0, 4.5, 1.8, 10.0, 0.0, 5)
    p = plan(ego, 10.0, EGO_LEN, route, (follower, through, itself), cfg, DT)
    assert p.reason == "leader" and p.obstacle == through
    crossing = Track(4, LINE_X + 5.0, 0.2, math.pi / 2, 4.5, 1.8, 0.0, 8.0, 5)  # inside the zone, going north
    assert plan(ego, 10.0, EGO_LEN, route, (crossing,), cfg, DT).reason == "yield"


def test_an_obstacle_beside_the_path_is_not_a_leader() -> None:
    cfg = PlannerConfig()
    route = _route(0.0)
    ego = Pose(0.0, 0.0, 0.0, 0.0)
    beside = Track(0, 20.0, 5.0, 0.0, 4.5, 1.8, 0.0, 0.0, 3)
    assert find_leader(route, (beside,), cfg) is None
    p = plan(ego, 10.0, EGO_LEN, route, (beside,), cfg, DT)
    assert p.reason == "free" and p.obstacle is None and p.accel > 0
    straddling = Track(0, 20.0, 2.0, 0.0, 4.5, 1.8, 0.0, 0.0, 3)  # 2 m off: its footprint reaches the lane
    assert plan(ego, 10.0, EGO_LEN, route, (straddling,), cfg, DT).reason == "leader"
    behind = Track(0, -10.0, 0.0, 0.0, 4.5, 1.8, 0.0, 0.0, 3)
    assert plan(ego, 10.0, EGO_LEN, route, (behind,), cfg, DT).reason == "free"


def test_a_stop_line_without_a_zone_is_held() -> None:
    route = RouteAhead(np.array([[2.25, 0.0], [300.0, 0.0]]), 13.9, 10.0, None)
    p = plan(Pose(0.0, 0.0, 0.0, 0.0), 10.0, EGO_LEN, route, (), PlannerConfig(), DT)
    assert p.reason == "stop_line" and p.obstacle is None and p.accel < 0


def test_commands_stay_within_limits_and_never_reverse() -> None:
    cfg = PlannerConfig()
    wall = Track(0, EGO_LEN / 2 + 3.0, 0.0, 0.0, 4.5, 1.8, 0.0, 0.0, 3)  # 0.75 m ahead at 20 m/s
    p = plan(Pose(0.0, 0.0, 0.0, 0.0), 20.0, EGO_LEN, _route(0.0), (wall,), cfg, DT)
    assert p.accel == -cfg.max_decel and np.isclose(p.speed, 20.0 - cfg.max_decel * DT)
    p = plan(Pose(0.0, 0.0, 0.0, 0.0), 0.3, EGO_LEN, _route(0.0), (wall,), cfg, DT)
    assert p.speed == 0.0 and np.isclose(p.accel, -3.0)


def test_polyline_projection() -> None:
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # east, then north
    s, lat, tangent = project_onto_polyline(path, np.array([[5.0, 1.0], [11.0, 4.0], [-3.0, -2.0], [10.0, 15.0]]))
    assert np.allclose(s, [5.0, 14.0, -3.0, 25.0])  # the ends are extended: behind is s < 0, beyond s > length
    assert np.allclose(lat, [1.0, -1.0, -2.0, 0.0])
    assert np.allclose(tangent, [[1, 0], [0, 1], [1, 0], [0, 1]])


def test_rays_and_the_grown_polygon() -> None:
    square = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    assert point_in_polygon(square, np.array([[5.0, 5.0], [11.0, 5.0]])).tolist() == [True, False]
    assert np.isclose(ray_to_grown_polygon(square, 2.0, np.array([5.0, -30.0]), np.array([0.0, 3.0])), 28.0)
    assert ray_to_grown_polygon(square, 2.0, np.array([5.0, -30.0]), np.array([0.0, -1.0])) == math.inf
    assert ray_to_grown_polygon(square, 2.0, np.array([11.0, 5.0]), np.array([1.0, 0.0])) == 0.0
    # Towards a corner along the diagonal: the grown corner is a disc of radius 2 around (0, 0).
    d = ray_to_grown_polygon(square, 2.0, np.array([-10.0, -10.0]), np.array([1.0, 1.0]))
    assert np.isclose(d, math.hypot(10.0, 10.0) - 2.0)
    # Passing 1.5 m beside the square's side: inside the margin, so a hit where the ray meets the grown side.
    assert np.isclose(ray_to_grown_polygon(square, 2.0, np.array([11.5, -20.0]), np.array([0.0, 1.0])),
                      20.0 - math.sqrt(4.0 - 1.5**2))


def test_stops_at_a_red_light_whatever_the_traffic() -> None:
    cfg = PlannerConfig()
    ego_x, v = 0.0, 12.0
    reasons = set()
    for _ in range(200):  # 20 s with the light red 40 m ahead of the bumper's start, no other vehicle
        front = ego_x + EGO_LEN / 2
        route = RouteAhead(np.array([[front, 0.0], [front + 300.0, 0.0]]), 13.9, None, None, red_m=40.0 - front)
        p = plan(Pose(ego_x, 0.0, 0.0, 0.0), v, EGO_LEN, route, (), cfg, DT)
        reasons.add(p.reason)
        ego_x += p.speed * DT
        v = p.speed
    assert v < 0.05 and 0.0 < 40.0 - (ego_x + EGO_LEN / 2) < 3.0 and "red_light" in reasons


def test_a_vehicle_waiting_in_the_junction_blocks_only_on_the_ego_s_path() -> None:
    """The ego's path crosses the zone along y = 0. A standing vehicle in the zone 4.5 m to its side (waiting to
    turn, say) leaves it room; one standing across its path does not."""
    cfg = PlannerConfig()
    aside = (LINE_X + 5.0, 4.5, 0.0, 0.0, 0.0)
    across = (LINE_X + 5.0, 0.5, math.pi / 2, 0.0, 0.0)
    assert all(s.plan.reason != "yield" for s in _drive(8.0, [aside], 3.0, cfg, junction=True))
    blocked = _drive(8.0, [across], 6.0, cfg, junction=True)
    assert blocked[-1].plan.reason == "yield" and blocked[-1].ego_x + EGO_LEN / 2 < LINE_X


def test_with_priority_it_gives_way_to_a_crossing_vehicle_that_cannot_stop() -> None:
    """A green light (no stop line) and a red-light runner: 11 m/s northbound, timed to be on the ego's path when
    the ego would be (both there ~2.5 s in). The ego brakes for the junction's entry as soon as the runner can no
    longer stop before the junction (v^2 / 2d > 6 m/s^2: its front 10 m from the zone), is never on the runner's
    path while the runner is, and goes after it. Without the rule (yield_to_violators false) it drives on into the
    runner's path."""
    runner = (LINE_X + 5.0, -26.0, math.pi / 2, 0.0, 11.0)
    clear_t = (_REACH - runner[1]) / 11.0
    steps = _drive(11.0, [runner], 8.0, PlannerConfig(), junction=True, priority=True)
    assert steps[0].plan.reason == "free"  # 18.75 m from the zone: it could still stop at 3.2 m/s^2
    assert any(s.plan.reason == "yield" and s.plan.obstacle is not None for s in steps)
    on_path = [s for k, s in enumerate(steps) if abs(s.others[0][1]) <= _REACH]
    assert on_path and all(s.ego_x + EGO_LEN / 2 < LINE_X + 5.0 - 1.0 for s in on_path)  # short of its lane
    assert steps[-1].ego_x + EGO_LEN / 2 > LINE_X + 10.0 and clear_t < 8.0  # and went on after it
    careless = _drive(11.0, [runner], 8.0, PlannerConfig(yield_to_violators=False), junction=True, priority=True)
    assert all(s.plan.reason != "yield" for s in careless)
    # footprints (4.5 x 1.8 m, crossing at right angles) overlap: |dx| and |dy| both within 2.25 + 0.9 m
    assert any(abs(s.others[0][1]) <= 3.15 and abs(s.ego_x - s.others[0][0]) <= 3.15 for s in careless)


def test_with_priority_a_vehicle_stopping_for_its_red_is_not_a_violator() -> None:
    """The same car braking at 4.5 m/s^2 to stand at its line (centre 2.25 m before the zone), and one already
    standing there: the ego keeps its speed through the junction."""
    cfg = PlannerConfig()
    stopping = (LINE_X + 5.0, -26.0, math.pi / 2, 0.0, 11.0)
    steps = _drive(11.0, [stopping], 5.0, cfg, junction=True, priority=True, stop_y=-5.0 - 2.25)
    assert all(s.plan.reason != "yield" for s in steps)
    assert steps[-1].ego_x + EGO_LEN / 2 > LINE_X + 10.0
    standing = (LINE_X + 5.0, -7.25, math.pi / 2, 0.0, 0.0)
    assert all(s.plan.reason != "yield" for s in _drive(11.0, [standing], 5.0, cfg, junction=True, priority=True))
