"""BEV ground truth: footprint areas, grid orientation, road/lane masks, visibility, GT boxes."""

from __future__ import annotations

import math

import numpy as np

from tests.v2vsim.sensors._worlds import car, rect, static_map, world
from v2vsim.config import BevConfig, CamerasConfig, LidarConfig
from v2vsim.evaluation.gt import bev_ground_truth, gt_boxes, rasterise_boxes, visible_actor_ids
from v2vsim.sensors.camera import render_cameras
from v2vsim.sensors.lidar import lidar_sweep
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.world.geometry import BevGrid
from v2vsim.world.state import Building

BEV = BevConfig()
GRID = BevGrid(BEV.size_m, BEV.cells)


def test_footprint_area_matches_length_times_width() -> None:
    """Cell-centre inclusion: area = l x w within a cell's rounding along the perimeter."""
    rng = np.random.default_rng(0)
    res = GRID.res
    for length, width in ((4.6, 1.9), (9.0, 2.5), (3.9, 1.7)):
        for yaw in (0.0, 0.3, math.pi / 4, 1.2, math.pi / 2, 2.9, -2.0):
            x, y = rng.uniform(-30, 30, 2)
            area = rasterise_boxes(np.array([[x, y, length, width, yaw]]), GRID).sum() * res * res
            tol = 0.5 * 2 * (length + width) * res  # half a cell along the whole perimeter, worst case
            assert abs(area - length * width) < tol, (length, width, yaw, area)
    # On average over sub-cell offsets the error vanishes (no bias towards growing or shrinking).
    areas = [rasterise_boxes(np.array([[*rng.uniform(-5, 5, 2), 4.6, 1.9, rng.uniform(-3, 3)]]), GRID).sum()
             for _ in range(200)]
    assert abs(np.mean(areas) * res * res - 4.6 * 1.9) < 0.2


def test_orientation_follows_bev_grid() -> None:
    """Ego heading up the image: a car ahead-left lands in the upper-left quadrant, and so does a
    road patch ahead-left, whatever the ego's world yaw."""
    for yaw in (0.0, 1.0, -2.5):
        c, s = math.cos(yaw), math.sin(yaw)

        def to_world(bx: float, by: float, c: float = c, s: float = s) -> tuple[float, float]:
            return 10.0 + c * bx - s * by, 5.0 + s * bx + c * by

        patch = np.array([to_world(*p) for p in ((10, 10), (30, 10), (30, 30), (10, 30))])
        w = world([car("ego", 10.0, 5.0, yaw, cav=True), car("c", *to_world(20.0, 15.0), yaw)],
                  static_map(roads=(patch,)))
        gt = bev_ground_truth(w, "ego", BEV, {"c"})
        assert set(gt) == {"dynamic", "visible", "road", "lane"}
        assert all(m.shape == (256, 256) and m.dtype == bool for m in gt.values())
        rows, cols = np.nonzero(gt["visible"])
        rc = GRID.xy_to_rc(np.array([20.0, 15.0]))
        assert abs(rows.mean() + 0.5 - rc[0]) < 0.6 and abs(cols.mean() + 0.5 - rc[1]) < 0.6
        assert rows.mean() < 128 and cols.mean() < 128
        road_rows, road_cols = np.nonzero(gt["road"])
        assert road_rows.max() < 128 and road_cols.max() < 128
        assert abs(gt["road"].sum() * GRID.res**2 - 400.0) < 8.0
        # dynamic holds the ego too (centre of the grid); visible only what we said.
        assert gt["dynamic"][127:129, 127:129].all() and not gt["visible"][127:129, 127:129].any()


def test_lane_mask_two_cells_wide_and_dashed() -> None:
    markings = (np.array([[-60.0, 3.0], [60.0, 3.0]]), np.array([[-60.0, -3.0], [60.0, -3.0]]))
    w = world([car("ego", 0.0, 0.0, cav=True)],
              static_map(roads=(rect(-60, -5, 60, 5),), markings=markings, dashed=(False, True)))
    gt = bev_ground_truth(w, "ego", BEV, set(), assets=build_map_assets(w.static))
    lane = gt["lane"]
    solid_col = int(GRID.xy_to_rc(np.array([0.0, 3.0]))[1])
    dashed_col = int(GRID.xy_to_rc(np.array([0.0, -3.0]))[1])
    width = lane.sum(axis=1)  # per row: solid + dashed cells
    solid = lane[:, solid_col - 3:solid_col + 4]
    assert (solid.any(axis=1)).all()  # continuous along the whole grid
    assert 1.5 <= solid.sum(axis=1).mean() <= 2.5  # ~2 cells wide
    dashed = lane[:, dashed_col - 3:dashed_col + 4].any(axis=1)
    assert 0.25 < dashed.mean() < 0.45  # 3 m painted per 9 m
    assert width.max() <= 6
    assert gt["road"][:, 128 - 12:128 + 12].all() and not gt["road"][:, :100].any()


def occlusion_world(with_building: bool):
    b = (Building("wall", rect(8.0, -8.0, 12.0, 8.0), 10.0),) if with_building else ()
    cavs = [car("ego", 0.0, 0.0, cav=True), car("other", -30.0, 30.0, cav=True)]
    return world([*cavs, car("seen", 5.0, -6.0), car("hidden", 20.0, 0.0)], static_map(b))


def test_visible_ids_exclude_the_occluded_car() -> None:
    lidar_cfg, cam_cfg = LidarConfig(noise_std_m=0.0), CamerasConfig()
    for with_building in (True, False):
        w = occlusion_world(with_building)
        scene = build_scene(w, build_map_assets(w.static, res=0.5))
        rng = np.random.default_rng(0)
        sweeps = [lidar_sweep(w, c.id, lidar_cfg, rng, scene=scene) for c in w.cavs]
        frames = [render_cameras(w, c.id, cam_cfg, scene=scene) for c in w.cavs]
        for use_lidar, use_cam in ((True, False), (False, True)):
            vis = visible_actor_ids(sweeps if use_lidar else [], frames if use_cam else [], w)
            assert {"ego", "other", "seen"} <= vis
            assert ("hidden" in vis) == (not with_building)
        gt = bev_ground_truth(w, "ego", BEV, visible_actor_ids(sweeps, frames, w), assets=scene.assets)
        hidden = rasterise_boxes(np.array([[20.0, 0.0, 4.6, 1.9, 0.0]]), GRID)
        assert (gt["dynamic"] & hidden).sum() == hidden.sum()
        assert (gt["visible"] & hidden).any() == (not with_building)


def test_gt_boxes_in_ego_frame() -> None:
    w = world([car("ego", 10.0, 5.0, math.pi / 2, cav=True), car("a", 10.0, 25.0, math.pi / 2),
               car("b", 0.0, 5.0, 0.0), car("far", 10.0, 200.0)])
    boxes, ids = gt_boxes(w, "ego", BEV)
    assert ids == ("a", "b")
    assert np.allclose(boxes[0], [20.0, 0.0, 4.6, 1.9, 0.0], atol=1e-9)
    assert np.allclose(boxes[1], [0.0, 10.0, 4.6, 1.9, -math.pi / 2], atol=1e-9)
    boxes, ids = gt_boxes(w, "ego", BEV, include_ego=True)
    assert ids[0] == "ego" and np.allclose(boxes[0], [0, 0, 4.6, 1.9, 0])
