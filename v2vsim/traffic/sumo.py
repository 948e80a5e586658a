"""SUMO traffic backend through libsumo (in-process, no TraCI socket).

Why libsumo and subscriptions: a socket round trip per getter per vehicle per step would cost
more than the simulation itself; one variable subscription per vehicle (made when it departs)
and a single `getAllSubscriptionResults()` per step gives every pose at once.

What the backend does, net-agnostically:
1. Analyse the network (sumolib): the main junction is the node with the most incoming edges;
   every shortest path from a fringe source edge to a fringe sink edge that crosses it is a
   route; the edge entering the junction names the route's *arm*; the turn at the junction gives
   its movement (straight / left / right).
2. Background traffic: a Poisson stream of `background_per_hour` vehicles in total, arms drawn
   uniformly and movements 2:1:1 (straight:left:right); a mix of cars, vans and trucks. The
   stream starts before t=0 so that the arms are already populated ("prefill") instead of
   empty when the warm-up begins. Drawn with numpy from the scenario seed; SUMO itself runs
   with `--seed`, so a seed fully determines a run.
3. CAVs "cav0".."cav{N-1}": cav0 approaches from a minor-road arm if there is one (it yields,
   so it lingers at the junction), else from the arm pointing most to the west (it drives east
   into the junction); cav1 from the arm most opposite to it, then the side arms, then further
   rounds on other lanes / further back. Each CAV is inserted one step before frame 0 at a free
   spot `v * t_i` before its stop line, where t_i (its free-flow arrival time) lies in
   `cavs.arrival_s` (default 0..4 s): the CAVs start near the junction and meet from frame 0.
   A spot is accepted only if SUMO's safe-gap rule will let the CAV in (a refused one is
   re-placed more cautiously, which at worst delays frame 0 by a step or two).
4. Placement by look-ahead (`cavs.meet`). Where the CAVs end up depends on what no formula
   knows in general: the signal phase at frame 0 (a CAV at red waits for tens of seconds while
   one with green leaves at ~14 m/s), yielding, queues of background traffic, and CAVs that
   cross in opposite directions separating at ~28 m/s. So `reset()` simulates candidate
   placements ahead over the scenario's duration (same seed, same warm-up: libsumo runs a
   candidate in ~0.03-0.06 s) and keeps the one where the first ego (cav0 by default) has at
   least `cavs.meet.neighbours` (2) other CAVs within `comm.range_m` (centre distance) in at
   least `cavs.meet.share` (0.9) of the frames from frame 0, and is still in the simulation at
   the last frame; among those, the one with the most distinct arms (CAVs that see the junction
   from different sides are what cooperation needs); if none qualifies, the one with the most
   such frames. Candidate 0 is the canonical plan above (movements from `_CAV_MOVES`, arrival
   times spread evenly over the window in CAV order); the others (`cavs.meet.trials` in all) are
   drawn from a generator seeded with the scenario seed: arrival times in the window, routes
   among the arm's movements (half of the time the one that leaves by cav0's exit, so the two
   drive off together), and in the second half of the trials a CAV may share an earlier CAV's
   arm (another lane, or behind it). The search stops at the first candidate that qualifies
   from min(N, arms) arms. Only the topology analysis above is used, so it works on any net;
   the whole procedure is deterministic per seed, and a backend keeps its choice for later resets
   (`placement` on the backend says which candidate won and how it scored). With
   `cavs.meet.trials: 1` the canonical plan is used unchecked.
   Exit edges are the long arms, so a CAV stays in the simulation for a while after crossing.

SUMO runs with `--lanechange.duration 2` (lane changes move sideways over 2 s instead of
jumping 3.5 m in one step), no teleports and collisions only noted, so a vehicle never vanishes
and reappears; only leaving the network removes it. Logs and warnings are off.

Conversions (DESIGN.md frames): SUMO's angle is degrees clockwise from north, yaw is radians
counter-clockwise from +x: yaw = radians(90 - angle). SUMO's position is the front bumper
centre; the footprint centre is length/2 behind it along the heading.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np
import sumolib

from v2vsim.config import Scenario
from v2vsim.traffic.base import BackendBase, cav_id
from v2vsim.traffic.static_map import load_sumo_map
from v2vsim.world.geometry import Pose, wrap_angle
from v2vsim.world.state import Actor, StaticMap, WorldState

# Vehicle types: (id, vClass, length m, width m, height m, max speed m/s, accel m/s^2, decel m/s^2,
# driver imperfection sigma, speed-factor deviation).
# Vans and trucks are tall enough to hide cars behind them (occlusion by traffic, not only buildings).
_VTYPES: tuple[tuple[str, str, float, float, float, float, float, float, float, float], ...] = (
    ("car", "passenger", 4.5, 1.9, 1.5, 50.0, 2.6, 4.5, 0.5, 0.1),
    ("van", "delivery", 5.4, 2.0, 2.4, 40.0, 2.0, 4.0, 0.5, 0.1),
    ("truck", "truck", 8.5, 2.5, 3.4, 30.0, 1.3, 4.0, 0.5, 0.05),
    # CAVs: car-sized, no driver imperfection or speed spread so their timing follows the plan.
    ("cav", "passenger", 4.5, 1.9, 1.5, 50.0, 2.6, 4.5, 0.0, 0.0),
)
_BACKGROUND_MIX = (("car", 0.80), ("van", 0.12), ("truck", 0.08))
_KIND = {"car": "car", "van": "van", "truck": "truck", "cav": "car"}
_MOVEMENT_WEIGHT = {"straight": 2.0, "left": 1.0, "right": 1.0}
# Movement wished for the i-th CAV (falls back to whatever its arm offers): turning CAVs stay
# near the junction longer and cross the paths of the others.
_CAV_MOVES = ("straight", "left", "left", "right", "right", "left")
_MIN_GAP = 2.5  # m, standstill gap of every vehicle type
_CAV_DECEL = 4.5  # m/s^2, the CAV type's comfortable deceleration
_FOLLOWER_DECEL = 4.0  # m/s^2, the smallest deceleration among the background types
_ENTRY_CLEARANCE_M = 40.0  # CAVs are not inserted this close to the start of an edge
_BG_CHUNK_S = 30.0  # background departures are generated this far ahead, lazily
_MAX_DEPART_DELAY_S = 5.0  # a background vehicle that cannot enter for this long is dropped


_ONE_SIM = ("another SUMO simulation is running in this process (libsumo allows one); close() its "
            "backend before starting a new one")


def _libsumo() -> ModuleType:
    """Import libsumo without its pyarrow-version banner on stdout (agents talk over stdout)."""
    with contextlib.redirect_stdout(io.StringIO()):
        import libsumo
    return libsumo


def sumo_to_pose(x_front: float, y_front: float, angle_deg: float, length: float) -> Pose:
    """SUMO front-bumper position + navigation angle -> footprint-centre Pose (z = 0, ground)."""
    yaw = math.radians(90.0 - angle_deg)
    yaw = float(wrap_angle(yaw))
    cx = x_front - 0.5 * length * math.cos(yaw)
    cy = y_front - 0.5 * length * math.sin(yaw)
    return Pose(cx, cy, 0.0, yaw)


def _krauss_safe_speed(v_lead: float, gap: float, decel: float = _CAV_DECEL, tau: float = 1.0) -> float:
    """Largest speed from which a Krauss driver can still stop behind a leader `gap` metres ahead."""
    bt = decel * tau
    return max(0.0, -bt + math.sqrt(bt * bt + v_lead * v_lead + 2.0 * decel * gap))


# ---- network analysis ------------------------------------------------------------------------


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
class CavPlan:
    """Where a CAV is inserted: route (starting at the insertion edge), lane, position."""

    id: str
    route: Route
    edges: tuple[str, ...]
    lane: int
    depart_pos: float  # front-bumper position on edges[0], m
    to_stop_line_m: float  # distance still to drive to the junction at insertion
    arrival_s: float = 0.0  # the planned free-flow time to the stop line


@dataclass(frozen=True)
class CavSpec:
    """A candidate placement of one CAV, before SUMO is asked: route, lane preference, timing."""

    id: str
    route: Route
    slot: int  # rotates the route's usable lanes: CAVs on one arm take different lanes
    arrival_s: float  # free-flow time from insertion to the stop line


@dataclass(frozen=True)
class Placement:
    """The placement chosen by the look-ahead (see module doc) and how it scored."""

    trial: int  # index of the chosen candidate (0 = the canonical one)
    trials_run: int
    share: float  # share of frames with >= `neighbours` other CAVs within comm range of the reference CAV
    neighbours: int  # the count aimed at: min(cavs.meet.neighbours, cavs.count - 1)
    ref_frames: int  # frames (of the look-ahead) the reference CAV was in the simulation
    frames: int  # frames looked ahead (the scenario's duration)
    arms: int  # distinct approach arms among the CAVs
    histogram: tuple[float, ...]  # share of frames with 0, 1, 2, ... other CAVs in range


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


# ---- the backend -----------------------------------------------------------------------------


class SumoBackend(BackendBase):
    """TrafficBackend over libsumo. One running simulation per process (a libsumo limit)."""

    def __init__(self, scenario: Scenario) -> None:
        if scenario.traffic.net is None:
            raise ValueError(f"{scenario.source}: traffic.net is required for the sumo backend")
        self.scenario = scenario
        self._dt = 1.0 / scenario.rate_hz
        self._net = sumolib.net.readNet(scenario.traffic.net, withInternal=True)
        self.topology = analyse_network(self._net)
        self._static = load_sumo_map(scenario.traffic.net, scenario.traffic.buildings,
                                     scenario.traffic.building_height_m, scenario.seed)
        self._running = False
        self._frame = 0
        self._known: list[str] = []  # subscribed vehicle ids in departure order
        self._cav_ids: tuple[str, ...] = tuple(cav_id(i) for i in range(scenario.cavs.count))
        self._rng = np.random.default_rng(scenario.seed)
        self._bg_next_t = 0.0
        self._bg_horizon = 0.0
        self._bg_count = 0
        self.cav_plans: tuple[CavPlan, ...] = ()
        self.placement: Placement | None = None
        self._chosen: tuple[CavSpec, ...] | None = None  # the look-ahead's choice; a later reset() reuses it

    # -- public API ----------------------------------------------------------------------------

    @property
    def static(self) -> StaticMap:
        return self._static

    def reset(self) -> WorldState:
        """Start SUMO, run the warm-up with background traffic, insert the CAVs, return frame 0.

        The CAV placement is chosen first by looking ahead (see module doc; kept for later resets).
        """
        self.close()
        if _libsumo().simulation.isLoaded():
            raise RuntimeError(_ONE_SIM)
        specs = self._choose_placement()
        ls = self._launch(specs)
        return self._state(ls)

    def _launch(self, specs: tuple[CavSpec, ...]) -> ModuleType:
        """Start SUMO, warm up, insert the CAVs of `specs` and take the step that makes frame 0."""
        ls = _libsumo()
        if ls.simulation.isLoaded():
            raise RuntimeError(_ONE_SIM)
        sc = self.scenario
        ls.start(["sumo", "--net-file", sc.traffic.net,
                  "--seed", str(sc.seed), "--step-length", repr(self._dt), "--begin", "0",
                  "--no-step-log", "true", "--no-warnings", "true", "--duration-log.disable", "true",
                  "--xml-validation", "never", "--time-to-teleport", "-1", "--eager-insert", "true",
                  "--collision.action", "warn", "--lanechange.duration", "2",
                  "--max-depart-delay", repr(_MAX_DEPART_DELAY_S)])
        self._running = True
        self._frame = 0
        self._known = []
        self._rng = np.random.default_rng(sc.seed)
        self._bg_count = 0
        self._define_types(ls)
        for r in self.topology.routes:
            ls.route.add(r.id, list(r.edges))
        ls.simulation.subscribe([ls.constants.VAR_DEPARTED_VEHICLES_IDS])
        self._prefill(ls)
        warm_steps = max(0, round(sc.traffic.warmup_s * sc.rate_hz))
        for _ in range(max(0, warm_steps - 1)):
            self._advance(ls)
        self.cav_plans = self._insert_cavs(ls, specs)
        self._advance(ls)
        for margin in (2.0, 3.0, 4.0, 6.0):  # rare: SUMO refused a spot; re-plan it more cautiously
            missing = {c for c in self._cav_ids if c not in self._known}
            if not missing:
                break
            for c in sorted(missing):
                ls.vehicle.remove(c)
            plans = self._insert_cavs(ls, specs, only=missing, margin=margin)
            self.cav_plans = tuple(p if p.id in missing else q for p, q in zip(plans, self.cav_plans, strict=True))
            self._advance(ls)
        missing = {c for c in self._cav_ids if c not in self._known}
        if missing:
            self.close()
            raise RuntimeError(f"SUMO could not insert {sorted(missing)} (no free space on their lanes)")
        return ls

    # -- CAV placement: candidates and look-ahead ------------------------------------------------

    def _meet_ref(self) -> str:
        """The CAV whose neighbours placement counts: the first ego."""
        ego = self.scenario.cavs.ego
        if isinstance(ego, tuple) and ego[0] in self._cav_ids:
            return ego[0]
        return self._cav_ids[0]

    def _arrival_times(self) -> list[float]:
        lo, hi = self.scenario.cavs.arrival_s
        n = len(self._cav_ids)
        return [lo + (hi - lo) * (i / (n - 1) if n > 1 else 0.0) for i in range(n)]

    def candidates(self) -> list[tuple[CavSpec, ...]]:
        """The candidate placements, in the order the look-ahead tries them (deterministic per seed).

        0: the canonical plan: CAV i on arm i (order_arms), its preferred movement (_CAV_MOVES),
        arrival times spread evenly over cavs.arrival_s in CAV order. Then seeded variations: arrival
        times drawn in the window, routes drawn among the arm's movements (half of the time the
        route that leaves by cav0's exit, so the two drive off together); in the second half of the
        trials a CAV may share an arm (another lane, or behind) with an earlier one.
        """
        sc = self.scenario
        arms = order_arms(self.topology.arms)
        na = len(arms)
        lo, hi = sc.cavs.arrival_s
        times = self._arrival_times()
        out = [tuple(CavSpec(vid, self._cav_route(i, arms[i % na]), i // na, times[i])
                     for i, vid in enumerate(self._cav_ids))]
        trials = sc.cavs.meet.trials
        for j in range(1, trials):
            rng = np.random.default_rng([sc.seed, 0x5A, j])
            group = j >= max(2, trials // 2)
            specs: list[CavSpec] = []
            used: dict[int, int] = {}
            for i, vid in enumerate(self._cav_ids):
                k = i % na
                if group and i > 0 and rng.random() < 0.5:
                    k = int(rng.integers(min(i, na)))  # an arm an earlier CAV took
                arm = arms[k]
                slot = used.get(k, 0)
                used[k] = slot + 1
                if i > 0 and specs and rng.random() < 0.5:
                    same_exit = [r for r in arm.routes if r.exit == specs[0].route.exit]
                    route = same_exit[0] if same_exit else arm.routes[int(rng.integers(len(arm.routes)))]
                else:
                    route = arm.routes[int(rng.integers(len(arm.routes)))]
                t = float(rng.uniform(lo, hi))
                specs.append(CavSpec(vid, route, slot, t))
            out.append(tuple(specs))
        return out

    def _look_ahead(self, specs: tuple[CavSpec, ...], max_bad: int | None = None) -> tuple[list[int], int, int]:
        """Run the scenario's duration with `specs`: per frame, the other CAVs within comm range of
        the reference CAV (0 once it has left); the frames it was present; the distinct arms the
        CAVs were inserted on. Stops early (fewer counts) once more than `max_bad` frames fell
        short of the wanted neighbours."""
        sc = self.scenario
        want = min(sc.cavs.meet.neighbours, len(self._cav_ids) - 1)
        ls = self._launch(specs)
        arms = len({p.route.approach for p in self.cav_plans})
        tc = ls.constants
        ref = self._meet_ref()
        r2 = sc.comm.range_m ** 2
        counts: list[int] = []
        present = bad = 0
        try:
            for k in range(sc.frames):
                if k:
                    self._advance(ls)
                res = ls.vehicle.getAllSubscriptionResults()
                n = 0
                if ref in res:
                    present += 1
                    centres = {}
                    for c in self._cav_ids:
                        r = res.get(c)
                        if r is not None:
                            x, y = r[tc.VAR_POSITION]
                            p = sumo_to_pose(float(x), float(y), float(r[tc.VAR_ANGLE]), float(r[tc.VAR_LENGTH]))
                            centres[c] = (p.x, p.y)
                    ex, ey = centres[ref]
                    n = sum(1 for c, (x, y) in centres.items() if c != ref and (x - ex) ** 2 + (y - ey) ** 2 <= r2)
                counts.append(n)
                bad += ref not in res or n < want
                if max_bad is not None and bad > max_bad:
                    break
        finally:
            self.close()
        return counts, present, arms

    def _choose_placement(self) -> tuple[CavSpec, ...]:
        """Simulate candidates ahead; keep the one that meets cavs.meet from the most arms (see module doc)."""
        sc = self.scenario
        if self._chosen is not None:
            return self._chosen
        meet = sc.cavs.meet
        if meet.trials == 1:  # the canonical plan, unchecked
            self.placement = None
            return self.candidates()[0]
        frames = sc.frames
        want = min(meet.neighbours, len(self._cav_ids) - 1)
        max_bad = math.floor((1.0 - meet.share) * frames + 1e-9)
        max_arms = min(len(self._cav_ids), len(self.topology.arms))
        best: tuple[tuple, int, tuple[CavSpec, ...], list[int], int, int] | None = None
        errors: list[RuntimeError] = []
        run = 0
        for j, specs in enumerate(self.candidates()):
            run += 1
            try:
                counts, present, arms = self._look_ahead(specs, max_bad)
            except RuntimeError as e:  # this candidate could not be inserted
                errors.append(e)
                continue
            good = sum(1 for c in counts if c >= want) - (len(counts) - present)
            ok = len(counts) == frames and present == frames and good >= frames - max_bad
            score = (ok, arms if ok else 0, good)
            if best is None or score > best[0]:
                best = (score, j, specs, counts, present, arms)
            if ok and arms >= max_arms:
                break
        if best is None:
            raise errors[0]
        _, j, specs, counts, present, arms = best
        if len(counts) < frames:  # nothing met the aim: score the best one over the whole run
            counts, present, arms = self._look_ahead(specs)
        hist = np.bincount(np.asarray(counts, dtype=np.int64), minlength=len(self._cav_ids)) / len(counts)
        placement = Placement(trial=j, trials_run=run, share=sum(1 for c in counts if c >= want) / len(counts),
                              neighbours=want, ref_frames=present, frames=len(counts), arms=arms,
                              histogram=tuple(round(float(h), 4) for h in hist))
        self.placement = placement
        self._chosen = specs
        return specs

    def step(self) -> WorldState:
        """Advance SUMO by one frame (1/rate_hz)."""
        if not self._running:
            raise RuntimeError("step() before reset() (or after close())")
        ls = _libsumo()
        self._advance(ls)
        self._frame += 1
        return self._state(ls)

    def close(self) -> None:
        """Stop this backend's SUMO run (if it is the running one) so another can start."""
        if not getattr(self, "_running", False):
            return
        self._running = False
        ls = _libsumo()
        if ls.simulation.isLoaded():
            ls.close()

    # -- internals -----------------------------------------------------------------------------

    def _define_types(self, ls: ModuleType) -> None:
        for tid, vclass, length, width, height, vmax, accel, decel, sigma, sdev in _VTYPES:
            ls.vehicletype.copy("DEFAULT_VEHTYPE", tid)
            ls.vehicletype.setVehicleClass(tid, vclass)
            ls.vehicletype.setLength(tid, length)
            ls.vehicletype.setWidth(tid, width)
            ls.vehicletype.setHeight(tid, height)
            ls.vehicletype.setMaxSpeed(tid, vmax)
            ls.vehicletype.setAccel(tid, accel)
            ls.vehicletype.setDecel(tid, decel)
            ls.vehicletype.setImperfection(tid, sigma)
            ls.vehicletype.setSpeedDeviation(tid, sdev)
            ls.vehicletype.setMinGap(tid, _MIN_GAP)

    def _draw_background(self) -> tuple[float, Route, str]:
        """Next background vehicle of the Poisson stream: (departure time, route, type)."""
        rate = self.scenario.traffic.background_per_hour / 3600.0
        self._bg_next_t += float(self._rng.exponential(1.0 / rate))
        arm = self.topology.arms[int(self._rng.integers(len(self.topology.arms)))]
        w = np.array([_MOVEMENT_WEIGHT[r.movement] for r in arm.routes])
        route = arm.routes[int(self._rng.choice(len(arm.routes), p=w / w.sum()))]
        types, probs = zip(*_BACKGROUND_MIX, strict=True)
        vtype = types[int(self._rng.choice(len(types), p=np.asarray(probs)))]
        return self._bg_next_t, route, vtype

    def _prefill(self, ls: ModuleType) -> None:
        """Populate the arms as if the stream had run before t=0 (free-flow extrapolation)."""
        if self.scenario.traffic.background_per_hour <= 0:
            self._bg_horizon = math.inf
            return
        lead_s = max(self._net.getEdge(a.routes[0].edges[0]).getLength() for a in self.topology.arms) / 12.0
        self._bg_next_t = -lead_s
        placed: dict[str, list[float]] = {}
        while True:
            t, route, vtype = self._draw_background()
            if t >= 0.0:
                self._add_background(ls, t, route, vtype)
                break
            first = self._net.getEdge(route.edges[0])
            pos = 12.0 * -t
            if pos > first.getLength() - 25.0 or any(abs(pos - p) < 12.0 for p in placed.get(first.getID(), [])):
                continue
            placed.setdefault(first.getID(), []).append(pos)
            self._add_background(ls, 0.0, route, vtype, depart_pos=pos)
        self._bg_horizon = 0.0
        self._top_up(ls, 0.0)

    def _top_up(self, ls: ModuleType, now: float) -> None:
        """Schedule background departures up to `_BG_CHUNK_S` ahead of `now` (lazy, deterministic)."""
        while self._bg_horizon < now + _BG_CHUNK_S:
            self._bg_horizon += _BG_CHUNK_S
            while self._bg_next_t < self._bg_horizon:
                t, route, vtype = self._draw_background()
                self._add_background(ls, t, route, vtype)

    def _add_background(self, ls: ModuleType, t: float, route: Route, vtype: str,
                        depart_pos: float | None = None) -> None:
        vid = f"veh{self._bg_count}"
        self._bg_count += 1
        ls.vehicle.add(vid, route.id, typeID=vtype, depart=f"{max(t, 0.0):.2f}", departLane="best",
                       departPos="base" if depart_pos is None else f"{depart_pos:.2f}",
                       departSpeed="max")

    def _advance(self, ls: ModuleType) -> None:
        """One SUMO step; subscribe to everything that just departed."""
        tc = ls.constants
        ls.simulationStep()
        departed = ls.simulation.getSubscriptionResults()[tc.VAR_DEPARTED_VEHICLES_IDS]
        for vid in departed:
            ls.vehicle.subscribe(vid, [tc.VAR_POSITION, tc.VAR_ANGLE, tc.VAR_SPEED, tc.VAR_LENGTH,
                                       tc.VAR_WIDTH, tc.VAR_HEIGHT, tc.VAR_TYPE])
            self._known.append(vid)
        if self._bg_horizon != math.inf:
            self._top_up(ls, ls.simulation.getTime())

    def _cav_route(self, i: int, arm: Arm) -> Route:
        wanted = _CAV_MOVES[i % len(_CAV_MOVES)]
        for move in (wanted, "left", "right", "straight"):  # turning keeps a CAV near the junction
            for r in arm.routes:
                if r.movement == move:
                    return r
        return arm.routes[0]

    def _lanes_for(self, route: Route) -> list[int]:
        """Lanes of the approach edge that connect to the route's exit edge."""
        approach = self._net.getEdge(route.approach)
        exit_edge = self._net.getEdge(route.exit)
        ok = [ln.getIndex() for ln in approach.getLanes()
              if any(c.getTo() is exit_edge for c in ln.getOutgoing())]
        return ok or [0]

    def _insert_cavs(self, ls: ModuleType, specs: tuple[CavSpec, ...], only: set[str] | None = None,
                     margin: float = 1.5) -> tuple[CavPlan, ...]:
        """Add the CAVs (depart now) at free spots before their stop lines; see module doc.

        SUMO refuses an insertion when the vehicle behind could not brake in time (Krauss safe
        gap), so a spot is accepted only with that gap (times `margin`, raised on retries).
        """
        arms = order_arms(self.topology.arms)
        cav_len = next(t[2] for t in _VTYPES if t[0] == "cav")
        occupied: dict[str, list[tuple[float, float, float]]] = {}  # lane -> [(rear, front, speed)]

        def lane_occupants(lane_id: str) -> list[tuple[float, float, float]]:
            if lane_id not in occupied:
                occupied[lane_id] = []
                for v in ls.lane.getLastStepVehicleIDs(lane_id):
                    front = ls.vehicle.getLanePosition(v)
                    occupied[lane_id].append((front - ls.vehicle.getLength(v), front, ls.vehicle.getSpeed(v)))
            return occupied[lane_id]

        def fits(p: float, vmax: float, to_stop: float,
                 occ: list[tuple[float, float, float]]) -> float | None:
            """Insertion speed if a CAV with its front at p can enter safely, else None."""
            ahead = [o for o in occ if o[0] >= p]
            behind = [o for o in occ if o[1] <= p - cav_len]
            if len(ahead) + len(behind) != len(occ):
                return None  # overlaps someone
            v = min(vmax, _krauss_safe_speed(0.0, max(to_stop - 2.0, 0.0)))  # may have to stop there
            if ahead:
                rear, _, v_lead = min(ahead)
                gap = rear - p - _MIN_GAP
                if gap < 2.0 * margin:
                    return None
                v = min(v, _krauss_safe_speed(v_lead, gap))
            if behind:
                _, front, v_f = max(behind, key=lambda o: o[1])
                gap = p - cav_len - front - _MIN_GAP
                need = v_f * 1.0 + max(0.0, v_f ** 2 / (2 * _FOLLOWER_DECEL) - v ** 2 / (2 * _CAV_DECEL))
                if gap < margin * need + 1.0:
                    return None
            return v

        plans = []
        for i, spec in enumerate(specs):
            vid, slot, t_arr = spec.id, spec.slot, spec.arrival_s
            # The spec's route and lane first; if that lane is jammed, its other lanes, then the
            # same timing on the other arms.
            lanes = self._lanes_for(spec.route)
            options = [(spec.route, lanes[(slot + m) % len(lanes)]) for m in range(len(lanes))]
            k0 = next(j for j, a in enumerate(arms) if a.approach == spec.route.approach)
            for j in range(1, len(arms)):
                route = self._cav_route(i, arms[(k0 + j) % len(arms)])
                lanes = self._lanes_for(route)
                options += [(route, lanes[(slot + m) % len(lanes)]) for m in range(len(lanes))]
            chosen = None
            # Keep clear of the edge start (background vehicles enter there at full speed) unless
            # the network is too crowded for that.
            for clearance, (route, lane) in itertools.product((_ENTRY_CLEARANCE_M, 1.0), options):
                k = route.edges.index(route.approach)
                speed = min(self._net.getEdge(route.approach).getSpeed(), 50.0 / 3.6)
                # Walk back from the stop line to the edge that contains the target point.
                start, remaining = k, speed * t_arr
                while remaining > self._net.getEdge(route.edges[start]).getLength() and start > 0:
                    remaining -= self._net.getEdge(route.edges[start]).getLength()
                    start -= 1
                edge = self._net.getEdge(route.edges[start])
                lane_n = min(lane, edge.getLaneNumber() - 1)
                length = edge.getLength()
                beyond = sum(self._net.getEdge(e).getLength() for e in route.edges[start + 1:k + 1])
                lo_pos = min(cav_len + clearance, length / 2)
                target = float(np.clip(length - remaining, lo_pos, length - 1.0))
                occ = lane_occupants(f"{edge.getID()}_{lane_n}")
                for delta in [0.0, *[sg * d for d in np.arange(2.0, length, 2.0) for sg in (-1.0, 1.0)]]:
                    p = target + delta
                    v = fits(p, edge.getSpeed(), length - p + beyond, occ) if lo_pos <= p <= length - 1.0 else None
                    if v is not None:
                        chosen = (route, start, lane_n, p, v, occ, (length - p) + beyond)
                        break
                if chosen is not None:
                    break
            if chosen is None:
                raise RuntimeError(f"no free space to insert {vid}: every approach lane is jammed "
                                   f"(traffic.background_per_hour too high for this network?)")
            route, start, lane_n, pos, v_ins, occ, to_stop = chosen
            occ.append((pos - cav_len, pos, v_ins))
            edges = route.edges[start:]
            plans.append(CavPlan(vid, route, edges, lane_n, pos, to_stop, t_arr))
            if only is not None and vid not in only:
                continue
            rid = f"route_{vid}_{margin:g}"
            ls.route.add(rid, list(edges))
            ls.vehicle.add(vid, rid, typeID="cav", depart="now", departLane=str(lane_n),
                           departPos=f"{pos:.2f}", departSpeed="max")
        return tuple(plans)

    def _state(self, ls: ModuleType) -> WorldState:
        tc = ls.constants
        results = ls.vehicle.getAllSubscriptionResults()
        cav_set = set(self._cav_ids)
        order = [c for c in self._cav_ids if c in results]
        order += [v for v in self._known if v in results and v not in cav_set]
        self._known = [v for v in self._known if v in results]  # forget vehicles that left
        actors = []
        for vid in order:
            r = results[vid]
            length, width, height = float(r[tc.VAR_LENGTH]), float(r[tc.VAR_WIDTH]), float(r[tc.VAR_HEIGHT])
            x, y = r[tc.VAR_POSITION]
            actors.append(Actor(
                id=vid, kind=_KIND.get(r[tc.VAR_TYPE], "car"), cav=vid in cav_set,
                pose=sumo_to_pose(float(x), float(y), float(r[tc.VAR_ANGLE]), length),
                extent=(length, width, height), speed=float(r[tc.VAR_SPEED])))
        return WorldState(time=self._frame * self._dt, frame=self._frame, actors=tuple(actors),
                          static=self._static)
