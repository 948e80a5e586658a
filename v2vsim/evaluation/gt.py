"""BEV ground truth on the ego grid (geometry.BevGrid: row 0 = front +x, column 0 = left +y).

Masks, all (cells, cells) bool, rasterised by cell-centre inclusion:
  * "dynamic": footprints of every vehicle, the ego included (as OPV2V's BEV maps do: the ego
    is a vehicle on the road and the decoder is expected to paint it);
  * "visible": footprints of the vehicles in `visible_ids` (the OPV2V camera-track target);
  * "road": drivable area; "lane": lane markings ~2 cells wide, dashed where dashed.
Road and lane are sampled from the map's ground raster (`MapAssets`, built once per map),
so a frame costs a gather, not a redraw.

Visibility follows OPV2V: a vehicle is visible when any CAV's LiDAR puts at least
`min_points` points on it or any CAV's cameras show at least `min_pixels` pixels of it. The
sensing CAVs themselves count as visible (each knows where it is).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping

import numpy as np

from v2vsim.config import BevConfig
from v2vsim.sensors.camera import CameraFrame
from v2vsim.sensors.lidar import LidarSweep
from v2vsim.sensors.scene import GROUND_GT_LANE, GROUND_ROAD, GroundRaster, MapAssets, actor_index, build_map_assets
from v2vsim.world.geometry import BevGrid, Pose
from v2vsim.world.state import WorldState


def _ego_boxes(world: WorldState, ego_id: str, ids: Iterable[str] | None = None
               ) -> tuple[np.ndarray, tuple[str, ...]]:
    """(K, 5) x, y, l, w, yaw of actors in the ego body frame (all actors when ids is None)."""
    ego = world.actors[actor_index(world, ego_id)].pose
    wanted = None if ids is None else set(ids)
    sel = [a for a in world.actors if wanted is None or a.id in wanted]
    if not sel:
        return np.zeros((0, 5)), ()
    p = np.array([(a.pose.x, a.pose.y, a.pose.yaw, a.extent[0], a.extent[1]) for a in sel])
    c, s = math.cos(ego.yaw), math.sin(ego.yaw)
    dx, dy = p[:, 0] - ego.x, p[:, 1] - ego.y
    yaw = (p[:, 2] - ego.yaw + math.pi) % (2 * math.pi) - math.pi
    boxes = np.stack([c * dx + s * dy, -s * dx + c * dy, p[:, 3], p[:, 4], yaw], axis=-1)
    return boxes, tuple(a.id for a in sel)


def rasterise_boxes(boxes: np.ndarray, grid: BevGrid) -> np.ndarray:
    """(cells, cells) bool: cells whose centre lies inside any (x, y, l, w, yaw) box (ego frame)."""
    out = np.zeros((grid.cells, grid.cells), dtype=bool)
    res, half = grid.res, grid.size_m / 2
    for x, y, length, width, yaw in boxes:
        r = 0.5 * math.hypot(length, width)
        # Candidate rows/cols from the bounding circle; centre of cell k is half - (k + 0.5) res.
        r0 = max(0, int(math.floor((half - x - r) / res - 0.5)))
        r1 = min(grid.cells, int(math.ceil((half - x + r) / res - 0.5)) + 1)
        c0 = max(0, int(math.floor((half - y - r) / res - 0.5)))
        c1 = min(grid.cells, int(math.ceil((half - y + r) / res - 0.5)) + 1)
        if r0 >= r1 or c0 >= c1:
            continue
        cx = half - (np.arange(r0, r1) + 0.5) * res - x
        cy = half - (np.arange(c0, c1) + 0.5) * res - y
        c, s = math.cos(yaw), math.sin(yaw)
        lx = c * cx[:, None] + s * cy[None, :]
        ly = -s * cx[:, None] + c * cy[None, :]
        out[r0:r1, c0:c1] |= (np.abs(lx) <= length / 2) & (np.abs(ly) <= width / 2)
    return out


def gt_boxes(world: WorldState, ego_id: str, bev: BevConfig, include_ego: bool = False
             ) -> tuple[np.ndarray, tuple[str, ...]]:
    """GT boxes for detection scoring: (K, 5) x, y, l, w, yaw in the ego frame, and their ids.

    Vehicles whose centre lies on the BEV grid; the ego is left out by default (its own
    sensors never see it, and OPV2V's object lists omit it).
    """
    boxes, ids = _ego_boxes(world, ego_id)
    half = bev.size_m / 2
    keep = (np.abs(boxes[:, 0]) < half) & (np.abs(boxes[:, 1]) < half)
    if not include_ego:
        keep &= np.array([i != ego_id for i in ids], dtype=bool)
    return boxes[keep], tuple(i for i, k in zip(ids, keep, strict=True) if k)


def bev_ground_truth(world: WorldState, ego_id: str, bev: BevConfig, visible_ids: Collection[str],
                     assets: MapAssets | None = None,
                     more_visible: Mapping[str, Collection[str]] | None = None) -> dict[str, np.ndarray]:
    """{"dynamic", "visible", "road", "lane"} bool masks on the ego's BEV grid (see module doc).

    Pass `assets` (build_map_assets once per map); without it the map is rasterised here (slow).
    `more_visible`: further visibility masks by name, e.g. {"visible_self": ids the ego itself saw}.
    """
    grid = BevGrid(bev.size_m, bev.cells)
    if assets is None:
        assets = build_map_assets(world.static, gt_lane_width_m=2 * grid.res)
    boxes, ids = _ego_boxes(world, ego_id)
    vis = np.array([i in visible_ids for i in ids], dtype=bool)
    bits = _map_bits(assets.ground, world.actors[actor_index(world, ego_id)].pose, grid)
    out = {
        "dynamic": rasterise_boxes(boxes, grid),
        "visible": rasterise_boxes(boxes[vis], grid),
        "road": (bits & GROUND_ROAD) > 0,
        "lane": (bits & GROUND_GT_LANE) > 0,
    }
    for name, seen in (more_visible or {}).items():
        out[name] = rasterise_boxes(boxes[np.array([i in seen for i in ids], dtype=bool)], grid)
    return out


def _map_bits(ground: GroundRaster, pose: Pose, grid: BevGrid) -> np.ndarray:
    """The map raster's GROUND_* bits at the centre of each cell of `grid` around `pose` (its body frame)."""
    centres = grid.cell_centres()
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    wxy = np.stack([pose.x + c * centres[..., 0] - s * centres[..., 1],
                    pose.y + s * centres[..., 0] + c * centres[..., 1]], axis=-1)
    return ground.sample(wxy)


def map_layer(ground: GroundRaster, pose: Pose, size_m: float, cells: int, bit: int) -> np.ndarray:
    """[cells, cells] bool: the cells of a `size_m` grid around `pose` whose centre the map raster marks with `bit`
    (GROUND_ROAD, GROUND_BUILDING, ...)."""
    return (_map_bits(ground, pose, BevGrid(size_m, cells)) & bit) > 0


def visible_actor_ids(lidar_sweeps: Iterable[LidarSweep], camera_frames: Iterable[CameraFrame],
                      world: WorldState, min_points: int = 3, min_pixels: int = 10,
                      include_cavs: bool = True) -> frozenset[str]:
    """Ids of vehicles any CAV sees: >= min_points LiDAR points or >= min_pixels camera pixels
    from a single CAV's sensor (OPV2V). With include_cavs, the sensing CAVs count as seen."""
    n = len(world.actors)
    seen = np.zeros(n, dtype=bool)
    sensing: set[str] = set()
    for sw in lidar_sweeps:
        seen |= sw.hits_per_actor(n) >= min_points
        sensing.add(sw.cav_id)
    for fr in camera_frames:
        seen |= fr.pixels_per_actor(n) >= min_pixels
        sensing.add(fr.cav_id)
    ids = {a.id for a, s in zip(world.actors, seen, strict=True) if s}
    if include_cavs:
        ids |= {a.id for a in world.actors if a.id in sensing}
    return frozenset(ids)
