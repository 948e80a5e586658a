"""Frames, poses and the BEV grid (DESIGN.md "Frames and units").

World frame: x east, y north, z up; yaw counter-clockwise from +x, radians.
A vehicle's body frame: x forward, y left, z up, origin at the footprint centre on the ground.

BEV grid (ego-centred, ego heading along +x, "up" in images is +x):
    row r, column c  <->  x = size/2 - (r + 0.5) * res,   y = size/2 - (c + 0.5) * res
so row 0 is the far front, column 0 the far left (+y), and an image of the grid shows the
scene as seen from above with the ego driving up the page.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Pose:
    """(x, y, z, yaw) in the world frame."""

    x: float
    y: float
    z: float
    yaw: float

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.x, self.y, self.z, self.yaw)


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Wrap to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def se2_matrix(x: float, y: float, yaw: float) -> np.ndarray:
    """3x3 homogeneous transform of a 2D pose (body -> parent)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def relative_pose(reference: Pose, other: Pose) -> tuple[float, float, float]:
    """Pose of `other` expressed in `reference`'s body frame: (dx, dy, dyaw)."""
    dx, dy = other.x - reference.x, other.y - reference.y
    c, s = math.cos(reference.yaw), math.sin(reference.yaw)
    return (c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(other.yaw - reference.yaw)))


def world_to_body(points_xy: np.ndarray, pose: Pose) -> np.ndarray:
    """(..., 2) world xy -> (..., 2) xy in the body frame of `pose`."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    d = points_xy - np.array([pose.x, pose.y])
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def body_to_world(points_xy: np.ndarray, pose: Pose) -> np.ndarray:
    """(..., 2) xy in the body frame of `pose` -> (..., 2) world xy."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    p = np.asarray(points_xy)
    return np.stack(
        [c * p[..., 0] - s * p[..., 1] + pose.x, s * p[..., 0] + c * p[..., 1] + pose.y], axis=-1
    )


@dataclass(frozen=True)
class BevGrid:
    """The ego-centred BEV raster: `cells` x `cells` over `size_m` x `size_m` metres."""

    size_m: float = 100.0
    cells: int = 256

    @property
    def res(self) -> float:
        return self.size_m / self.cells

    def cell_centres(self) -> np.ndarray:
        """(cells, cells, 2) body-frame xy of every cell centre."""
        idx = (np.arange(self.cells) + 0.5) * self.res
        coord = self.size_m / 2 - idx
        xs, ys = np.meshgrid(coord, coord, indexing="ij")  # xs varies along rows, ys along columns
        return np.stack([xs, ys], axis=-1)

    def xy_to_rc(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) body-frame xy -> (..., 2) continuous (row, col); cell k spans [k, k+1)."""
        xy = np.asarray(xy, dtype=np.float64)
        r = (self.size_m / 2 - xy[..., 0]) / self.res
        c = (self.size_m / 2 - xy[..., 1]) / self.res
        return np.stack([r, c], axis=-1)


def box_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    """(4, 2) corners of an oriented rectangle, counter-clockwise starting front-left."""
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = length / 2, width / 2
    local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.array([x, y])
