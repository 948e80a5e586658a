"""Velocities of perceived obstacles by tracking them from frame to frame (greedy nearest-neighbour association).

Perception gives positions only; the planner needs velocities (IDM's approach rate, the time a crossing vehicle
needs to reach the junction). A track missed by perception coasts (moved on by its velocity) for at most
`max_misses` frames (default 2, 200 ms at 10 Hz) and is then dropped: long enough that one frame's detection
flicker does not make a vehicle vanish and reappear as a new, standing track (which the planner brakes hard
for), short enough that the planner does not act for long on something the method lost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2vsim.control.perceived import Obstacle


@dataclass(frozen=True)
class Track:
    """A tracked obstacle in the world frame; (vx, vy) is meaningless (0) while age == 1."""

    id: int
    x: float
    y: float
    yaw: float
    length: float
    width: float
    vx: float
    vy: float
    age: int  # frames seen in a row (1 = new: velocity unknown)
    missed: int = 0  # frames in a row it was not seen (coasting; 0 = seen this frame)


def _associate(predicted: np.ndarray, observed: np.ndarray, gate_m: float) -> list[tuple[int, int]]:
    """Greedy one-to-one (track index, obstacle index) pairs, nearest first, within gate_m.

    Pairs are taken in order of (distance, track index, obstacle index), so ties go to the lower indices and the
    result does not depend on anything but the inputs.
    """
    if len(predicted) == 0 or len(observed) == 0:
        return []
    dist = np.linalg.norm(predicted[:, None, :] - observed[None, :, :], axis=-1)
    ti, oi = np.nonzero(dist <= gate_m)
    order = np.lexsort((oi, ti, dist[ti, oi]))  # last key is the primary one
    used_t: set[int] = set()
    used_o: set[int] = set()
    pairs = []
    for k in order:
        t, o = int(ti[k]), int(oi[k])
        if t in used_t or o in used_o:
            continue
        used_t.add(t)
        used_o.add(o)
        pairs.append((t, o))
    return pairs


def track(
    previous: tuple[Track, ...],
    obstacles: tuple[Obstacle, ...],
    dt: float,
    next_id: int,
    gate_m: float = 4.0,
    smoothing: float = 0.5,
    max_misses: int = 2,
) -> tuple[tuple[Track, ...], int]:
    """One tracking step: (tracks of this frame, the next free id).

    Each previous track is predicted over dt with its velocity (constant velocity), then matched greedily to this
    frame's obstacles by centre distance within gate_m. A matched track takes the new footprint and the velocity
    v = smoothing * (new - old position) / dt + (1 - smoothing) * v_previous (exponential smoothing; a previous
    track of age 1 has no velocity yet, so the measured one is taken as is). Unmatched obstacles start tracks with
    v = 0 and age 1 (ids from next_id in obstacle order); an unmatched previous track coasts (moved by its velocity,
    `missed` + 1) while it has missed at most max_misses frames, and is dropped after. The tracks come back in the
    order of the obstacles they stand for, then the coasting ones in their previous order.
    """
    if dt <= 0:
        raise ValueError("dt must be positive")
    prev_xy = np.array([[t.x, t.y] for t in previous], dtype=np.float64).reshape(-1, 2)
    prev_v = np.array([[t.vx, t.vy] for t in previous], dtype=np.float64).reshape(-1, 2)
    obs_xy = np.array([[o.x, o.y] for o in obstacles], dtype=np.float64).reshape(-1, 2)
    match = {o: t for t, o in _associate(prev_xy + prev_v * dt, obs_xy, gate_m)}
    out = []
    for oi, ob in enumerate(obstacles):
        if oi in match:
            old = previous[match[oi]]
            mvx, mvy = (ob.x - old.x) / dt, (ob.y - old.y) / dt
            if old.age > 1:
                mvx = smoothing * mvx + (1 - smoothing) * old.vx
                mvy = smoothing * mvy + (1 - smoothing) * old.vy
            out.append(Track(old.id, ob.x, ob.y, ob.yaw, ob.length, ob.width, float(mvx), float(mvy), old.age + 1))
        else:
            out.append(Track(next_id, ob.x, ob.y, ob.yaw, ob.length, ob.width, 0.0, 0.0, 1))
            next_id += 1
    matched = set(match.values())
    for ti, old in enumerate(previous):
        if ti not in matched and old.missed < max_misses:
            out.append(Track(old.id, old.x + old.vx * dt, old.y + old.vy * dt, old.yaw, old.length, old.width,
                             old.vx, old.vy, old.age, old.missed + 1))
    return tuple(out), next_id
