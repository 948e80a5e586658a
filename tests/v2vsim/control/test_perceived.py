"""Perception outputs become world-frame obstacles: boxes are moved out of the ego's body frame and filtered by
score, a BEV probability map becomes one oriented box per blob (the ego's own blob left out), the truth is every
actor but the ego."""

from __future__ import annotations

import math

import numpy as np

from v2vsim.control.perceived import label_components, obstacles_from_bev, obstacles_from_boxes, obstacles_from_truth
from v2vsim.world.geometry import BevGrid, Pose, body_to_world, world_to_body
from v2vsim.world.state import Actor


def _axis_error(a: float, b: float) -> float:
    """Angle between two undirected axes, in [0, pi/2]."""
    return abs((a - b + math.pi / 2) % math.pi - math.pi / 2)


def _rasterise(grid: BevGrid, ego: Pose, boxes: list[tuple[float, float, float, float, float]]) -> np.ndarray:
    """A probability map: 0.9 on cells whose centre lies in one of the world-frame boxes (x, y, yaw, l, w)."""
    world = body_to_world(grid.cell_centres(), ego)
    prob = np.full((grid.cells, grid.cells), 0.05)
    for x, y, yaw, length, width in boxes:
        local = world_to_body(world, Pose(x, y, 0.0, yaw))
        inside = (np.abs(local[..., 0]) <= length / 2) & (np.abs(local[..., 1]) <= width / 2)
        prob[inside] = 0.9
    return prob


def test_boxes_move_to_the_world_frame_and_low_scores_are_dropped() -> None:
    ego = Pose(1.0, 2.0, 0.0, math.pi / 2)
    boxes = np.array([[3.0, 0.0, 4.5, 1.8, 0.0, 0.8],  # 3 m ahead of an ego facing north -> (1, 5), yaw pi/2
                      [0.0, 2.0, 4.0, 1.7, 0.5, 0.9],  # 2 m to its left -> (-1, 2), yaw pi/2 + 0.5
                      [9.0, 9.0, 4.0, 1.7, 0.0, 0.1]])  # below min_score
    obs = obstacles_from_boxes(boxes, ego, min_score=0.3)
    assert len(obs) == 2
    assert np.allclose([obs[0].x, obs[0].y, obs[0].yaw], [1.0, 5.0, math.pi / 2])
    assert (obs[0].length, obs[0].width, obs[0].score) == (4.5, 1.8, 0.8)
    assert np.allclose([obs[1].x, obs[1].y, obs[1].yaw], [-1.0, 2.0, math.pi / 2 + 0.5])
    assert obstacles_from_boxes(None, ego) == ()
    assert obstacles_from_boxes(np.zeros((0, 6)), ego) == ()


def test_bev_blobs_become_world_boxes_without_the_ego_and_small_blobs() -> None:
    grid = BevGrid(100.0, 256)
    ego = Pose(10.0, -5.0, 0.0, 0.7)
    other_xy = body_to_world(np.array([15.0, 4.0]), ego)
    other = (float(other_xy[0]), float(other_xy[1]), 0.7 + 0.5, 4.6, 1.9)
    speck_xy = body_to_world(np.array([-20.0, -10.0]), ego)
    prob = _rasterise(grid, ego, [(ego.x, ego.y, ego.yaw, 4.5, 1.8), other])
    r, c = grid.xy_to_rc(world_to_body(speck_xy, ego)).astype(int)
    prob[r, c] = prob[r, c + 1] = 0.95  # a two-cell speck: below min_cells
    obs = obstacles_from_bev(prob, grid, ego, threshold=0.5, min_cells=4)
    assert len(obs) == 1
    o = obs[0]
    assert math.hypot(o.x - other[0], o.y - other[1]) < 2 * grid.res
    assert _axis_error(o.yaw, other[2]) < math.radians(10)
    assert abs(o.length - other[3]) < 1.0 and abs(o.width - other[4]) < 1.0
    assert abs(o.score - 0.9) < 1e-9


def test_the_ego_blob_is_found_on_an_odd_grid_too() -> None:
    """With an odd cell count the body origin is a cell centre, not a corner: the ego's blob still goes."""
    grid = BevGrid(50.0, 129)
    ego = Pose(0.0, 0.0, 0.0, 0.0)
    prob = _rasterise(grid, ego, [(0.0, 0.0, 0.0, 4.5, 1.8), (0.0, 8.0, 0.0, 4.5, 1.8)])
    obs = obstacles_from_bev(prob, grid, ego)
    assert len(obs) == 1 and abs(obs[0].y - 8.0) < grid.res


def test_components_are_eight_connected_and_numbered_in_scan_order() -> None:
    mask = np.array([[1, 0, 0, 1],
                     [0, 1, 0, 1],
                     [0, 0, 0, 0],
                     [1, 1, 0, 0]], dtype=bool)
    labels, count = label_components(mask)
    assert count == 3
    assert labels[0, 0] == labels[1, 1] == 1  # diagonal neighbours join
    assert labels[0, 3] == labels[1, 3] == 2
    assert labels[3, 0] == labels[3, 1] == 3


def test_truth_is_every_actor_but_the_ego() -> None:
    actors = [Actor("ego", "car", True, Pose(0.0, 0.0, 0.0, 0.0), (4.5, 1.8, 1.5)),
              Actor("v1", "car", False, Pose(10.0, 3.0, 0.0, 0.2), (4.0, 1.7, 1.4))]
    obs = obstacles_from_truth(actors, "ego")
    assert len(obs) == 1
    o = obs[0]
    assert (o.x, o.y, o.yaw, o.length, o.width, o.score) == (10.0, 3.0, 0.2, 4.0, 1.7, 1.0)
