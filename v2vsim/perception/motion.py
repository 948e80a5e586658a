"""Model-free latency compensation for late fusion: move a neighbour's outputs by its objects' motion.

In late fusion every CAV ships its own decoded outputs: probability maps [3, S, S] (vehicle, road, lane) on
its own BEV grid and boxes [K, 6] (x, y, l, w, yaw, score) in its body frame, tagged with its capture pose
(x, y, z, yaw) and capture time. A message that is `age_s` seconds old when the ego fuses shows the
vehicles where they were. This module moves them to where they should be now, without any learned model:

1. Velocity (`box_velocities`): the sender's two latest messages are put in the world frame through their
   own capture poses, so the sender's own motion cancels. Each new box is matched to an old box by greedy
   nearest centre (globally shortest pairs first, one-to-one) within a gate sized from a plausible top
   speed, `max_speed_mps * dt + slack_m` (40 m/s * dt + 1 m by default). A matched box gets the world
   velocity (new centre - old centre) / dt; an unmatched box, or any box when dt <= 0 or dt > max_dt_s,
   gets zero. Speeds below `min_speed_mps` are set to zero so that detection jitter does not shake
   parked cars (and a static scene stays bitwise static).
2. Boxes (`move_boxes`): each box centre moves by v * dt, with v turned from the world frame into the
   sender's body frame (the frame the boxes are in). The yaw is left unchanged: a constant-velocity model
   has no turn rate, and a heading taken from the displacement of two noisy detections would be worse
   than the detector's own yaw.
3. Vehicle map (`move_vehicle_map`): for each box that moves, the cells of the vehicle probability inside
   its footprint (the rotated rectangle dilated by `dilate_m`) are cut (set to `background`) and pasted at
   the footprint translated by the box's motion (max with what is there). The translation is sub-cell:
   the cut patch is shifted bilinearly, so its centroid moves by exactly v * dt; a fractional shift
   softens the patch by at most one cell. A cell inside another box's (undilated) footprint is never
   carried away by a neighbour's dilation. Road and lane maps are unchanged (`compensate_outputs`).

Limits: constant velocity over the message age (no acceleration or turning; error grows as age^2); the
velocity is as good as two detections dt apart, so detector jitter sigma gives about sqrt(2) sigma / dt of
velocity noise (with dt = 0.1 s, 0.1 m of jitter is 1.4 m/s) and sender pose error between the two
captures shows up as motion of every object; a vehicle the detector missed (score below its threshold, or
boxes not decoded) is not moved, in the boxes nor in the map; greedy nearest matching can swap two close
vehicles and the gate is loose when dt is long (message loss); an object entering or leaving the sender's
grid is only partly handled (nothing is invented from outside the grid). Everything is pure numpy, without
hidden state: the caller keeps each sender's previous message.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from v2vsim.world.geometry import BevGrid, Pose, body_to_world

PoseLike = Pose | Sequence[float] | np.ndarray


@dataclass(frozen=True)
class OutputMessage:
    """One CAV's late-fusion outputs: maps [3, S, S] (vehicle, road, lane) on its BEV grid, boxes [K, 6]
    (x, y, l, w, yaw, score) in its body frame, its capture pose (x, y, z, yaw) and capture time (s)."""

    maps: np.ndarray
    boxes: np.ndarray
    pose: PoseLike
    capture_time: float


def as_pose(pose: PoseLike) -> Pose:
    """A Pose from a Pose or (x, y, z, yaw) (a message's sender pose)."""
    return pose if isinstance(pose, Pose) else Pose(*(float(v) for v in pose))


def _boxes(boxes: np.ndarray) -> np.ndarray:
    b = np.asarray(boxes)
    return b.reshape(0, 6) if b.size == 0 else b


def box_velocities(
    new_boxes: np.ndarray,
    new_pose: PoseLike,
    new_time: float,
    old_boxes: np.ndarray,
    old_pose: PoseLike,
    old_time: float,
    gate_m: float | None = None,
    max_speed_mps: float = 40.0,
    slack_m: float = 1.0,
    min_speed_mps: float = 0.5,
    max_dt_s: float = 1.0,
) -> np.ndarray:
    """World-frame velocity (vx, vy) [N, 2] of each new box, from its match among the old boxes.

    Both sets are placed in the world frame through their capture poses; pairs closer than the gate
    (gate_m, or max_speed_mps * dt + slack_m) are matched greedily, shortest first, one-to-one. Unmatched
    boxes, speeds below min_speed_mps, and every box when dt = new_time - old_time is <= 0 or > max_dt_s
    get (0, 0).
    """
    new_b, old_b = _boxes(new_boxes), _boxes(old_boxes)
    n, m = len(new_b), len(old_b)
    vel = np.zeros((n, 2), dtype=np.float64)
    dt = float(new_time) - float(old_time)
    if n == 0 or m == 0 or not (0.0 < dt <= max_dt_s):
        return vel
    gate = max_speed_mps * dt + slack_m if gate_m is None else float(gate_m)
    pn = body_to_world(new_b[:, :2].astype(np.float64), as_pose(new_pose))  # [N, 2]
    po = body_to_world(old_b[:, :2].astype(np.float64), as_pose(old_pose))  # [M, 2]
    dist = np.linalg.norm(pn[:, None, :] - po[None, :, :], axis=-1)  # [N, M]
    cand = np.flatnonzero(dist.ravel() <= gate)
    cand = cand[np.argsort(dist.ravel()[cand], kind="stable")]
    used_new = np.zeros(n, dtype=bool)
    used_old = np.zeros(m, dtype=bool)
    for flat in cand:
        i, j = divmod(int(flat), m)
        if used_new[i] or used_old[j]:
            continue
        used_new[i] = used_old[j] = True
        vel[i] = (pn[i] - po[j]) / dt
    vel[np.linalg.norm(vel, axis=1) < min_speed_mps] = 0.0
    return vel


def _body_shift(pose: PoseLike, velocities: np.ndarray, dt: float) -> np.ndarray:
    """[K, 2] displacement v * dt turned from the world frame into the body frame of `pose`."""
    yaw = as_pose(pose).yaw
    c, s = math.cos(yaw), math.sin(yaw)
    v = np.asarray(velocities, dtype=np.float64).reshape(-1, 2)
    return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], axis=-1) * float(dt)


def move_boxes(boxes: np.ndarray, pose: PoseLike, velocities: np.ndarray, dt: float) -> np.ndarray:
    """Boxes [K, 6] in the body frame of `pose` moved by world velocities [K, 2] over dt seconds.

    The centre moves by exactly v * dt (v turned into the body frame); size, yaw and score are unchanged.
    Returns a new array of the input's dtype.
    """
    b = _boxes(boxes)
    out = b.copy()
    if len(b):
        out[:, :2] = b[:, :2] + _body_shift(pose, velocities, dt).astype(b.dtype)
    return out


def _inside(rows: np.ndarray, cols: np.ndarray, grid: BevGrid, boxes: np.ndarray, margin_m: float) -> np.ndarray:
    """Whether the centres of cells (rows, cols) [K, ...] lie in box k's rectangle grown by margin_m."""
    extra = (1,) * (rows.ndim - 1)
    x = grid.size_m / 2 - (rows + 0.5) * grid.res
    y = grid.size_m / 2 - (cols + 0.5) * grid.res
    dx = x - boxes[:, 0].reshape(-1, *extra)
    dy = y - boxes[:, 1].reshape(-1, *extra)
    c = np.cos(boxes[:, 4]).reshape(-1, *extra)
    s = np.sin(boxes[:, 4]).reshape(-1, *extra)
    hl = (boxes[:, 2] / 2 + margin_m).reshape(-1, *extra)
    hw = (boxes[:, 3] / 2 + margin_m).reshape(-1, *extra)
    return (np.abs(c * dx + s * dy) <= hl) & (np.abs(-s * dx + c * dy) <= hw)


def move_vehicle_map(
    p_vehicle: np.ndarray,
    boxes: np.ndarray,
    pose: PoseLike,
    velocities: np.ndarray,
    dt: float,
    bev_size_m: float = 100.0,
    dilate_m: float = 0.5,
    background: float = 0.0,
) -> np.ndarray:
    """The vehicle probability [S, S] (sender's grid) moved with its objects over dt seconds.

    For each box with nonzero motion the cells of its footprint dilated by dilate_m (less the cells inside
    another box's undilated footprint) are set to `background` and their values pasted, shifted bilinearly by
    v * dt, with max over what is there. Boxes are in the body frame of `pose` (the grid's frame), velocities
    [K, 2] in the world frame. Returns a new array.
    """
    p = np.asarray(p_vehicle)
    out = p.copy()
    b = _boxes(boxes).astype(np.float64)
    if len(b) == 0 or dt == 0:
        return out
    size = p.shape[-1]
    grid = BevGrid(size_m=float(bev_size_m), cells=size)
    res = grid.res
    shift = _body_shift(pose, velocities, dt)  # [K, 2] metres, body frame
    moving = np.flatnonzero(np.any(shift != 0.0, axis=1) & np.all(np.isfinite(shift), axis=1))
    if len(moving) == 0:
        return out
    bg = float(background)

    # One square window of w x w cells per box, big enough for any dilated footprint (plus a spare cell).
    half = (0.5 * np.hypot(b[:, 2], b[:, 3]) + max(dilate_m, 0.0)) / res
    w = int(min(2 * math.ceil(float(half.max())) + 3, size + 2))
    rc = grid.xy_to_rc(b[:, :2])  # [K, 2] continuous row, col of every centre
    r0 = np.floor(rc[:, 0]).astype(np.int64) - w // 2
    c0 = np.floor(rc[:, 1]).astype(np.int64) - w // 2
    ar = np.arange(w)
    rows = r0[:, None, None] + ar[None, :, None]  # [K, w, 1]
    cols = c0[:, None, None] + ar[None, None, :]  # [K, 1, w]
    ingrid = (rows >= 0) & (rows < size) & (cols >= 0) & (cols < size)  # [K, w, w]

    # Owner of each cell: the box whose undilated footprint holds its centre (-1: none).
    owner = np.full((size, size), -1, dtype=np.int64)
    core = _inside(rows, cols, grid, b, 0.0) & ingrid
    k_idx = np.broadcast_to(np.arange(len(b))[:, None, None], core.shape)
    rr = np.broadcast_to(rows, core.shape)
    cc = np.broadcast_to(cols, core.shape)
    owner[rr[core], cc[core]] = k_idx[core]

    # Source patches of the moving boxes: dilated footprint, on the grid, not another box's core.
    mv = b[moving]
    rows_m, cols_m, ingrid_m = rows[moving], cols[moving], ingrid[moving]
    rr_m = np.broadcast_to(rows_m, ingrid_m.shape)
    cc_m = np.broadcast_to(cols_m, ingrid_m.shape)
    rr_c = np.clip(rr_m, 0, size - 1)
    cc_c = np.clip(cc_m, 0, size - 1)
    own = owner[rr_c, cc_c]
    src = _inside(rows_m, cols_m, grid, mv, dilate_m) & ingrid_m
    src &= (own == -1) | (own == moving[:, None, None])
    patch = np.where(src, p[rr_c, cc_c], 0).astype(np.float64)  # [Km, w, w]

    # Cut every source patch first, then paste all of them (so moving boxes do not disturb each other).
    out[rr_m[src], cc_m[src]] = bg

    # Shift in cells: rows grow towards -x, columns towards -y. Integer part moves the window, the fraction
    # is a bilinear blend of the patch with its neighbours (a zero border around it).
    d = -shift[moving] / res  # [Km, 2] (drow, dcol)
    fd = np.floor(d)
    fr = (d - fd)[:, 0, None, None]
    fc = (d - fd)[:, 1, None, None]
    pp = np.pad(patch, ((0, 0), (1, 1), (1, 1)))  # [Km, w + 2, w + 2]; pp[a + 1] is patch[a]
    moved = (
        (1 - fr) * (1 - fc) * pp[:, 1:, 1:]
        + fr * (1 - fc) * pp[:, :-1, 1:]
        + (1 - fr) * fc * pp[:, 1:, :-1]
        + fr * fc * pp[:, :-1, :-1]
    )  # [Km, w + 1, w + 1]; local (a, b) lands on global (r0 + floor(drow) + a, c0 + floor(dcol) + b)
    ar1 = np.arange(w + 1)
    dr = (r0[moving] + fd[:, 0].astype(np.int64))[:, None, None] + ar1[None, :, None]
    dc = (c0[moving] + fd[:, 1].astype(np.int64))[:, None, None] + ar1[None, None, :]
    dr, dc = np.broadcast_to(dr, moved.shape), np.broadcast_to(dc, moved.shape)
    keep = (moved > 0) & (dr >= 0) & (dr < size) & (dc >= 0) & (dc < size)
    flat = np.zeros(size * size, dtype=np.float64)
    np.maximum.at(flat, dr[keep] * size + dc[keep], moved[keep])
    pasted = flat.reshape(size, size)
    hit = pasted > 0
    out[hit] = np.maximum(out[hit], pasted[hit].astype(out.dtype))
    return out


def _unpack(msg: OutputMessage | Sequence) -> OutputMessage:
    if isinstance(msg, OutputMessage):
        return msg
    maps, boxes, pose, t = msg
    return OutputMessage(maps, boxes, pose, float(t))


def compensate_outputs(
    new: OutputMessage | Sequence,
    old: OutputMessage | Sequence | None,
    age_s: float,
    bev_size_m: float = 100.0,
    dilate_m: float = 0.5,
    background: float = 0.0,
    **velocity_kwargs: float,
) -> tuple[np.ndarray, np.ndarray]:
    """A sender's latest outputs (maps [3, S, S], boxes [K, 6]) moved forward by age_s seconds.

    new / old: the sender's two latest messages, OutputMessage or (maps, boxes, pose, capture_time).
    Velocities come from `box_velocities(new, old)` (velocity_kwargs go to it); boxes move by
    `move_boxes`, the vehicle map (channel 0) by `move_vehicle_map`; road and lane are unchanged. With
    age_s == 0, no old message, or no box that moves, the new maps and boxes are returned as they are (the
    same arrays, not copies).
    """
    m = _unpack(new)
    if age_s == 0 or old is None:
        return m.maps, m.boxes
    o = _unpack(old)
    vel = box_velocities(m.boxes, m.pose, m.capture_time, o.boxes, o.pose, o.capture_time, **velocity_kwargs)
    if not np.any(vel):
        return m.maps, m.boxes
    boxes = move_boxes(m.boxes, m.pose, vel, age_s)
    maps = np.array(m.maps, copy=True)
    maps[0] = move_vehicle_map(m.maps[0], m.boxes, m.pose, vel, age_s, bev_size_m, dilate_m, background)
    return maps, boxes
