"""What a perception method perceived, as oriented obstacles in the world frame (the planner's only input).

Three sources: a detector's boxes (ego body frame), a BEV vehicle-probability map (ego-centred grid) and the
ground truth (the `oracle`). Each becomes the same plain `Obstacle`, so the planner cannot tell them apart.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from v2vsim.world.geometry import BevGrid, Pose, body_to_world, wrap_angle


@dataclass(frozen=True)
class Obstacle:
    """An oriented footprint in the world frame; `score` is the detector's confidence (1 for the truth)."""

    x: float
    y: float
    yaw: float
    length: float
    width: float
    score: float = 1.0


class _ActorLike(Protocol):
    """Anything with a vehicle's id, pose and extent (v2vsim.world.state.Actor fits)."""

    @property
    def id(self) -> str: ...

    @property
    def pose(self) -> Pose: ...

    @property
    def extent(self) -> tuple[float, float, float]: ...


def obstacles_from_boxes(boxes: np.ndarray | None, ego_pose: Pose, min_score: float = 0.3) -> tuple[Obstacle, ...]:
    """[K, 6] body-frame boxes (x, y, length, width, yaw, score) -> world-frame obstacles with score >= min_score."""
    if boxes is None:
        return ()
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 6)
    b = b[b[:, 5] >= min_score]
    if len(b) == 0:
        return ()
    centres = body_to_world(b[:, :2], ego_pose)
    yaws = wrap_angle(b[:, 4] + ego_pose.yaw)
    return tuple(
        Obstacle(float(c[0]), float(c[1]), float(yaw), float(row[2]), float(row[3]), float(row[5]))
        for c, yaw, row in zip(centres, np.atleast_1d(yaws), b, strict=True)
    )


def label_components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected components of a 2-D bool mask: (labels, count), labels 1..count, 0 for background.

    A breadth-first flood fill from each unlabelled foreground cell in row-major order, so labels are numbered
    in order of each component's first cell (deterministic). scipy is not a dependency of the harness, and the
    foreground of a vehicle map is small, so a Python loop over foreground cells is cheap enough.
    """
    m = np.asarray(mask, dtype=bool)
    labels = np.zeros(m.shape, dtype=np.int32)
    rows, cols = m.shape
    count = 0
    for r0, c0 in zip(*np.nonzero(m), strict=True):
        if labels[r0, c0]:
            continue
        count += 1
        labels[r0, c0] = count
        queue = deque([(int(r0), int(c0))])
        while queue:
            r, c = queue.popleft()
            for dr in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < rows and 0 <= cc < cols and m[rr, cc] and not labels[rr, cc]:
                        labels[rr, cc] = count
                        queue.append((rr, cc))
    return labels, count


def _cells_at_origin(grid: BevGrid) -> list[tuple[int, int]]:
    """The cells whose closed extent holds the ego's footprint centre, body (0, 0): one cell, or the 2 x 2 cells
    meeting there when the origin falls on a cell corner (an even `cells`, the usual case)."""
    r, c = grid.xy_to_rc(np.zeros(2))
    eps = 1e-9
    rows = sorted({math.floor(r - eps), math.floor(r + eps)} & set(range(grid.cells)))
    cols = sorted({math.floor(c - eps), math.floor(c + eps)} & set(range(grid.cells)))
    return [(i, j) for i in rows for j in cols]


def _oriented_box(xy: np.ndarray, res: float) -> tuple[float, float, float, float, float]:
    """(x, y, yaw, length, width) of the cell centres `xy` (N, 2): centre = mean, yaw = principal axis (PCA),
    length / width = extent along / across that axis plus one cell (the centres are half a cell inside the edge).
    The yaw is only defined modulo pi (a blob has no front); it is returned in [-pi/2, pi/2)."""
    centre = xy.mean(axis=0)
    d = xy - centre
    if len(xy) > 1:
        _, vecs = np.linalg.eigh(d.T @ d / len(xy))
        axis = vecs[:, -1]  # eigenvector of the largest eigenvalue
    else:
        axis = np.array([1.0, 0.0])
    yaw = float(wrap_angle(math.atan2(axis[1], axis[0])))
    yaw = float(wrap_angle(2 * yaw) / 2)  # fold the pi ambiguity into [-pi/2, pi/2)
    along = d @ np.array([math.cos(yaw), math.sin(yaw)])
    across = d @ np.array([-math.sin(yaw), math.cos(yaw)])
    length = float(np.ptp(along)) + res
    width = float(np.ptp(across)) + res
    return float(centre[0]), float(centre[1]), yaw, length, width


def obstacles_from_bev(
    prob: np.ndarray, grid: BevGrid, ego_pose: Pose, threshold: float = 0.5, min_cells: int = 4
) -> tuple[Obstacle, ...]:
    """A [cells, cells] vehicle-probability map -> one world-frame obstacle per 8-connected blob of prob > threshold
    with at least `min_cells` cells; score = the blob's mean probability. The blob over the ego's own footprint
    centre is the ego itself and is left out. Yaw is ambiguous by pi (see `_oriented_box`)."""
    p = np.asarray(prob, dtype=np.float64)
    if p.shape != (grid.cells, grid.cells):
        raise ValueError(f"prob map {p.shape} does not match the grid ({grid.cells}, {grid.cells})")
    labels, count = label_components(p > threshold)
    ego_labels = {int(labels[r, c]) for r, c in _cells_at_origin(grid)} - {0}
    centres = grid.cell_centres()
    out = []
    for k in range(1, count + 1):
        if k in ego_labels:
            continue
        cells = labels == k
        n = int(cells.sum())
        if n < min_cells:
            continue
        bx, by, byaw, length, width = _oriented_box(centres[cells], grid.res)
        wx, wy = body_to_world(np.array([bx, by]), ego_pose)
        out.append(Obstacle(float(wx), float(wy), float(wrap_angle(byaw + ego_pose.yaw)), length, width,
                            float(p[cells].mean())))
    return tuple(out)


def obstacles_from_truth(actors: Iterable[_ActorLike], ego_id: str) -> tuple[Obstacle, ...]:
    """Every actor but the ego, as it truly is (the `oracle` method's perception)."""
    return tuple(
        Obstacle(a.pose.x, a.pose.y, a.pose.yaw, a.extent[0], a.extent[1]) for a in actors if a.id != ego_id
    )
