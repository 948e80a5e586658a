"""WorldState and StaticMap to bytes and back, for the simulator driver -> agents link.

The world is plain JSON (a few KB a tick); the static map is an .npz archive sent once.
Neither uses pickle, so a message from another host cannot run code here.
"""

from __future__ import annotations

import io
import json

import numpy as np

from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, Building, DrivenState, StaticMap, WorldState

MAX_WORLD_BYTES = 1 << 20
"""The longest world message an agent accepts: ~150 bytes an actor, so some 7,000 actors (a scenario's worlds
are a few KB). Agents refuse a longer one before copying or parsing it, and the driver refuses to publish one."""
MAX_STATIC_BYTES = 16 << 20
"""The longest static map (compressed .npz) an agent accepts: the shipped ones are under 25 KB."""


def _rounded(points: np.ndarray | None) -> list | None:
    return None if points is None else np.round(np.asarray(points, dtype=np.float64), 2).tolist()


def _driven_to_json(d: DrivenState) -> dict:
    return {"id": d.id, "path": _rounded(d.path), "speed_limit": d.speed_limit, "stop_m": d.stop_m,
            "conflict_zone": _rounded(d.conflict_zone), "in_junction": d.in_junction, "odometer_m": d.odometer_m,
            "collisions": list(d.collisions), "ssm": list(d.ssm), "red_m": d.red_m, "route_m": d.route_m,
            "route_done_m": d.route_done_m, "finished": d.finished}


def _driven_from_json(doc: dict) -> DrivenState:
    def points(v: object) -> np.ndarray | None:
        if v is None:
            return None
        a = np.asarray(v, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 2 or not np.isfinite(a).all():
            raise ValueError("a driven vehicle's path or conflict zone is not a list of finite (x, y) points")
        return a

    def opt(v: object) -> float | None:
        return None if v is None else float(v)  # type: ignore[arg-type]

    path = points(doc["path"])
    ssm = [opt(v) for v in doc["ssm"]]
    if path is None or len(ssm) != 3:
        raise ValueError("a driven vehicle needs a path and three SSM values")
    return DrivenState(id=str(doc["id"]), path=path, speed_limit=float(doc["speed_limit"]),
                       stop_m=opt(doc["stop_m"]), conflict_zone=points(doc["conflict_zone"]),
                       in_junction=bool(doc["in_junction"]), odometer_m=float(doc["odometer_m"]),
                       collisions=tuple(str(c) for c in doc["collisions"]), ssm=(ssm[0], ssm[1], ssm[2]),
                       red_m=opt(doc.get("red_m")), route_m=opt(doc.get("route_m")),
                       route_done_m=float(doc.get("route_done_m", 0.0)), finished=bool(doc.get("finished", False)))


def world_to_bytes(world: WorldState) -> bytes:
    doc = world.to_json()
    doc["frame"] = world.frame
    if world.driven:  # closed loop only: an open-loop world's bytes are as before
        doc["driven"] = [_driven_to_json(d) for d in world.driven]
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
        driven = tuple(_driven_from_json(d) for d in doc.get("driven", ()))
        return WorldState(time=float(doc["time"]), frame=int(doc["frame"]), actors=actors, static=static,
                          driven=driven)
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
