"""WorldState and StaticMap to bytes and back, for the simulator driver -> agents link.

The world is plain JSON (a few KB a tick); the static map is an .npz archive sent once.
Neither uses pickle, so a message from another host cannot run code here.
"""

from __future__ import annotations

import io
import json

import numpy as np

from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, Building, StaticMap, WorldState

MAX_WORLD_BYTES = 1 << 20
"""The longest world message an agent accepts: ~150 bytes an actor, so some 7,000 actors (a scenario's worlds
are a few KB). Agents refuse a longer one before copying or parsing it, and the driver refuses to publish one."""
MAX_STATIC_BYTES = 16 << 20
"""The longest static map (compressed .npz) an agent accepts: the shipped ones are under 25 KB."""


def world_to_bytes(world: WorldState) -> bytes:
    doc = world.to_json()
    doc["frame"] = world.frame
    return json.dumps(doc, separators=(",", ":")).encode()


def world_from_bytes(data: bytes, static: StaticMap) -> WorldState:
    """Raises ValueError on anything that is not a well-formed world message."""
    try:
        doc = json.loads(data)
        actors = tuple(
            Actor(
                id=str(a["id"]), kind=str(a["kind"]), cav=bool(a["cav"]),
                pose=Pose(*(float(v) for v in a["pose"])),
                extent=tuple(float(v) for v in a["extent"]),  # type: ignore[arg-type]
                speed=float(a.get("speed", 0.0)),
            )
            for a in doc["actors"]
        )
        return WorldState(time=float(doc["time"]), frame=int(doc["frame"]), actors=actors, static=static)
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
        raise ValueError(f"malformed world message: {e}") from None


def static_to_bytes(static: StaticMap) -> bytes:
    arrays: dict[str, np.ndarray] = {"bounds": np.asarray(static.bounds, dtype=np.float64),
                                     "dashed": np.asarray(static.dashed, dtype=bool)}
    for i, r in enumerate(static.roads):
        arrays[f"road_{i}"] = np.asarray(r, dtype=np.float64)
    for i, m in enumerate(static.lane_markings):
        arrays[f"mark_{i}"] = np.asarray(m, dtype=np.float64)
    for i, b in enumerate(static.buildings):
        arrays[f"bpoly_{i}"] = np.asarray(b.polygon, dtype=np.float64)
    arrays["bldg_height"] = np.asarray([b.height for b in static.buildings], dtype=np.float64)
    arrays["bldg_ids"] = np.asarray([b.id for b in static.buildings], dtype=str)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def static_from_bytes(data: bytes) -> StaticMap:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        def series(prefix: str) -> tuple[np.ndarray, ...]:
            n = sum(1 for k in z.files if k.startswith(prefix))
            return tuple(z[f"{prefix}{i}"] for i in range(n))

        heights, ids = z["bldg_height"], z["bldg_ids"]
        polys = series("bpoly_")
        buildings = tuple(Building(id=str(ids[i]), polygon=polys[i], height=float(heights[i]))
                          for i in range(len(heights)))
        return StaticMap(roads=series("road_"), lane_markings=series("mark_"),
                         dashed=tuple(bool(d) for d in z["dashed"]), buildings=buildings,
                         bounds=tuple(float(b) for b in z["bounds"]))  # type: ignore[arg-type]
