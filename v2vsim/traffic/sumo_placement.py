"""CAV placement for the SUMO backend: which candidate placements to try, how to insert the CAVs
into running traffic, and which candidate to keep after the look-ahead.

The backend (v2vsim/traffic/sumo.py) launches and steps SUMO, and runs a candidate ahead for this
module (`look_ahead`); only the topology from v2vsim/traffic/sumo_network.py is used here.

1. CAVs "cav0".."cav{N-1}": cav0 approaches from a minor-road arm if there is one (it yields,
   so it lingers at the junction), else from the arm pointing most to the west (it drives east
   into the junction); cav1 from the arm most opposite to it, then the side arms, then further
   rounds on other lanes / further back. Each CAV is inserted one step before frame 0 at a free
   spot `v * t_i` before its stop line, where t_i (its free-flow arrival time) lies in
   `cavs.arrival_s` (default 0..4 s): the CAVs start near the junction and meet from frame 0.
   A spot is accepted only if SUMO's safe-gap rule will let the CAV in (a refused one is
   re-placed more cautiously, which at worst delays frame 0 by a step or two).
2. Placement by look-ahead (`cavs.meet`). Where the CAVs end up depends on what no formula
   knows in general: the signal phase at frame 0 (a CAV at red waits for tens of seconds while
   one with green leaves at ~14 m/s), yielding, queues of background traffic, and CAVs that
   cross in opposite directions separating at ~28 m/s. So `reset()` simulates candidate
   placements ahead over the scenario's duration or `cavs.meet.horizon_s` (same seed, same warm-up: libsumo runs a
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
   from min(N, arms) arms. Only the topology analysis (sumo_network) is used, so it works on any net;
   the whole procedure is deterministic per seed, and a backend keeps its choice for later resets
   (`placement` on the backend says which candidate won and how it scored). With
   `cavs.meet.trials: 1` the canonical plan is used unchecked.
   Exit edges are the long arms, so a CAV stays in the simulation for a while after crossing.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import numpy as np
import sumolib

from v2vsim.config import ConfigError, Scenario
from v2vsim.traffic.sumo_network import Arm, Route, Topology, order_arms

# Movement wished for the i-th CAV (falls back to whatever its arm offers): turning CAVs stay
# near the junction longer and cross the paths of the others.
_CAV_MOVES = ("straight", "left", "left", "right", "right", "left")
_CAV_DECEL = 4.5  # m/s^2, the CAV type's comfortable deceleration
_FOLLOWER_DECEL = 4.0  # m/s^2, the smallest deceleration among the background types
_ENTRY_CLEARANCE_M = 40.0  # CAVs are not inserted this close to the start of an edge


def _krauss_safe_speed(v_lead: float, gap: float, decel: float = _CAV_DECEL, tau: float = 1.0) -> float:
    """Largest speed from which a Krauss driver can still stop behind a leader `gap` metres ahead."""
    bt = decel * tau
    return max(0.0, -bt + math.sqrt(bt * bt + v_lead * v_lead + 2.0 * decel * gap))


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
    frames: int  # frames looked ahead (the scenario's duration, or cavs.meet.horizon_s)
    arms: int  # distinct approach arms among the CAVs
    histogram: tuple[float, ...]  # share of frames with 0, 1, 2, ... other CAVs in range


# Runs one candidate ahead: (specs, max_bad) -> (neighbour counts per frame, frames the reference CAV
# was present, distinct arms); see SumoBackend._look_ahead.
LookAhead = Callable[[tuple[CavSpec, ...], int | None], tuple[list[int], int, int]]


# ---- candidates and the choice among them ----------------------------------------------------


def meet_ref(scenario: Scenario, cav_ids: tuple[str, ...]) -> str:
    """The CAV whose neighbours placement counts: the first ego."""
    ego = scenario.cavs.ego
    if isinstance(ego, tuple) and ego[0] in cav_ids:
        return ego[0]
    return cav_ids[0]


def _arrival_times(scenario: Scenario, cav_ids: tuple[str, ...]) -> list[float]:
    lo, hi = scenario.cavs.arrival_s
    n = len(cav_ids)
    return [lo + (hi - lo) * (i / (n - 1) if n > 1 else 0.0) for i in range(n)]


def _fixed_route(scenario: Scenario, i: int, arm: Arm) -> Route | None:
    """CAV i's route when cavs.movements fixes its movement (None: not fixed). A movement its arm does not offer
    is a scenario error, said with the arm's movements."""
    moves = scenario.cavs.movements
    if i >= len(moves):
        return None
    for r in arm.routes:
        if r.movement == moves[i]:
            return r
    offered = ", ".join(sorted({r.movement for r in arm.routes}))
    raise ConfigError(f"{scenario.source}: cavs.movements[{i}]: {moves[i]!r} is not a movement of cav{i}'s arm "
                      f"{arm.approach}; allowed there: {offered}")


def _cav_route(i: int, arm: Arm) -> Route:
    wanted = _CAV_MOVES[i % len(_CAV_MOVES)]
    for move in (wanted, "left", "right", "straight"):  # turning keeps a CAV near the junction
        for r in arm.routes:
            if r.movement == move:
                return r
    return arm.routes[0]


def _lanes_for(net: sumolib.net.Net, route: Route) -> list[int]:
    """Lanes of the approach edge that connect to the route's exit edge."""
    approach = net.getEdge(route.approach)
    exit_edge = net.getEdge(route.exit)
    ok = [ln.getIndex() for ln in approach.getLanes()
          if any(c.getTo() is exit_edge for c in ln.getOutgoing())]
    return ok or [0]


def candidates(scenario: Scenario, topology: Topology, cav_ids: tuple[str, ...]) -> list[tuple[CavSpec, ...]]:
    """The candidate placements, in the order the look-ahead tries them (deterministic per seed).

    0: the canonical plan: CAV i on arm i (order_arms), its preferred movement (_CAV_MOVES, or cavs.movements),
    arrival times spread evenly over cavs.arrival_s in CAV order. Then seeded variations: arrival
    times drawn in the window, routes drawn among the arm's movements (half of the time the
    route that leaves by cav0's exit, so the two drive off together); in the second half of the
    trials a CAV may share an arm (another lane, or behind) with an earlier one.
    """
    sc = scenario
    arms = order_arms(topology.arms)
    na = len(arms)
    lo, hi = sc.cavs.arrival_s
    times = _arrival_times(sc, cav_ids)
    out = [tuple(CavSpec(vid, _fixed_route(sc, i, arms[i % na]) or _cav_route(i, arms[i % na]), i // na, times[i])
                 for i, vid in enumerate(cav_ids))]
    trials = sc.cavs.meet.trials
    for j in range(1, trials):
        rng = np.random.default_rng([sc.seed, 0x5A, j])
        group = j >= max(2, trials // 2)
        specs: list[CavSpec] = []
        used: dict[int, int] = {}
        for i, vid in enumerate(cav_ids):
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
            route = _fixed_route(sc, i, arm) or route  # drawn all the same: the generator's stream stays as it was
            t = float(rng.uniform(lo, hi))
            specs.append(CavSpec(vid, route, slot, t))
        out.append(tuple(specs))
    return out


def choose_placement(scenario: Scenario, topology: Topology, cav_ids: tuple[str, ...],
                     look_ahead: LookAhead) -> tuple[tuple[CavSpec, ...], Placement | None]:
    """Simulate candidates ahead; keep the one that meets cavs.meet from the most arms (see module doc).

    `look_ahead(specs, max_bad)` runs one candidate (the backend's `_look_ahead`). Returns the chosen
    specs and how they scored (None for the canonical plan taken unchecked).
    """
    sc = scenario
    meet = sc.cavs.meet
    if meet.trials == 1:  # the canonical plan, unchecked
        return candidates(sc, topology, cav_ids)[0], None
    frames = meet.frames(sc.frames, sc.rate_hz)
    want = min(meet.neighbours, len(cav_ids) - 1)
    max_bad = math.floor((1.0 - meet.share) * frames + 1e-9)
    max_arms = min(len(cav_ids), len(topology.arms))
    best: tuple[tuple, int, tuple[CavSpec, ...], list[int], int, int] | None = None
    errors: list[RuntimeError] = []
    run = 0
    for j, specs in enumerate(candidates(sc, topology, cav_ids)):
        run += 1
        try:
            counts, present, arms = look_ahead(specs, max_bad)
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
        counts, present, arms = look_ahead(specs, None)
    hist = np.bincount(np.asarray(counts, dtype=np.int64), minlength=len(cav_ids)) / len(counts)
    placement = Placement(trial=j, trials_run=run, share=sum(1 for c in counts if c >= want) / len(counts),
                          neighbours=want, ref_frames=present, frames=len(counts), arms=arms,
                          histogram=tuple(round(float(h), 4) for h in hist))
    return specs, placement


# ---- insertion -------------------------------------------------------------------------------


def insert_cavs(ls: ModuleType, net: sumolib.net.Net, topology: Topology, specs: tuple[CavSpec, ...],
                cav_len: float, min_gap: float, only: set[str] | None = None,
                margin: float = 1.5) -> tuple[CavPlan, ...]:
    """Add the CAVs (depart now) at free spots before their stop lines; see module doc.

    SUMO refuses an insertion when the vehicle behind could not brake in time (Krauss safe
    gap), so a spot is accepted only with that gap (times `margin`, raised on retries).
    `cav_len` and `min_gap` come from the backend's vehicle types (the CAV's length, the
    standstill gap of every type).
    """
    arms = order_arms(topology.arms)
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
            gap = rear - p - min_gap
            if gap < 2.0 * margin:
                return None
            v = min(v, _krauss_safe_speed(v_lead, gap))
        if behind:
            _, front, v_f = max(behind, key=lambda o: o[1])
            gap = p - cav_len - front - min_gap
            need = v_f * 1.0 + max(0.0, v_f ** 2 / (2 * _FOLLOWER_DECEL) - v ** 2 / (2 * _CAV_DECEL))
            if gap < margin * need + 1.0:
                return None
        return v

    plans = []
    for i, spec in enumerate(specs):
        vid, slot, t_arr = spec.id, spec.slot, spec.arrival_s
        # The spec's route and lane first; if that lane is jammed, its other lanes, then the
        # same timing on the other arms.
        lanes = _lanes_for(net, spec.route)
        options = [(spec.route, lanes[(slot + m) % len(lanes)]) for m in range(len(lanes))]
        k0 = next(j for j, a in enumerate(arms) if a.approach == spec.route.approach)
        for j in range(1, len(arms)):
            route = _cav_route(i, arms[(k0 + j) % len(arms)])
            lanes = _lanes_for(net, route)
            options += [(route, lanes[(slot + m) % len(lanes)]) for m in range(len(lanes))]
        chosen = None
        # Keep clear of the edge start (background vehicles enter there at full speed) unless
        # the network is too crowded for that.
        for clearance, (route, lane) in itertools.product((_ENTRY_CLEARANCE_M, 1.0), options):
            k = route.edges.index(route.approach)
            speed = min(net.getEdge(route.approach).getSpeed(), 50.0 / 3.6)
            # Walk back from the stop line to the edge that contains the target point.
            start, remaining = k, speed * t_arr
            while remaining > net.getEdge(route.edges[start]).getLength() and start > 0:
                remaining -= net.getEdge(route.edges[start]).getLength()
                start -= 1
            edge = net.getEdge(route.edges[start])
            lane_n = min(lane, edge.getLaneNumber() - 1)
            length = edge.getLength()
            beyond = sum(net.getEdge(e).getLength() for e in route.edges[start + 1:k + 1])
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
