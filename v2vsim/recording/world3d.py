"""What the recording draws in the 3D world view (world frame: x east, y north, z up).

The map (ground, drivable area, lane markings, buildings) is built once as static meshes; per
frame come the vehicles as 3D boxes, each CAV's LiDAR points in its colour, the ego's BEV
extent, the V2V links coloured by what the channel did, and the ego's camera frusta.
Each function returns rerun archetypes; `Recorder` decides where and when they are logged.
"""

from __future__ import annotations

import math

import numpy as np
import rerun as rr
import shapely
from shapely.geometry import Polygon

from v2vsim.comm.inbox import LinkEvent
from v2vsim.sensors.camera import CameraRig
from v2vsim.world.geometry import Pose, body_to_world
from v2vsim.world.state import Actor, StaticMap

GROUND_RGB = (58, 74, 48)
ROAD_RGB = (88, 88, 94)
MARKING_RGB = (225, 225, 225)
DASHED_RGB = (170, 170, 170)
BUILDING_RGB = (196, 178, 146)
OTHER_VEHICLE_RGB = (190, 190, 190)
# Tableau 10: one colour per CAV, shared by its box, its points, its link time series.
CAV_PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
               (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
OUTCOME_RGB = {"delivered": (40, 210, 90), "reused": (120, 200, 200), "in_flight": (250, 210, 40),
               "stale": (250, 140, 30), "dropped": (235, 50, 40), "out_of_range": (150, 150, 150),
               "rejected": (210, 60, 220)}
LINK_HEIGHT_M = 3.0  # links are drawn above the roofs so they do not hide in the boxes


# A mixed fleet (cavs.fleet) colours each CAV by its agent type instead: LiDAR types blues, camera types oranges.
TYPE_PALETTE = {"lidar": [(31, 119, 180), (23, 190, 207), (148, 103, 189)],
                "camera": [(255, 127, 14), (227, 119, 194), (188, 189, 34)]}


def cav_colour(cavs: list[str], cav: str, types: dict[str, str] | None = None) -> tuple[int, int, int]:
    """A CAV's colour: its own (CAV_PALETTE by its place among `cavs`), or with `types` (CAV id -> agent type
    label, e.g. "camera (sinbevt)") its type's, the same for every CAV of the type."""
    if cav not in cavs:
        return OTHER_VEHICLE_RGB
    if not types:
        return CAV_PALETTE[cavs.index(cav) % len(CAV_PALETTE)]
    label = types[cav]
    kind = "lidar" if label.startswith("LiDAR") else "camera"
    same = sorted({t for t in types.values() if t.startswith("LiDAR") == (kind == "lidar")})
    palette = TYPE_PALETTE[kind]
    return palette[same.index(label) % len(palette)]


def _triangles(area: Polygon | shapely.MultiPolygon) -> np.ndarray:
    """(T, 3, 2) triangles covering `area` exactly (constrained Delaunay: holes and concave parts stay out)."""
    tris = shapely.constrained_delaunay_triangles(area)
    return np.array([np.asarray(t.exterior.coords)[:3] for t in tris.geoms], np.float64).reshape(-1, 3, 2)


def _flat_mesh(tris: np.ndarray, z: float, rgb: tuple[int, int, int]) -> rr.Mesh3D:
    n = len(tris)
    pos = np.concatenate([tris.reshape(-1, 2), np.full((3 * n, 1), z)], axis=1)
    return rr.Mesh3D(vertex_positions=pos.astype(np.float32), triangle_indices=np.arange(3 * n).reshape(n, 3),
                     vertex_normals=np.tile([0.0, 0.0, 1.0], (3 * n, 1)).astype(np.float32), albedo_factor=rgb,
                     face_rendering=rr.components.MeshFaceRendering.DoubleSided)


def ground_mesh(static: StaticMap, margin_m: float = 30.0) -> rr.Mesh3D:
    x0, y0, x1, y1 = static.bounds
    quad = np.array([[[x0 - margin_m, y0 - margin_m], [x1 + margin_m, y0 - margin_m], [x1 + margin_m, y1 + margin_m]],
                     [[x0 - margin_m, y0 - margin_m], [x1 + margin_m, y1 + margin_m], [x0 - margin_m, y1 + margin_m]]])
    return _flat_mesh(quad, -0.05, GROUND_RGB)


def road_mesh(static: StaticMap) -> rr.Mesh3D | None:
    polys = [Polygon(r).buffer(0) for r in static.roads if len(r) >= 3]
    if not polys:
        return None
    return _flat_mesh(_triangles(shapely.unary_union(polys)), 0.0, ROAD_RGB)


def marking_strips(static: StaticMap) -> rr.LineStrips3D:
    strips = [np.concatenate([m, np.full((len(m), 1), 0.03)], axis=1) for m in static.lane_markings]
    colours = [DASHED_RGB if d else MARKING_RGB for d in static.dashed]
    return rr.LineStrips3D(strips, colors=colours, radii=0.08)


def building_mesh(static: StaticMap) -> rr.Mesh3D | None:
    """Footprints extruded to their height: a roof and one quad per wall, flat-shaded."""
    tris: list[np.ndarray] = []  # (3, 3) world triangles
    for b in static.buildings:
        poly = Polygon(b.polygon).buffer(0)
        if poly.is_empty or poly.area < 1e-6:
            continue
        for t in _triangles(poly):
            tris.append(np.concatenate([t, np.full((3, 1), b.height)], axis=1))
        ring = np.asarray(poly.exterior.coords)[:-1] if poly.geom_type == "Polygon" else b.polygon
        for a, c in zip(ring, np.roll(ring, -1, axis=0), strict=True):
            lo_a, lo_c = [*a, 0.0], [*c, 0.0]
            hi_a, hi_c = [*a, b.height], [*c, b.height]
            tris += [np.array([lo_a, lo_c, hi_c]), np.array([lo_a, hi_c, hi_a])]
    if not tris:
        return None
    t = np.array(tris, np.float64)
    normals = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-9)
    n = len(t)
    return rr.Mesh3D(vertex_positions=t.reshape(-1, 3).astype(np.float32),
                     triangle_indices=np.arange(3 * n).reshape(n, 3),
                     vertex_normals=np.repeat(normals, 3, axis=0).astype(np.float32), albedo_factor=BUILDING_RGB,
                     face_rendering=rr.components.MeshFaceRendering.DoubleSided)


def vehicle_boxes(actors: list[Actor], colours: list[tuple[int, int, int]], labels: list[str] | None = None,
                  solid: bool = False) -> rr.Boxes3D:
    """Boxes standing on the ground at each actor's pose: centre z = pose.z + h/2, yaw about +z."""
    if not actors:
        return rr.Boxes3D(centers=np.zeros((0, 3)), half_sizes=np.zeros((0, 3)))
    pose = np.array([a.pose.as_tuple() for a in actors], np.float64)
    ext = np.array([a.extent for a in actors], np.float64)
    centres = np.stack([pose[:, 0], pose[:, 1], pose[:, 2] + ext[:, 2] / 2], axis=1)
    half = pose[:, 3] / 2
    quats = np.stack([np.zeros_like(half), np.zeros_like(half), np.sin(half), np.cos(half)], axis=1)  # xyzw
    return rr.Boxes3D(centers=centres, half_sizes=ext / 2, quaternions=quats, colors=colours, labels=labels,
                      fill_mode="solid" if solid else "transparentfillmajorwireframe",
                      radii=rr.components.Radius.ui_points(1.5))


def bev_extent(ego: Pose, size_m: float) -> rr.LineStrips3D:
    h = size_m / 2
    corners = body_to_world(np.array([[h, h], [-h, h], [-h, -h], [h, -h], [h, h]]), ego)
    return rr.LineStrips3D([np.concatenate([corners, np.full((5, 1), ego.z + 0.1)], axis=1)],
                           colors=[(255, 255, 255)], radii=0.12)


def link_lines(events: list[LinkEvent], ego: Pose, poses: dict[str, Pose]) -> rr.LineStrips3D:
    """One line per sender (at its true pose) to the ego, coloured by outcome, labelled with it and with the age
    of the message the ego fused from that sender (0 ms: captured at the fused frame's instant)."""
    strips, colours, labels = [], [], []
    for e in events:
        p = poses.get(e.sender)
        if p is None:
            continue
        strips.append([[p.x, p.y, p.z + LINK_HEIGHT_M], [ego.x, ego.y, ego.z + LINK_HEIGHT_M]])
        colours.append(OUTCOME_RGB[e.outcome])
        what = e.outcome.replace("_", " ")
        ms = f" {e.latency_ms:.0f} ms" if e.latency_ms is not None else ""
        age = f", fused age {e.age_ms:.0f} ms" if e.age_ms is not None else ""
        labels.append(f"{e.sender}: {what}{ms}{age}")
    return rr.LineStrips3D(np.array(strips, np.float32).reshape(-1, 2, 3), colors=colours, labels=labels, radii=0.25)


def camera_pose(rig: CameraRig, i: int, ego: Pose) -> rr.Transform3D:
    """Camera i -> world: the body's yaw and position after the rig's camera -> body extrinsics."""
    c, s = math.cos(ego.yaw), math.sin(ego.yaw)
    body_to_world_rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    ext = rig.extrinsics[i]
    t = body_to_world_rot @ ext[:3, 3] + np.array([ego.x, ego.y, ego.z])
    return rr.Transform3D(translation=t, mat3x3=body_to_world_rot @ ext[:3, :3])


def camera_pinhole(rig: CameraRig, i: int) -> rr.Pinhole:
    return rr.Pinhole(image_from_camera=rig.intrinsics[i], resolution=[rig.width, rig.height],
                      camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=2.0)
