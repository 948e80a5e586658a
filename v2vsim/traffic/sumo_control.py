"""The closed loop on the SUMO side (docs/run.md "The closed loop"): the vehicles v2vsim drives, their commands,
and what SUMO measures of their safety.

- Driven vehicles ignore SUMO's own safety: speed mode 0 (no safe-speed, right-of-way or acceleration checks),
  so a vehicle whose planner missed another one can hit it. Each step's speed comes from `command`; before the
  first command arrives (the actuation delay) a vehicle keeps the speed it had when it was taken over. A command
  is an acceleration, held over the step it is applied to.
- Collisions: SUMO checks them on lanes and inside junctions (`--collision.check-junctions`), counts physical
  contact only (`--collision.mingap-factor 0`) and lets the run go on (`--collision.action warn`, already the
  backend's default).
- Safety: SUMO's SSM device on each driven vehicle (TTC, DRAC, PET with the control.ssm thresholds and range;
  its log in the run folder). SUMO treats conflict areas as orthogonal lanes and ignores lateral conflicts, and a
  crossing encounter may log nothing (DESIGN.md domain notes): the ego's trajectory-based measures stand beside it
  (v2vsim/control/measures.py).
- The planner may know its own route (map knowledge, not perception): `observe` gives each driven vehicle's path
  ahead, the stop line where it must yield (a link without priority: SUMO's state 'm' or lower case), the
  outline of the junction it crosses next, and the distance to a traffic light showing red or amber (a driven
  vehicle is told the signal, as a connected vehicle would be by SPaT, and stops for it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import ModuleType

import numpy as np
import sumolib

from v2vsim.config import ControlConfig
from v2vsim.world.state import DrivenState

PATH_AHEAD_M = 120.0  # how far along its route a driven vehicle's path reaches
ARRIVAL_MARGIN_M = 3.0  # a route to the end of the SUMO route finishes this short of it: SUMO removes a vehicle
# that reaches its route's end within a step (up to ~1.5 m at 14 m/s), before the finish could be seen
PATH_STEP_M = 2.0  # spacing of the path's points
ZONE_AHEAD_M = 150.0  # a junction farther than this along the lane is not yet "next"


def control_args(control: ControlConfig, driven: Sequence[str], ssm_file: str | None) -> list[str]:
    """SUMO options of a closed-loop run (added to the backend's own)."""
    s = control.ssm
    args = ["--collision.check-junctions", "true", "--collision.mingap-factor", "0",
            "--device.ssm.explicit", ",".join(driven), "--device.ssm.measures", "TTC DRAC PET",
            "--device.ssm.thresholds", f"{s.ttc_s!r} {s.drac_mps2!r} {s.pet_s!r}",
            "--device.ssm.range", repr(s.range_m), "--device.ssm.trajectories", "false"]
    return args + (["--device.ssm.file", ssm_file] if ssm_file else [])


def _resample(points: list[tuple[float, float]], step: float, length: float) -> np.ndarray:
    """A polyline's points every `step` metres along it, up to `length` (its own points deduplicated first)."""
    p = np.asarray(points, dtype=np.float64)
    keep = np.r_[True, np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-6]
    p = p[keep]
    if len(p) < 2:
        return p
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    at = np.arange(0.0, min(length, s[-1]) + 1e-9, step)
    if at[-1] < min(length, s[-1]) - 1e-6:
        at = np.r_[at, min(length, s[-1])]
    return np.stack([np.interp(at, s, p[:, 0]), np.interp(at, s, p[:, 1])], axis=1)


def _cut_from(shape: list[tuple[float, float]], pos: float) -> list[tuple[float, float]]:
    """The part of a lane shape from arc length `pos` on."""
    out: list[tuple[float, float]] = []
    run = 0.0
    for (x0, y0), (x1, y1) in zip(shape, shape[1:], strict=False):
        seg = math.hypot(x1 - x0, y1 - y0)
        if run + seg >= pos:
            t = 0.0 if seg == 0 else max(0.0, (pos - run) / seg)
            if not out:
                out.append((x0 + t * (x1 - x0), y0 + t * (y1 - y0)))
            out.append((x1, y1))
        run += seg
    return out or [shape[-1]]


class DrivenVehicles:
    """The vehicles of a closed-loop run that follow v2vsim's commands (the egos' own vehicles)."""

    def __init__(self, net: sumolib.net.Net, ids: Sequence[str], control: ControlConfig) -> None:
        self._net = net
        self.ids = tuple(ids)
        self.control = control
        self._taken: set[str] = set()
        self._route: dict[str, tuple[float, float]] = {}  # vehicle -> (odometer at take-over, its route's length)
        self._finished: set[str] = set()  # completed their route: removed at the next step

    def take_over(self, ls: ModuleType, present: Sequence[str]) -> None:
        """From now on SUMO's safety checks are off for these vehicles; they hold their speed until commanded."""
        for v in self.ids:
            if v in present and v not in self._taken:
                ls.vehicle.setSpeedMode(v, 0)
                ls.vehicle.setSpeed(v, ls.vehicle.getSpeed(v))
                self._taken.add(v)
                self._route[v] = (float(ls.vehicle.getDistance(v)), self._route_length(ls, v))

    def _route_length(self, ls: ModuleType, v: str) -> float:
        """The route it must complete from here: control.route_m along its SUMO route, at most to that route's end
        (less ARRIVAL_MARGIN_M)."""
        last = ls.vehicle.getRoute(v)[-1]
        to_end = float(ls.vehicle.getDrivingDistance(v, last, self._net.getEdge(last).getLength()))
        to_end = max(1.0, to_end - ARRIVAL_MARGIN_M)
        return to_end if self.control.route_m is None else min(self.control.route_m, to_end)

    def retire_finished(self, ls: ModuleType, present: Sequence[str]) -> None:
        """Before a step: the vehicles that completed their route arrive (leave the simulation), as at a route's
        end; their egos ended their part of the run on the frame that said so."""
        for v in sorted(self._finished):
            if v in present:
                ls.vehicle.unsubscribe(v)  # (a subscription outliving its vehicle fails the next step)
                ls.vehicle.remove(v, ls.constants.REMOVE_ARRIVED)
            self._taken.discard(v)

    def command(self, ls: ModuleType, accels: Mapping[str, float], present: Sequence[str], dt: float) -> None:
        """Apply each driven vehicle's commanded acceleration (m/s^2) over the next step: its speed then is its
        speed now + a dt (never below 0). An acceleration, not a speed: a plan acts `actuation_delay` frames after
        the speed it was made at, and a speed planned from a stale one would jerk the vehicle back and forth."""
        for v, a in accels.items():
            if v in self._taken and v in present:
                ls.vehicle.setSpeed(v, max(0.0, float(ls.vehicle.getSpeed(v)) + float(a) * dt))

    def release(self, ls: ModuleType, vehicle: str, present: Sequence[str]) -> None:
        """Give a vehicle back to SUMO's own driver (its ego is gone: nobody plans for it any more)."""
        if vehicle in self._taken and vehicle in present:
            ls.vehicle.setSpeedMode(vehicle, 31)
            ls.vehicle.setSpeed(vehicle, -1)
        self._taken.discard(vehicle)

    def observe(self, ls: ModuleType, present: Sequence[str]) -> tuple[DrivenState, ...]:
        """Each present driven vehicle's route ahead, collisions at the last step and SSM values so far."""
        hits: dict[str, list[str]] = {}
        for c in ls.simulation.getCollisions():
            hits.setdefault(c.collider, []).append(c.victim)
            hits.setdefault(c.victim, []).append(c.collider)
        out = []
        for v in self.ids:
            if v not in present:
                continue
            path, stop_m, zone, in_junction = self._route_ahead(ls, v)
            odometer = float(ls.vehicle.getDistance(v))
            start, length = self._route.get(v, (odometer, math.inf))
            done = min(length, max(0.0, odometer - start))
            finished = v in self._taken and done >= length
            if finished:
                self._finished.add(v)
            out.append(DrivenState(
                id=v, path=path, speed_limit=float(ls.lane.getMaxSpeed(ls.vehicle.getLaneID(v))), stop_m=stop_m,
                conflict_zone=zone, in_junction=in_junction, odometer_m=odometer,
                collisions=tuple(sorted(set(hits.get(v, ())))), ssm=self._ssm(ls, v), red_m=self._red(ls, v),
                route_m=None if math.isinf(length) else round(length, 3), route_done_m=round(done, 3),
                finished=finished))
        return tuple(out)

    @staticmethod
    def _red(ls: ModuleType, v: str) -> float | None:
        """Distance to the next traffic light's stop line while it shows red or amber (r, y, u: red-amber)."""
        for _tls, _index, dist, state in ls.vehicle.getNextTLS(v):
            return float(dist) if state in "rRyYu" and dist <= ZONE_AHEAD_M else None
        return None

    @staticmethod
    def _ssm(ls: ModuleType, v: str) -> tuple[float | None, float | None, float | None]:
        def read(name: str) -> float | None:
            text = ls.vehicle.getParameter(v, f"device.ssm.{name}")
            try:
                value = float(text)
            except ValueError:  # '' until an encounter measured one
                return None
            return value if math.isfinite(value) else None

        return read("minTTC"), read("maxDRAC"), read("minPET")

    @staticmethod
    def _beyond_junction(ls: ModuleType, v: str, lane: str) -> list[tuple[float, float]]:
        """The shapes from an internal lane to the first lane of the route's next edge (via further internal
        lanes, if any): without them a vehicle crossing a junction would see its path end at the junction's edge
        and lose the vehicle standing just past it."""
        route = ls.vehicle.getRoute(v)
        ahead = set(route[ls.vehicle.getRouteIndex(v) + 1:])
        points: list[tuple[float, float]] = []
        for _ in range(4):  # a connection has at most a couple of internal lanes
            nxt = next((lk[0] for lk in ls.lane.getLinks(lane) if ls.lane.getEdgeID(lk[0]) in ahead
                        or lk[0].startswith(":")), None)
            if nxt is None:
                break
            points += list(ls.lane.getShape(nxt))
            if not nxt.startswith(":"):
                break
            lane = nxt
        return points

    def _route_ahead(self, ls: ModuleType, v: str) -> tuple[np.ndarray, float | None, np.ndarray | None, bool]:
        lane = ls.vehicle.getLaneID(v)
        pos = float(ls.vehicle.getLanePosition(v))
        length = float(ls.lane.getLength(lane))
        in_junction = lane.startswith(":")
        points = _cut_from(list(ls.lane.getShape(lane)), pos)
        links = ls.vehicle.getNextLinks(v)
        for link in links:
            approached, internal = link[0], link[4]
            for nxt in (internal, approached):
                if nxt:
                    points += list(ls.lane.getShape(nxt))
        if in_junction and not links:  # SUMO lists no next links inside a junction: follow the lane's own ones
            points += self._beyond_junction(ls, v, lane)
        path = _resample(points, PATH_STEP_M, PATH_AHEAD_M)
        node = self._net.getEdge(ls.lane.getEdgeID(lane)).getToNode()
        ahead = length - pos
        zone = None
        stop_m = None
        if in_junction or ahead <= ZONE_AHEAD_M:
            shape = node.getShape()
            zone = np.asarray(shape, dtype=np.float64)[:, :2] if shape else None
        if not in_junction and links and not links[0][1] and ahead <= ZONE_AHEAD_M:
            stop_m = ahead  # the first link has no priority: yield at the end of this lane
        return path, stop_m, zone, in_junction
