"""highway-env traffic backend: the "intersection-v0" environment mapped into v2vsim's world frame.

Why: a pure-Python alternative to SUMO (no native library) with the same WorldState contract.
The env's controlled vehicles are the CAVs ("cav0".. from arms 0,1,2,3,0,...); its other
vehicles are background traffic, spawned by the env itself.

Frame mapping (documented contract of this backend): highway-env works in screen coordinates
(x right, y DOWN, heading measured from +x towards +y, i.e. clockwise on screen). v2vsim's world
is right-handed with y up (north), so every point maps as (x, y) -> (x, -y) and every heading as
yaw = -heading. The world plotted north-up therefore looks exactly like the env's rendering, and
traffic keeps driving on the right. Units are metres; the junction centre is the origin.

Other mappings:
- footprint = (LENGTH, WIDTH) of the vehicle class, height 1.5 m (highway-env is 2D);
- roads = each lane's centre line sampled every metre and buffered by half its width;
  markings = each lane's two side lines with their line types (STRIPED = dashed,
  CONTINUOUS/CONTINUOUS_LINE = solid, NONE = not painted);
- `background_per_hour` sets the env's per-step spawn probability (rate / 3600 / rate_hz);
- `warmup_s` is not applied: the env pre-populates its roads itself on reset (3 s of
  pre-simulation) and its CAVs start 35-45 m before the junction, so a warm-up would only
  drive them through it before frame 0;
- the env steps at `rate_hz` (policy frequency) with ceil(15 / rate_hz) physics substeps;
- the env never removes controlled vehicles; a CAV is dropped here once it has driven past the
  end of its exit lane, and it never comes back.

CAV driving: the env's controlled vehicles are MDP vehicles that brake for no one (its
right-of-way rule exempts them: they are the agents it expects to learn), so with a fixed
action CAVs from crossing arms collided at the junction within 5 s. After reset each CAV is
swapped, in place in the env's road and controlled-vehicle lists, for an IDM/MOBIL vehicle on
the same route: it drives like background traffic and yields under the env's rule (the
meta-actions the env still sends are ignored by IDM vehicles). highway-env's own rule is not
collision-free: over seeds 0-4 and 200 frames, 4 of 20 CAVs still crashed (vs. most before);
crashed vehicles stay in the WorldState, as in the env.

CAV placement: `cavs.arrival_s` and `cavs.meet` (the SUMO backend's "CAVs meet from frame 0"
placement) are not applied here, because this map cannot give both at once. Its arms are 100 m
in + 100 m out at 10 m/s, and a CAV is dropped 20 m before the end of its exit lane, so even a
straight route from the far end of an arm (111 m out) is ~200 m, ~20 s: the ego lasts the
200 frames of a 20 s run only if it starts within a few metres of that far end or is held at
the junction for as long as it started closer. Starting there, it is more than 70 m from every
lane of the other arms until it has driven ~40 m, and a CAV of an adjacent (opposite) arm is in
range only once both are within ~50 m (~35 m) of the centre; so CAVs from other arms timed to
reach the junction with the ego and to leave by its exit are in range for ~14 of the 20 s at
best (< 80 %), and CAVs of its own arm are ahead of it and leave the map before it. Only a
single-arm platoon could do better, which gives up the different viewpoints cooperative
perception is about. So the env's own spawn is kept (arm i % 4,
35-45 m before the junction). Measured with v2vsim/bench/placement.py over seeds 0-19: >= 2 other
CAVs within 70 m of cav0 in 62-100 % of the frames (min 0.62), and cav0 leaves before frame 200
on 7 of the 20 seeds (as early as frame 175).
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Any

import numpy as np
from shapely.geometry import LineString

from v2vsim.config import Scenario
from v2vsim.traffic.base import BackendBase, cav_id
from v2vsim.world.geometry import Pose, wrap_angle
from v2vsim.world.state import Actor, StaticMap, WorldState

ENV_ID = "intersection-v0"
VEHICLE_HEIGHT_M = 1.5
_TARGET_SPEEDS = (0.0, 4.5, 9.0)
_IDLE = 1  # DiscreteMetaAction (longitudinal only): 0 SLOWER, 1 IDLE, 2 FASTER
_SAMPLE_M = 1.0  # lane centre lines are sampled this densely for polygons and markings
_EXTRA_CAV_SPACING_M = 12.0  # CAVs beyond the fourth start this much further back on an arm


def _to_world(xy: np.ndarray) -> np.ndarray:
    """highway-env (x right, y down) -> world (x east, y north)."""
    out = np.array(xy, dtype=np.float64, copy=True)
    out[..., 1] *= -1.0
    return out


def _import_env() -> Any:
    """Import gymnasium + highway_env quietly and headless (no window, no pygame banner)."""
    os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import gymnasium
    import highway_env  # noqa: F401 - registers the environments

    return gymnasium


def _lane_geometry(lane: Any) -> tuple[np.ndarray, float]:
    """(K, 2) env-frame centre-line samples of a lane and its width."""
    n = max(2, int(math.ceil(lane.length / _SAMPLE_M)) + 1)
    s = np.linspace(0.0, lane.length, n)
    pts = np.array([lane.position(float(si), 0.0) for si in s])
    return pts, float(lane.width_at(0.0))


def highway_static_map(road: Any) -> StaticMap:
    """StaticMap of a highway-env road network, in the world frame."""
    from highway_env.road.lane import LineType

    roads: list[np.ndarray] = []
    markings: list[np.ndarray] = []
    dashed: list[bool] = []
    for lane in road.network.lanes_list():
        pts, width = _lane_geometry(lane)
        area = LineString(_to_world(pts)).buffer(width / 2.0, cap_style="flat", join_style="round")
        if area.geom_type == "MultiPolygon":
            area = max(area.geoms, key=lambda g: g.area)
        if not area.is_empty:
            roads.append(np.asarray(area.exterior.coords, dtype=np.float64)[:-1])
        n = len(pts)
        s = np.linspace(0.0, lane.length, n)
        for side, line_type in enumerate(lane.line_types):
            if line_type == LineType.NONE:
                continue
            lateral = (side - 0.5) * width
            line = np.array([lane.position(float(si), lateral) for si in s])
            markings.append(_to_world(line))
            dashed.append(line_type == LineType.STRIPED)
    allpts = np.concatenate(roads, axis=0)
    (xmin, ymin), (xmax, ymax) = allpts.min(axis=0), allpts.max(axis=0)
    return StaticMap(roads=tuple(roads), lane_markings=tuple(markings), dashed=tuple(dashed),
                     buildings=(), bounds=(float(xmin), float(ymin), float(xmax), float(ymax)))


class HighwayEnvBackend(BackendBase):
    """TrafficBackend over highway-env's intersection (see module doc for the frame mapping)."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self._n = scenario.cavs.count
        self._dt = 1.0 / scenario.rate_hz
        substeps = max(1, math.ceil(15.0 / scenario.rate_hz))
        sim_hz = round(scenario.rate_hz * substeps)
        if abs(sim_hz - scenario.rate_hz * substeps) > 1e-9:
            raise ValueError(f"{scenario.source}: rate_hz: the highway-env backend needs a rate whose "
                             f"physics rate ({substeps} x rate_hz) is a whole number of Hz")
        config = {
            "controlled_vehicles": self._n,
            "action": {"type": "MultiAgentAction",
                       "action_config": {"type": "DiscreteMetaAction", "lateral": False,
                                         "longitudinal": True, "target_speeds": list(_TARGET_SPEEDS)}},
            "policy_frequency": scenario.rate_hz,
            "simulation_frequency": sim_hz,
            "spawn_probability": float(min(1.0, scenario.traffic.background_per_hour / 3600.0 / scenario.rate_hz)),
            "destination": None,
            "duration": 1e9,  # episode length is the runner's business, not the env's
            "offscreen_rendering": True,
            "real_time_rendering": False,
        }
        gym = _import_env()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "intersection-v0 is out of date": we want this version
            self._env = gym.make(ENV_ID, config=config, disable_env_checker=True).unwrapped
        self._env.reset(seed=scenario.seed)  # builds the road (independent of the seed)
        self._static = highway_static_map(self._env.road)
        self._names: dict[int, tuple[Any, str]] = {}
        self._next_bg = 0
        self._gone: set[str] = set()
        self._on_exit: set[str] = set()
        self._frame = 0
        self._open = True

    @property
    def static(self) -> StaticMap:
        return self._static

    def reset(self) -> WorldState:
        """Reset the env with the scenario seed; return frame 0 (see module doc on warm-up)."""
        if not self._open:
            raise RuntimeError("reset() after close()")
        env = self._env
        env.reset(seed=self.scenario.seed)
        self._names = {}
        self._next_bg = 0
        self._gone = set()
        self._on_exit = set()
        self._frame = 0
        cavs = list(env.controlled_vehicles)
        for i, v in enumerate(cavs):
            self._names[id(v)] = (v, cav_id(i))
            arm = i % 4
            if i >= 4:  # the env puts CAV i and i-4 on the same spot: move the later one back
                lane = env.road.network.get_lane((f"o{arm}", f"ir{arm}", 0))
                s0, _ = lane.local_coordinates(cavs[arm].position)
                s = max(5.0, s0 - _EXTRA_CAV_SPACING_M * (i // 4))
                v.position = np.array(lane.position(s, 0.0))
                v.heading = lane.heading_at(s)
                env.road.vehicles = [o for o in env.road.vehicles if o in cavs
                                     or np.linalg.norm(o.position - v.position) > 10.0]
            # Own destinations (the env may draw the CAV's own arm): the other arms in turn.
            v.plan_route_to(f"o{(arm + 1 + i % 3) % 4}")
        self._drive_with_idm(cavs)
        return self._state()

    def _drive_with_idm(self, cavs: list[Any]) -> None:
        """Swap each controlled MDP vehicle for an IDM vehicle on its route (see module doc)."""
        from highway_env.vehicle.behavior import IDMVehicle  # imported with the env (see _import_env)

        env = self._env
        idm_cavs = []
        for v in cavs:
            idm = IDMVehicle.create_from(v)  # copies position, heading, speed, target lane and route
            env.road.vehicles[env.road.vehicles.index(v)] = idm
            self._names[id(idm)] = (idm, self._names.pop(id(v))[1])
            idm_cavs.append(idm)
        env.controlled_vehicles = idm_cavs
        for action_type, idm in zip(env.action_type.agents_action_types, idm_cavs, strict=True):
            action_type.controlled_vehicle = idm

    def step(self) -> WorldState:
        """One env step (1/rate_hz) with each CAV's meta-action."""
        if not self._open:
            raise RuntimeError("step() after close()")
        self._env.step((_IDLE,) * self._n)
        self._frame += 1
        return self._state()

    def close(self) -> None:
        if getattr(self, "_open", False):
            self._open = False
            self._env.close()

    # -- internals -----------------------------------------------------------------------------

    def _name(self, v: Any) -> str:
        entry = self._names.get(id(v))
        if entry is not None and entry[0] is v:
            return entry[1]
        name = f"hw{self._next_bg}"
        self._next_bg += 1
        self._names[id(v)] = (v, name)  # keeps v alive, so its id() cannot be reused meanwhile
        return name

    def _left(self, name: str, v: Any) -> bool:
        """Has this CAV left? The env keeps simulating controlled vehicles forever (past the end
        of their route they U-turn onto the incoming lane), so v2vsim ends them where the env
        clears its background vehicles: 4 vehicle lengths before the end of the exit lane, or as
        soon as a CAV that was on an exit lane is on any other lane."""
        start, end, _ = v.lane_index
        if start.startswith("il") and end.startswith("o"):
            self._on_exit.add(name)
            s, _ = v.lane.local_coordinates(v.position)
            return s >= v.lane.length - 4 * v.LENGTH
        return name in self._on_exit

    def _state(self) -> WorldState:
        env = self._env
        cav_actors: list[Actor] = []
        bg: list[Actor] = []
        alive = set()
        for v in env.road.vehicles:
            name = self._name(v)
            alive.add(id(v))
            is_cav = name.startswith("cav")
            if is_cav and (name in self._gone or self._left(name, v)):
                self._gone.add(name)
                continue
            x, y = _to_world(np.asarray(v.position))
            actor = Actor(id=name, kind="car", cav=is_cav,
                          pose=Pose(float(x), float(y), 0.0, float(wrap_angle(-v.heading))),
                          extent=(float(v.LENGTH), float(v.WIDTH), VEHICLE_HEIGHT_M), speed=float(v.speed))
            (cav_actors if is_cav else bg).append(actor)
        self._names = {k: e for k, e in self._names.items() if k in alive}
        cav_actors.sort(key=lambda a: int(a.id[3:]))
        bg.sort(key=lambda a: int(a.id[2:]))
        return WorldState(time=self._frame * self._dt, frame=self._frame,
                          actors=tuple(cav_actors + bg), static=self._static)
