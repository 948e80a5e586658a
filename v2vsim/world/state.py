"""WorldState: what a traffic backend yields every tick, and the static map beside it.

Plain frozen data; sensors, ground truth and agents read nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from v2vsim.world.geometry import Pose, box_corners


@dataclass(frozen=True)
class Actor:
    """One vehicle. `pose` is the footprint centre on the ground; extent is (length, width, height)."""

    id: str
    kind: str  # "car", "truck", ... (SUMO vClass / highway-env class)
    cav: bool
    pose: Pose
    extent: tuple[float, float, float]
    speed: float = 0.0

    def footprint(self) -> np.ndarray:
        """(4, 2) world-frame corners of the footprint."""
        return box_corners(self.pose.x, self.pose.y, self.pose.yaw, self.extent[0], self.extent[1])


@dataclass(frozen=True)
class Building:
    """A vertical prism: footprint polygon (K, 2) in the world frame extruded to `height`."""

    id: str
    polygon: np.ndarray
    height: float


@dataclass(frozen=True)
class StaticMap:
    """What does not move.

    roads: drivable-area polygons (each (K, 2)), lane polygons and junction outlines.
    lane_markings: polylines (each (K, 2)) painted on the road; `dashed` says which are broken lines.
    """

    roads: tuple[np.ndarray, ...]
    lane_markings: tuple[np.ndarray, ...]
    dashed: tuple[bool, ...]
    buildings: tuple[Building, ...] = ()
    bounds: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # xmin, ymin, xmax, ymax

    def __post_init__(self) -> None:
        if len(self.dashed) != len(self.lane_markings):
            raise ValueError("StaticMap: one `dashed` flag per lane marking")


@dataclass(frozen=True)
class DrivenState:
    """What the simulator says about one vehicle v2vsim drives (closed loop, v2vsim/traffic/sumo_control.py): the
    route ahead that its planner may know (map knowledge, not perception) and what SUMO measured of its safety.

    path: (M, 2) world-frame polyline from its front bumper forward along its route (about 120 m).
    stop_m: distance along `path` to the stop line where it must yield (None: it has priority, or is past it).
    conflict_zone: (K, 2) outline of the junction it crosses next or is in (None: past it).
    collisions: the vehicles SUMO found it touching at this step.
    ssm: SUMO's SSM device so far (min TTC s, max DRAC m/s^2, min PET s); None where no encounter measured one.
    red_m: distance along its lane(s) to the next traffic light's stop line while it shows red or amber.
    route_m, route_done_m, finished: its route (control.route_m) and its progress along it (the driving score).
    """

    id: str
    path: np.ndarray
    speed_limit: float
    stop_m: float | None
    conflict_zone: np.ndarray | None
    in_junction: bool
    odometer_m: float
    collisions: tuple[str, ...] = ()
    ssm: tuple[float | None, float | None, float | None] = (None, None, None)
    red_m: float | None = None  # distance to the next traffic light if it shows red or amber (None: no such light)
    route_m: float | None = None  # the length of the route it must complete (control.route_m), from frame 0
    route_done_m: float = 0.0  # how much of it is behind it
    finished: bool = False  # it completed its route at this frame: it leaves the simulation at the next step


@dataclass(frozen=True)
class WorldState:
    """One tick of the world: sim time (s), frame index, actors. The static map is shared by reference."""

    time: float
    frame: int
    actors: tuple[Actor, ...]
    static: StaticMap = field(repr=False)
    driven: tuple[DrivenState, ...] = ()  # closed loop only: the vehicles v2vsim drives

    @property
    def cavs(self) -> tuple[Actor, ...]:
        return tuple(a for a in self.actors if a.cav)

    def actor(self, actor_id: str) -> Actor | None:
        for a in self.actors:
            if a.id == actor_id:
                return a
        return None

    def to_json(self) -> dict:
        """The `world.json` of `v2vsim frame` (DESIGN.md)."""
        return {
            "time": self.time,
            "actors": [
                {
                    "id": a.id,
                    "kind": a.kind,
                    "cav": a.cav,
                    "pose": list(a.pose.as_tuple()),
                    "extent": list(a.extent),
                    "speed": a.speed,
                }
                for a in self.actors
            ],
        }
