"""SUMO traffic backend through libsumo (in-process, no TraCI socket): launching, stepping,
background traffic and the conversion of SUMO's vehicles into WorldState.

Why libsumo and subscriptions: a socket round trip per getter per vehicle per step would cost
more than the simulation itself; one variable subscription per vehicle (made when it departs)
and a single `getAllSubscriptionResults()` per step gives every pose at once.

What the backend does, net-agnostically:
1. Analyse the network (sumolib): v2vsim/traffic/sumo_network.py (the main junction, its arms,
   the routes through it and their movements).
2. Background traffic: a Poisson stream of `background_per_hour` vehicles in total, arms drawn
   uniformly and movements 2:1:1 (straight:left:right); a mix of cars, vans, trucks and buses
   (`traffic.vehicle_mix`). The
   stream starts before t=0 so that the arms are already populated ("prefill") instead of
   empty when the warm-up begins. Drawn with numpy from the scenario seed; SUMO itself runs
   with `--seed`, so a seed fully determines a run.
3. CAVs "cav0".."cav{N-1}" and their placement by look-ahead (`cavs.meet`):
   v2vsim/traffic/sumo_placement.py says where they go and which candidate placement is kept;
   this backend launches SUMO for each candidate (`_look_ahead`), keeps the choice for later
   resets and inserts the CAVs one step before frame 0 (`placement` on the backend says which
   candidate won and how it scored, `cav_plans` where each CAV was inserted).

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
import math
import tempfile
from pathlib import Path
from types import ModuleType

import numpy as np
import sumolib

from v2vsim.config import ConfigError, Scenario
from v2vsim.traffic.base import BackendBase, cav_id
from v2vsim.traffic.penetration import connected_cavs
from v2vsim.traffic.static_map import load_sumo_map
from v2vsim.traffic.sumo_control import DrivenVehicles, control_args
from v2vsim.traffic.sumo_hidden_foe import FoePlan, insert_hidden_foe
from v2vsim.traffic.sumo_network import Route, analyse_network
from v2vsim.traffic.sumo_placement import CavPlan, CavSpec, Placement, choose_placement, insert_cavs, meet_ref
from v2vsim.traffic.sumo_standing import check_standing, insert_hidden_stop, insert_standing
from v2vsim.world.geometry import Pose, wrap_angle
from v2vsim.world.state import Actor, StaticMap, WorldState

# Vehicle types: (id, vClass, length m, width m, height m, max speed m/s, accel m/s^2, decel m/s^2,
# driver imperfection sigma, speed-factor deviation).
# Vans and trucks are tall enough to hide cars behind them (occlusion by traffic, not only buildings).
_VTYPES: tuple[tuple[str, str, float, float, float, float, float, float, float, float], ...] = (
    ("car", "passenger", 4.5, 1.9, 1.5, 50.0, 2.6, 4.5, 0.5, 0.1),
    ("van", "delivery", 5.4, 2.0, 2.4, 40.0, 2.0, 4.0, 0.5, 0.1),
    ("truck", "truck", 8.5, 2.5, 3.4, 30.0, 1.3, 4.0, 0.5, 0.05),
    ("bus", "bus", 12.0, 2.55, 3.2, 25.0, 1.2, 4.0, 0.5, 0.05),
    # CAVs: car-sized, no driver imperfection or speed spread so their timing follows the plan.
    ("cav", "passenger", 4.5, 1.9, 1.5, 50.0, 2.6, 4.5, 0.0, 0.0),
)
_KIND = {"car": "car", "van": "van", "truck": "truck", "bus": "bus", "cav": "car"}
_MOVEMENT_WEIGHT = {"straight": 2.0, "left": 1.0, "right": 1.0}
_MIN_GAP = 2.5  # m, standstill gap of every vehicle type
_BG_CHUNK_S = 30.0  # background departures are generated this far ahead, lazily
_MAX_DEPART_DELAY_S = 5.0  # a background vehicle that cannot enter for this long is dropped
_CAV_LENGTH = next(t[2] for t in _VTYPES if t[0] == "cav")  # m, for the CAV placement


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


# ---- the backend -----------------------------------------------------------------------------


class SumoBackend(BackendBase):
    """TrafficBackend over libsumo. One running simulation per process (a libsumo limit)."""

    def __init__(self, scenario: Scenario, ssm_file: str | None = None) -> None:
        if scenario.traffic.net is None:
            raise ValueError(f"{scenario.source}: traffic.net is required for the sumo backend")
        self.scenario = scenario
        self._dt = 1.0 / scenario.rate_hz
        self._net = sumolib.net.readNet(scenario.traffic.net, withInternal=True)
        self.topology = analyse_network(self._net)
        check_standing(self._net, scenario)
        if not scenario.traffic.vehicle_mix.shares():
            raise ConfigError(f"{scenario.source}: traffic.vehicle_mix: every share is 0; allowed: shares >= 0, "
                              "at least one above 0")
        self._static = load_sumo_map(scenario.traffic.net, scenario.traffic.buildings,
                                     scenario.traffic.building_height_m, scenario.seed)
        self._running = False
        self._frame = 0
        self._known: list[str] = []  # subscribed vehicle ids in departure order
        self._cav_ids: tuple[str, ...] = tuple(cav_id(i) for i in range(scenario.cavs.count))
        self._placed = frozenset(self._cav_ids)
        self._connected = frozenset(connected_cavs(scenario))
        self._rng = np.random.default_rng(scenario.seed)
        self._bg_next_t = 0.0
        self._bg_horizon = 0.0
        self._bg_count = 0
        self.cav_plans: tuple[CavPlan, ...] = ()
        self.placement: Placement | None = None
        self.hidden_foe: FoePlan | None = None  # traffic.hidden_foe: where foe0 went (sumo_hidden_foe)
        self.hidden_stop: str | None = None  # traffic.hidden_stop: stopped0, when it found a spot (sumo_standing)
        self._chosen: tuple[CavSpec, ...] | None = None  # the look-ahead's choice; a later reset() reuses it
        # closed loop (control section): the egos' vehicles follow commands; SSM log to ssm_file, or (none given)
        # to a temporary folder removed at close: SUMO's default, ssm_<vehicle>.xml, lands in the working directory
        self._ssm_file = ssm_file
        self._ssm_scratch: tempfile.TemporaryDirectory[str] | None = None
        self._driven = (None if scenario.control is None else
                        DrivenVehicles(self._net, tuple(scenario.cavs.egos_among(self._cav_ids)), scenario.control))

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
        ls = self._launch(specs, final=True)
        if self._driven is not None:
            self._driven.take_over(ls, self._known)
        return self._state(ls)

    def missing_actors(self) -> tuple[str, ...]:
        """The scenario's critical actors this run goes without (no free spot for them at insertion): each one a
        sentence for the run's log, since an episode without its critical actor is not the one the grid asked for."""
        sc = self.scenario
        out = []
        if sc.traffic.hidden_foe is not None and self.hidden_foe is None:
            out.append("traffic.hidden_foe: no lane of the foe's arm had room for foe0; this run goes without it")
        if sc.traffic.hidden_stop is not None and self.hidden_stop is None:
            out.append("traffic.hidden_stop: the ego's exit lane had no free spot for stopped0; this run goes "
                       "without it")
        return tuple(out)

    def _launch(self, specs: tuple[CavSpec, ...], final: bool = False) -> ModuleType:
        """Start SUMO, warm up, insert the CAVs of `specs` and take the step that makes frame 0. `final`: the
        run itself, not a placement look-ahead (only it gets the closed loop's collision and SSM options)."""
        ls = _libsumo()
        if ls.simulation.isLoaded():
            raise RuntimeError(_ONE_SIM)
        sc = self.scenario
        ls.start(["sumo", "--net-file", sc.traffic.net,
                  "--seed", str(sc.seed), "--step-length", repr(self._dt), "--begin", "0",
                  "--no-step-log", "true", "--no-warnings", "true", "--duration-log.disable", "true",
                  "--xml-validation", "never", "--time-to-teleport", "-1", "--eager-insert", "true",
                  "--collision.action", "warn", "--lanechange.duration", "2",
                  "--max-depart-delay", repr(_MAX_DEPART_DELAY_S),
                  *(control_args(sc.control, self._driven.ids, self._ssm_path())
                    if final and sc.control is not None and self._driven is not None else [])])
        self._running = True
        self._frame = 0
        self._known = []
        self._rng = np.random.default_rng(sc.seed)
        self._bg_count = 0
        self._define_types(ls)
        for r in self.topology.routes:
            ls.route.add(r.id, list(r.edges))
        ls.simulation.subscribe([ls.constants.VAR_DEPARTED_VEHICLES_IDS])
        insert_standing(ls, self._net, sc)  # before the background, which fills in around them
        self._prefill(ls)
        warm_steps = max(0, round(sc.traffic.warmup_s * sc.rate_hz))
        for _ in range(max(0, warm_steps - 1)):
            self._advance(ls)
        self.cav_plans = insert_cavs(ls, self._net, self.topology, specs, _CAV_LENGTH, _MIN_GAP)
        self.hidden_foe = insert_hidden_foe(ls, self._net, self.topology, sc, self.cav_plans, self._static.buildings)
        self.hidden_stop = insert_hidden_stop(ls, self._net, sc, self.cav_plans, self._dt)
        self._advance(ls)
        for margin in (2.0, 3.0, 4.0, 6.0):  # rare: SUMO refused a spot; re-plan it more cautiously
            missing = {c for c in self._cav_ids if c not in self._known}
            if not missing:
                break
            for c in sorted(missing):
                ls.vehicle.remove(c)
            plans = insert_cavs(ls, self._net, self.topology, specs, _CAV_LENGTH, _MIN_GAP, only=missing, margin=margin)
            self.cav_plans = tuple(p if p.id in missing else q for p, q in zip(plans, self.cav_plans, strict=True))
            self._advance(ls)
        missing = {c for c in self._cav_ids if c not in self._known}
        if missing:
            self.close()
            raise RuntimeError(f"SUMO could not insert {sorted(missing)} (no free space on their lanes)")
        return ls

    # -- CAV placement: the look-ahead runs (what to try and what to keep: sumo_placement) -----

    def _look_ahead(self, specs: tuple[CavSpec, ...], max_bad: int | None = None) -> tuple[list[int], int, int]:
        """Run the scenario's duration (or cavs.meet.horizon_s) with `specs`: per frame, the other CAVs within
        comm range of the reference CAV (0 once it has left); the frames it was present; the distinct arms the
        CAVs were inserted on. Stops early (fewer counts) once more than `max_bad` frames fell
        short of the wanted neighbours."""
        sc = self.scenario
        want = min(sc.cavs.meet.neighbours, len(self._cav_ids) - 1)
        ls = self._launch(specs)
        arms = len({p.route.approach for p in self.cav_plans})
        tc = ls.constants
        ref = meet_ref(sc, self._cav_ids)
        r2 = sc.comm.range_m ** 2
        counts: list[int] = []
        present = bad = 0
        try:
            for k in range(sc.cavs.meet.frames(sc.frames, sc.rate_hz)):
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
        """The look-ahead's choice of placement (see sumo_placement); kept for later resets."""
        if self._chosen is not None:
            return self._chosen
        specs, self.placement = choose_placement(self.scenario, self.topology, self._cav_ids, self._look_ahead)
        if self.placement is not None:  # the search ran (not the canonical plan unchecked)
            self._chosen = specs
        return specs

    def step(self) -> WorldState:
        """Advance SUMO by one frame (1/rate_hz)."""
        if not self._running:
            raise RuntimeError("step() before reset() (or after close())")
        ls = _libsumo()
        if self._driven is not None:
            self._driven.retire_finished(ls, self._known)
        self._advance(ls)
        self._frame += 1
        return self._state(ls)

    def command(self, accels: dict[str, float]) -> None:
        """Closed loop: the driven vehicles' accelerations (m/s^2) over the next step()."""
        if self._driven is not None and self._running:
            self._driven.command(_libsumo(), accels, self._known, self._dt)

    def release(self, vehicle: str) -> None:
        """Closed loop: give a driven vehicle back to SUMO's driver (its ego is gone)."""
        if self._driven is not None and self._running:
            self._driven.release(_libsumo(), vehicle, self._known)

    def close(self) -> None:
        """Stop this backend's SUMO run (if it is the running one) so another can start."""
        if not getattr(self, "_running", False):
            return
        self._running = False
        ls = _libsumo()
        if ls.simulation.isLoaded():
            ls.close()
        if self._ssm_scratch is not None:  # SUMO has written the log it was given as it closed: nobody reads it
            self._ssm_scratch.cleanup()
            self._ssm_scratch = None

    def _ssm_path(self) -> str:
        """Where SUMO writes the closed loop's SSM log: ssm_file, or a file in a scratch folder of this run."""
        if self._ssm_file is not None:
            return self._ssm_file
        if self._ssm_scratch is None:
            self._ssm_scratch = tempfile.TemporaryDirectory(prefix="v2vsim-ssm-")
        return str(Path(self._ssm_scratch.name) / "ssm.xml")

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
        types, probs = zip(*self.scenario.traffic.vehicle_mix.shares(), strict=True)
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

    def _state(self, ls: ModuleType) -> WorldState:
        tc = ls.constants
        results = ls.vehicle.getAllSubscriptionResults()
        cav_set = self._connected  # a placed vehicle cavs.penetration left unconnected is an ordinary vehicle
        order = [c for c in self._cav_ids if c in results]
        order += [v for v in self._known if v in results and v not in self._placed]
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
        driven = () if self._driven is None else self._driven.observe(ls, [a.id for a in actors])
        return WorldState(time=self._frame * self._dt, frame=self._frame, actors=tuple(actors),
                          static=self._static, driven=driven)
