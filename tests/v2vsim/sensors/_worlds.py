"""Hand-built worlds for sensor and ground-truth tests (no traffic backend)."""

from __future__ import annotations

import numpy as np

from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, Building, StaticMap, WorldState


def rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Counter-clockwise axis-aligned rectangle."""
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def car(actor_id: str, x: float, y: float, yaw: float = 0.0, cav: bool = False,
        extent: tuple[float, float, float] = (4.6, 1.9, 1.5)) -> Actor:
    return Actor(actor_id, "car", cav, Pose(x, y, 0.0, yaw), extent)


def static_map(buildings: tuple[Building, ...] = (), roads: tuple[np.ndarray, ...] = (),
               markings: tuple[np.ndarray, ...] = (), dashed: tuple[bool, ...] = ()) -> StaticMap:
    return StaticMap(roads, markings, dashed, buildings, (-60.0, -60.0, 60.0, 60.0))


def world(actors: list[Actor], static: StaticMap | None = None) -> WorldState:
    return WorldState(0.0, 0, tuple(actors), static or static_map())
