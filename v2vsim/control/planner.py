"""The ego's longitudinal planner: a commanded speed along its fixed route from perceived tracks only.

Two terms, each an acceleration; the smaller one wins and `Plan.reason` says which:
  (a) car following with the Intelligent Driver Model (Treiber, Hennecke & Helbing 2000, Phys. Rev. E 62, 1805,
      Eqs. 2-3) behind the nearest perceived vehicle in the ego's corridor, or IDM's free-road term without one;
  (b) yielding at the stop line of a junction where the ego has no priority: a gap-acceptance test on every
      perceived vehicle near the junction's conflict zone; when the gap is too short the stop line becomes a
      standing virtual leader, so IDM brings the ego to rest in front of it. Where the ego has priority (a green
      light, the main road) it still gives way to a crossing vehicle that will not: one that reaches its path
      while the ego would be on it and can no longer stop before the junction (a red-light runner;
      `find_violator`), with the junction's entry as the virtual leader, unless the ego itself can no longer stop
      before it (it is then committed and carries on).
The winner is clamped to the vehicle's limits and integrated over one step (explicit Euler).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from v2vsim.control.geometry import (
    in_grown_polygon,
    point_in_polygon,
    polyline_length,
    project_onto_polyline,
    ray_to_grown_polygon,
)
from v2vsim.control.tracking import Track
from v2vsim.world.geometry import Pose, world_to_body

_MIN_GAP_FOR_IDM_M = 0.1  # IDM's interaction term diverges at s -> 0; a touching leader still means "brake hard"
_SELF_RADIUS_M = 1.0  # a track this close to the ego's centre is the ego seen by its own perception


@dataclass(frozen=True)
class RouteAhead:
    """What the ego knows of its own route (from the map, not from perception)."""

    path: np.ndarray  # (M, 2) world-frame polyline from the vehicle's front bumper forward along its route
    speed_limit: float
    stop_m: float | None  # distance along path to the stop line where it must yield (None: priority, or passed it)
    conflict_zone: np.ndarray | None  # (K, 2) world polygon of the junction area it crosses next (None: past it)
    red_m: float | None = None  # distance along path to a traffic light showing red or amber (None: none ahead)


@dataclass(frozen=True)
class PlannerConfig:
    """IDM parameters (Treiber et al. 2000, Table 1 names) and the corridor / gap-acceptance rules."""

    desired_speed: float | None = None  # v0; None = the route's speed limit
    time_headway_s: float = 1.5  # T
    min_gap_m: float = 2.0  # s0
    max_accel: float = 2.0  # a
    comfort_decel: float = 3.0  # b
    max_decel: float = 8.0  # hard limit of any command
    delta: float = 4.0  # acceleration exponent
    corridor_half_width_m: float = 1.5  # half a lane: in the path when |lateral| <= this + the obstacle's width/2
    gap_acceptance_s: float = 5.0  # a foe reaching the conflict zone sooner than this blocks the crossing
    zone_margin_m: float = 2.0  # the conflict zone is grown by this (a vehicle's half length, roughly)
    unknown_speed_mps: float = 13.9  # assumed approach speed of a new track (age 1), whose velocity is unknown
    min_moving_mps: float = 1.0  # slower tracked speeds are estimation noise of a standing vehicle
    yield_to_violators: bool = True  # with priority, give way to a crossing vehicle that cannot stop (find_violator)
    violator_margin_s: float = 1.0  # the ego's and a violator's times on the conflict may come this close
    # a crossing vehicle that would need to brake harder than this to stop before the junction will not stop:
    # SUMO's cars brake for a red light or a give-way line at up to 4.5 m/s^2; the rest is the tracker's lag
    violator_decel: float = 6.0


@dataclass(frozen=True)
class Plan:
    """The command for the next step."""

    speed: float  # commanded speed for the next step, m/s, >= 0
    accel: float
    reason: str  # "free" | "leader" | "yield" | "stop_line"
    obstacle: Track | None  # what the plan brakes for (None for free / stop_line without a foe)


@dataclass(frozen=True)
class _Term:
    """One candidate acceleration and why."""

    accel: float
    reason: str
    obstacle: Track | None


def idm_acceleration(speed: float, cfg: PlannerConfig, v0: float, gap: float | None = None,
                     approach_rate: float = 0.0) -> float:
    """IDM acceleration (Treiber et al. 2000, Eq. 2): a [1 - (v/v0)^delta - (s*/s)^2] with the desired gap
    s* = s0 + max(0, v T + v dv / (2 sqrt(a b))) (Eq. 3), dv = v - v_leader; without a leader (gap None) the
    free-road term a [1 - (v/v0)^delta] alone."""
    v = max(speed, 0.0)
    free = 1.0 - (v / max(v0, 1e-3)) ** cfg.delta
    if gap is None:
        return cfg.max_accel * free
    s_star = cfg.min_gap_m + max(
        0.0, v * cfg.time_headway_s + v * approach_rate / (2.0 * math.sqrt(cfg.max_accel * cfg.comfort_decel))
    )
    return cfg.max_accel * (free - (s_star / max(gap, _MIN_GAP_FOR_IDM_M)) ** 2)


def find_leader(route: RouteAhead, tracks: tuple[Track, ...], cfg: PlannerConfig) -> tuple[Track, float, float] | None:
    """The nearest track in the ego's corridor ahead: (track, bumper gap, its speed along the path >= 0).

    In the corridor: the centre projects onto the path at 0 < s <= path length and its lateral offset is at most
    corridor_half_width + width/2 (the footprint reaches into the lane). Gap = s - length/2 (the path starts at the
    ego's front bumper). A new track (age 1) has no velocity yet and counts as standing: the cautious reading.
    """
    if not tracks or len(route.path) < 2 or polyline_length(route.path) <= 0.0:
        return None
    xy = np.array([[t.x, t.y] for t in tracks])
    s, lat, tangent = project_onto_polyline(route.path, xy)
    widths = np.array([t.width for t in tracks])
    lengths = np.array([t.length for t in tracks])
    inside = (s > 0) & (s <= polyline_length(route.path)) & (np.abs(lat) <= cfg.corridor_half_width_m + widths / 2)
    if not inside.any():
        return None
    gaps = np.where(inside, s - lengths / 2, np.inf)
    k = int(np.argmin(gaps))  # ties: the lower index
    t = tracks[k]
    along = t.vx * tangent[k, 0] + t.vy * tangent[k, 1]
    return t, float(gaps[k]), max(float(along), 0.0)


def _leaves_to_car_following(t: Track, s: float, lat: float, tangent: np.ndarray, path_len: float,
                             cfg: PlannerConfig) -> bool:
    """A track ahead in the ego's own corridor heading its way (within 45 deg) is traffic in its lane, not a foe:
    term (a) follows it. Moving tracks are judged by their velocity; standing or new ones by their yaw, modulo pi
    (a BEV blob has no front)."""
    if not (0 < s <= path_len and abs(lat) <= cfg.corridor_half_width_m + t.width / 2):
        return False
    speed = math.hypot(t.vx, t.vy)
    if t.age > 1 and speed >= cfg.min_moving_mps:
        return (t.vx * tangent[0] + t.vy * tangent[1]) / speed > math.cos(math.pi / 4)
    return abs(math.sin(t.yaw - math.atan2(tangent[1], tangent[0]))) < math.sin(math.pi / 4)


def time_to_zone(t: Track, zone: np.ndarray, cfg: PlannerConfig) -> float:
    """Seconds until the track's centre reaches the conflict zone grown by zone_margin_m (0 inside, inf never).

    A tracked vehicle (age > 1) moves on along its velocity: distance along that ray to the grown zone / speed; one
    slower than min_moving_mps stands. A new track's velocity is unknown: it is assumed to drive at
    unknown_speed_mps along its yaw, either way (the yaw of a BEV blob is ambiguous by pi), the sooner arrival.
    """
    centre = np.array([t.x, t.y])
    if bool(in_grown_polygon(zone, cfg.zone_margin_m, centre[None])[0]):
        return 0.0
    if t.age > 1:
        speed = math.hypot(t.vx, t.vy)
        if speed < cfg.min_moving_mps:
            return math.inf
        return ray_to_grown_polygon(zone, cfg.zone_margin_m, centre, np.array([t.vx, t.vy])) / speed
    heading = np.array([math.cos(t.yaw), math.sin(t.yaw)])
    dist = min(ray_to_grown_polygon(zone, cfg.zone_margin_m, centre, heading),
               ray_to_grown_polygon(zone, cfg.zone_margin_m, centre, -heading))
    return dist / max(cfg.unknown_speed_mps, 1e-3)


PREDICT_STEP_S = 0.1  # time step of a foe's constant-velocity prediction (time_to_path)
CONFLICT_STEP_M = 1.0  # spacing of the points of the ego's path inside the junction (conflict_points)


def _path_samples(path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (M >= 2, 2) path sampled every CONFLICT_STEP_M: arc lengths (C,) and points (C, 2)."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    at = np.arange(0.0, s[-1] + 1e-9, CONFLICT_STEP_M)
    return at, np.stack([np.interp(at, s, path[:, 0]), np.interp(at, s, path[:, 1])], axis=1)


def conflict_points(route: RouteAhead, cfg: PlannerConfig) -> np.ndarray:
    """(C, 2) points every CONFLICT_STEP_M of the ego's path that lie in the conflict zone grown by zone_margin_m:
    the part of the junction the ego will sweep. Empty when the path does not enter it."""
    if route.conflict_zone is None or len(route.path) < 2:
        return np.zeros((0, 2))
    _, pts = _path_samples(route.path)
    return pts[in_grown_polygon(route.conflict_zone, cfg.zone_margin_m, pts)]


def time_to_path(t: Track, points: np.ndarray, cfg: PlannerConfig) -> float:
    """Seconds until the track comes within reach of the ego's path through the junction (`points`): its centre
    within corridor_half_width_m + its length / 2 of a point (0 already there; inf not within gap_acceptance_s).

    Constant velocity over the gap-acceptance horizon; a track slower than min_moving_mps stands; a new track
    (velocity unknown) drives at unknown_speed_mps along its yaw, either way, the sooner arrival. Unlike the whole
    junction outline, this lets the ego go past a vehicle that waits in another part of the junction."""
    reach = cfg.corridor_half_width_m + t.length / 2
    taus = np.arange(0.0, cfg.gap_acceptance_s + 1e-9, PREDICT_STEP_S)
    if t.age > 1:
        speed = math.hypot(t.vx, t.vy)
        velocities = [np.array([t.vx, t.vy]) if speed >= cfg.min_moving_mps else np.zeros(2)]
    else:
        heading = cfg.unknown_speed_mps * np.array([math.cos(t.yaw), math.sin(t.yaw)])
        velocities = [heading, -heading]
    best = math.inf
    for v in velocities:
        at = np.array([t.x, t.y]) + taus[:, None] * v  # [T, 2]
        near = (np.linalg.norm(at[:, None, :] - points[None, :, :], axis=-1) <= reach).any(axis=1)  # [T]
        if near.any():
            best = min(best, float(taus[int(np.argmax(near))]))
    return best


def _crossing_candidates(pose: Pose, length: float, route: RouteAhead, tracks: tuple[Track, ...],
                         cfg: PlannerConfig) -> list[Track]:
    """The tracks that may cross the ego's path: not the ego itself (within 1 m of its centre), not traffic behind
    its front bumper in its own lane (it cannot reach the junction first), not traffic ahead in its own lane going
    its way (term (a) follows it)."""
    xy = np.array([[t.x, t.y] for t in tracks]).reshape(-1, 2)
    body = world_to_body(xy, pose)
    has_path = len(route.path) >= 2 and polyline_length(route.path) > 0.0
    if has_path:
        s, lat, tangent = project_onto_polyline(route.path, xy)
        path_len = polyline_length(route.path)
    out = []
    for i, t in enumerate(tracks):
        bx, by = float(body[i, 0]), float(body[i, 1])
        if math.hypot(bx, by) <= _SELF_RADIUS_M:
            continue
        if abs(by) <= cfg.corridor_half_width_m + t.width / 2 and bx < length / 2:
            continue
        if has_path and _leaves_to_car_following(t, float(s[i]), float(lat[i]), tangent[i], path_len, cfg):
            continue
        out.append(t)
    return out


def zone_entry_m(route: RouteAhead) -> float | None:
    """Distance along the path (from the front bumper) to where it enters the conflict zone (0: the bumper is in
    it), to CONFLICT_STEP_M; None without a zone or when the path does not enter it."""
    if route.conflict_zone is None or len(route.path) < 2:
        return None
    at, pts = _path_samples(route.path)
    inside = point_in_polygon(route.conflict_zone, pts)
    return float(at[int(np.argmax(inside))]) if inside.any() else None


def find_violator(pose: Pose, speed: float, length: float, route: RouteAhead, tracks: tuple[Track, ...],
                  cfg: PlannerConfig, entry: float) -> tuple[Track, float] | None:
    """With priority, the crossing vehicle that will not give way, with its time to the ego's path, or None.
    `entry`: zone_entry_m of the route (> 0: the ego is not in the junction yet).

    A violator is tracked (age > 1: its speed is known) and moving, reaches the ego's path through the junction
    (time_to_path, constant velocity) at t_f, and can no longer stop before the junction: v^2 / (2 d) >
    violator_decel, d from its front bumper along its velocity to the conflict zone (0 already in it). It must
    also meet the ego there: it is on the path during [t_f, t_f + 2 reach / v] (reach = corridor_half_width + its
    length / 2), the ego during [entry / v_e, (last conflict point + ego length) / v_e] (v_e = max(its speed,
    min_moving_mps)), and the two come within violator_margin_s. Until a vehicle is that close to the junction it
    cannot be told from one that will brake for its red light; from then on an ego that sees it can still stop
    (Coopernaut's red-light-runner scenario); one that cannot see it cannot.
    """
    zone = route.conflict_zone
    points = conflict_points(route, cfg)
    if zone is None or entry <= 0.0 or not len(points) or not tracks:
        return None
    s_last, _, _ = project_onto_polyline(route.path, points[-1:])  # arc length of the last conflict point
    v_e = max(speed, cfg.min_moving_mps)
    ego_in, ego_out = entry / v_e, (float(s_last[0]) + length) / v_e
    best: tuple[Track, float] | None = None
    for t in _crossing_candidates(pose, length, route, tracks, cfg):
        v = math.hypot(t.vx, t.vy)
        if t.age <= 1 or v < cfg.min_moving_mps:
            continue
        tt = time_to_path(t, points, cfg)
        if not math.isfinite(tt):
            continue
        to_zone = ray_to_grown_polygon(zone, 0.0, np.array([t.x, t.y]), np.array([t.vx, t.vy])) - t.length / 2
        if v * v / (2.0 * max(to_zone, 0.1)) <= cfg.violator_decel:
            continue
        f_out = tt + 2.0 * (cfg.corridor_half_width_m + t.length / 2) / v
        if tt <= ego_out + cfg.violator_margin_s and f_out >= ego_in - cfg.violator_margin_s:
            if best is None or tt < best[1]:
                best = (t, tt)
    return best


def find_blocker(pose: Pose, length: float, route: RouteAhead, tracks: tuple[Track, ...],
                 cfg: PlannerConfig) -> tuple[Track, float] | None:
    """The foe that makes the gap unacceptable, with its time to the ego's path (the soonest one), or None.

    A foe blocks when it is on the ego's path through the junction (the path's points in the grown conflict zone),
    or reaches it in less than gap_acceptance_s (time_to_path; the zone itself when the path does not enter it).
    Not foes: a track within 1 m of the ego's centre (the ego itself), traffic behind the ego's front bumper in its
    own lane (it cannot reach the junction first, and would otherwise hold the ego up for as long as it queues
    behind), and traffic ahead in its own lane going its way (term (a) follows it).
    """
    zone = route.conflict_zone
    if zone is None or not tracks:
        return None
    points = conflict_points(route, cfg)
    best: tuple[Track, float] | None = None
    for t in _crossing_candidates(pose, length, route, tracks, cfg):
        tt = time_to_path(t, points, cfg) if len(points) else time_to_zone(t, zone, cfg)
        if tt < cfg.gap_acceptance_s and (best is None or tt < best[1]):
            best = (t, tt)
    return best


def plan(pose: Pose, speed: float, length: float, route: RouteAhead, tracks: tuple[Track, ...],
         cfg: PlannerConfig, dt: float) -> Plan:
    """The command for the next step of `dt` seconds.

    (a) IDM behind `find_leader`'s leader (dv = v - v_leader), or free road. (b) With a stop line ahead
    (route.stop_m not None): if `find_blocker` finds a foe, the line is a standing virtual leader at gap
    max(stop_m, 0.1) (dv = v) and the reason is "yield"; without a foe there is no stop-line term at all, near the
    line (the ego proceeds) or far from it (it approaches under (a)): the decision is made again every frame until
    the caller clears stop_m once the front bumper has passed the line. A stop line without a conflict zone cannot
    be judged and is held as a standing leader ("stop_line", no foe). The smaller acceleration wins, clamped to
    [-max_decel, max_accel]; speed = max(0, v + a dt), and a stop within the step reports a = -v / dt.
    """
    if dt <= 0:
        raise ValueError("dt must be positive")
    v = max(float(speed), 0.0)
    v0 = cfg.desired_speed if cfg.desired_speed is not None else route.speed_limit
    leader = find_leader(route, tracks, cfg)
    if leader is None:
        terms = [_Term(idm_acceleration(v, cfg, v0), "free", None)]
    else:
        lt, gap, v_lead = leader
        terms = [_Term(idm_acceleration(v, cfg, v0, gap, v - v_lead), "leader", lt)]
    if route.stop_m is not None:
        line_gap = max(route.stop_m, _MIN_GAP_FOR_IDM_M)
        if route.conflict_zone is None:
            terms.append(_Term(idm_acceleration(v, cfg, v0, line_gap, v), "stop_line", None))
        else:
            blocker = find_blocker(pose, length, route, tracks, cfg)
            if blocker is not None:
                terms.append(_Term(idm_acceleration(v, cfg, v0, line_gap, v), "yield", blocker[0]))
    elif route.conflict_zone is not None and cfg.yield_to_violators:
        entry = zone_entry_m(route)
        # the junction's entry is the standing virtual leader, while the ego can still stop before it: braking
        # that cannot would leave it standing in the violator's way, so it carries on instead (it is committed)
        if entry is not None and v * v / (2.0 * cfg.max_decel) <= entry:
            violator = find_violator(pose, v, length, route, tracks, cfg, entry)
            if violator is not None:
                terms.append(_Term(idm_acceleration(v, cfg, v0, max(entry, _MIN_GAP_FOR_IDM_M), v), "yield",
                                   violator[0]))
    if route.red_m is not None:  # a red (or amber) light: its stop line is a standing leader, whatever the traffic
        terms.append(_Term(idm_acceleration(v, cfg, v0, max(route.red_m, _MIN_GAP_FOR_IDM_M), v), "red_light", None))
    win = min(terms, key=lambda term: term.accel)  # min keeps the first of equal ones: (a) before (b)
    a = min(max(win.accel, -cfg.max_decel), cfg.max_accel)
    new_speed = v + a * dt
    if new_speed < 0.0:
        new_speed, a = 0.0, -v / dt
    return Plan(speed=new_speed, accel=a, reason=win.reason, obstacle=win.obstacle)
