"""What an agent's own LiDAR rays establish about its BEV grid: per cell occupied, free or unknown (issue 67 item 1).

The evidence of Collaborative Anomaly Detection (Zhang et al., "On Data Fabrication in Collaborative Vehicular
Perception", USENIX Security 2024): a ray that reaches a return has passed through every cell before it, so those
cells hold nothing tall enough to stop it. Here, from the sweep's points alone (what a real sensor knows: no hit
labels), in the agent's body frame with the sensor `height_m` above the ground:

    a ray's height over the ground at horizontal distance s:  h(s) = height_m + z * s / d   (d: the point's distance)
    free:      a cell the ray crosses at 0 <= h(s) <= FREE_BELOW_M before its return (a vehicle there, roof at
               ~1.5 m or higher, would have stopped it), the return's own cell too when the return is the ground
    occupied:  a cell holding a return between OBSTACLE_M[0] and OBSTACLE_M[1] above the ground (a vehicle, a
               wall); occupied wins over free
    unknown:   every other cell (never crossed low enough: shadows behind obstacles, beyond range)

The grid has the encoder's layout (models/pointpillars.py voxelize): `cells` x `cells` over `extent_m`, row =
floor((half - x) / cell), col = floor((half - y) / cell), at twice the feature grid's resolution (evidence_cells:
0.78 m cells at the 64 x 64 zoo, so that a wall 1 m from where the map has it is more than a cell off). Packed into
two bit planes, it costs 2 x cells^2 / 8 bytes a frame (4,096 at 128 x 128) beside a feature message of 65,627.
"""

from __future__ import annotations

import numpy as np

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
FREE_BELOW_M = 1.4  # a ray at most this high over a cell would have hit a car there (roofs at ~1.45 m and up)
GROUND_M = 0.3  # a return at most this high is the ground
OBSTACLE_M = (0.3, 3.0)  # a return in this band above the ground is an obstacle (car to truck roof, a wall's foot)


def evidence_grid(points: np.ndarray, height_m: float, extent_m: float, cells: int) -> np.ndarray:
    """(P, >=3) body-frame points (sensor origin) -> (cells, cells) uint8 of UNKNOWN / FREE / OCCUPIED."""
    grid = np.zeros((cells, cells), dtype=np.uint8)
    if len(points) == 0:
        return grid
    cell, half = extent_m / cells, extent_m / 2
    x, y, z = (points[:, i].astype(np.float64) for i in range(3))
    d = np.hypot(x, y)
    keep = (d > 1e-3) & np.isfinite(d) & np.isfinite(z)
    x, y, z, d = x[keep], y[keep], z[keep], d[keep]
    above = z + height_m  # the return's height over the ground
    ground = above <= GROUND_M
    obstacle = (above > OBSTACLE_M[0]) & (above <= OBSTACLE_M[1])

    # free: samples every half cell along each ray, up to its return (the ground's cell included, an obstacle's not)
    n = int(np.ceil(min(d.max(), np.sqrt(2) * half) / (cell / 2))) + 1
    s = (np.arange(n) + 0.5) * (cell / 2)  # [n]
    end = np.where(ground, d, d - cell / 2)  # [P]
    frac = s[None, :] / d[:, None]  # [P, n]
    h = height_m + z[:, None] * frac
    on_ray = (s[None, :] <= end[:, None]) & (h >= 0.0) & (h <= FREE_BELOW_M)
    fx, fy = (x[:, None] * frac)[on_ray], (y[:, None] * frac)[on_ray]
    _mark(grid, fx, fy, half, cell, FREE)
    _mark(grid, x[obstacle], y[obstacle], half, cell, OCCUPIED)
    return grid


def _mark(grid: np.ndarray, x: np.ndarray, y: np.ndarray, half: float, cell: float, value: int) -> None:
    cells = grid.shape[0]
    row, col = np.floor((half - x) / cell).astype(np.int64), np.floor((half - y) / cell).astype(np.int64)
    ok = (row >= 0) & (row < cells) & (col >= 0) & (col < cells)
    grid[row[ok], col[ok]] = value


def evidence_cells(feature_cells: int) -> int:
    """The evidence grid of an encoder with `feature_cells` x `feature_cells` features: twice as fine."""
    return 2 * feature_cells


def packed_size(cells: int) -> int:
    """Bytes of a packed `cells` x `cells` grid: two bit planes."""
    return 2 * ((cells * cells + 7) // 8)


def pack_array(grid: np.ndarray) -> np.ndarray:
    """`pack` as the uint8 array a message's "evidence" extra carries."""
    return np.frombuffer(pack(grid), dtype=np.uint8)


def pack(grid: np.ndarray) -> bytes:
    """Two bit planes (free, occupied), each np.packbits of the grid row by row: 2 x cells^2 / 8 bytes."""
    return np.packbits(grid == FREE).tobytes() + np.packbits(grid == OCCUPIED).tobytes()


def unpack(data: bytes, cells: int) -> np.ndarray:
    """The grid `pack` packed; ValueError when `data` is not two planes of `cells` x `cells`."""
    plane = packed_size(cells) // 2
    if len(data) != 2 * plane:
        raise ValueError(f"evidence: {len(data)} bytes, expected {2 * plane} for a {cells} x {cells} grid")
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8)).reshape(2, plane * 8)[:, :cells * cells]
    free, occupied = (b.reshape(cells, cells).astype(bool) for b in bits)
    if (free & occupied).any():
        raise ValueError("evidence: a cell both free and occupied")
    return np.where(occupied, OCCUPIED, np.where(free, FREE, UNKNOWN)).astype(np.uint8)
