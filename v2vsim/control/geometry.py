"""Plane geometry the planner needs: projection onto a polyline, point-in-polygon, rays against a grown polygon.

All inputs are world-frame metres; functions are pure and vectorised over points where that is cheap.
"""

from __future__ import annotations

import math

import numpy as np


def _clean_polyline(path: np.ndarray) -> np.ndarray:
    """(M, 2) polyline without consecutive duplicate vertices (a zero-length segment has no direction)."""
    p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
    if len(p) < 2:
        return p
    keep = np.ones(len(p), dtype=bool)
    keep[1:] = np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9
    return p[keep]


def polyline_length(path: np.ndarray) -> float:
    """Total arc length of an (M, 2) polyline."""
    p = _clean_polyline(path)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) >= 2 else 0.0


def project_onto_polyline(path: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project (N, 2) points onto an (M >= 2, 2) polyline.

    Returns (s, lateral, tangent): arc length of the foot point from path[0] (N,), signed lateral offset (N,),
    positive to the left of the direction of travel, and the unit tangent of the segment the foot lies on (N, 2).
    The first segment is extended backwards and the last one forwards, so a point behind path[0] gets s < 0 and
    one beyond the end s > length: callers decide "ahead" by s alone, and the lateral offset stays the
    perpendicular distance to the (extended) lane line instead of the distance to an end vertex.
    """
    p = _clean_polyline(path)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(p) < 2:
        raise ValueError("a polyline needs two distinct vertices")
    a, d = p[:-1], np.diff(p, axis=0)  # (S, 2)
    seg_len = np.linalg.norm(d, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])[:-1]
    rel = pts[:, None, :] - a[None, :, :]  # (N, S, 2)
    t = (rel * d[None]).sum(-1) / (seg_len**2)[None]  # (N, S): foot parameter on each segment's line
    lo = np.zeros(len(a))
    hi = np.ones(len(a))
    lo[0], hi[-1] = -np.inf, np.inf
    t = np.clip(t, lo[None], hi[None])
    foot = a[None] + t[..., None] * d[None]
    dist = np.linalg.norm(pts[:, None, :] - foot, axis=-1)
    k = np.argmin(dist, axis=1)  # the first of equally near segments: deterministic
    rows = np.arange(len(pts))
    tangent = d[k] / seg_len[k, None]
    s = cum[k] + t[rows, k] * seg_len[k]
    lateral = tangent[:, 0] * rel[rows, k, 1] - tangent[:, 1] * rel[rows, k, 0]  # z of tangent x (p - a)
    return s, lateral, tangent


def point_in_polygon(polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the (N, 2) points lie inside the (K, 2) polygon (even-odd rule, ray cast along +x)."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    a, b = poly, np.roll(poly, -1, axis=0)
    px, py = pts[:, 0:1], pts[:, 1:2]
    straddles = (a[None, :, 1] > py) != (b[None, :, 1] > py)  # (N, K): the edge crosses the point's horizontal
    ax, ay, bx, by = a[None, :, 0], a[None, :, 1], b[None, :, 0], b[None, :, 1]
    with np.errstate(divide="ignore", invalid="ignore"):  # horizontal edges never straddle: their inf is masked
        x_cross = ax + (py - ay) * (bx - ax) / (by - ay)
    crossings = straddles & (px < x_cross)
    return (crossings.sum(axis=1) % 2) == 1


def distance_to_boundary(polygon: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) distance of each (N, 2) point to the nearest edge of the closed (K, 2) polygon."""
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    a = poly
    d = np.roll(poly, -1, axis=0) - a
    len2 = np.maximum((d**2).sum(1), 1e-18)
    rel = pts[:, None, :] - a[None]
    t = np.clip((rel * d[None]).sum(-1) / len2[None], 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * d[None], axis=-1).min(axis=1)


def in_grown_polygon(polygon: np.ndarray, margin: float, points: np.ndarray) -> np.ndarray:
    """(N,) bool: inside the polygon grown by `margin` (its Minkowski sum with a disc of that radius)."""
    return point_in_polygon(polygon, points) | (distance_to_boundary(polygon, points) <= margin)


def ray_to_grown_polygon(polygon: np.ndarray, margin: float, origin: np.ndarray, direction: np.ndarray) -> float:
    """Distance along the ray origin + t * direction (t >= 0, direction any non-zero vector, normalised here) to
    the polygon grown by `margin`; 0 when the origin is already inside, inf when the ray misses.

    The grown polygon is the polygon's interior united with one capsule (segment + disc of radius `margin`) per
    edge. A ray starting outside can reach the interior only through an edge, i.e. through its capsule, so the
    first entry is the nearest entry into any capsule. A capsule is entered through one of its end discs or one of
    its two long sides (its short sides lie inside the end discs), which gives the three candidates below.
    """
    o = np.asarray(origin, dtype=np.float64).reshape(2)
    u = np.asarray(direction, dtype=np.float64).reshape(2)
    norm = math.hypot(u[0], u[1])
    if norm == 0.0:
        raise ValueError("a ray needs a direction")
    u = u / norm
    poly = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if bool(in_grown_polygon(poly, margin, o[None])[0]):
        return 0.0
    a = poly
    e = np.roll(poly, -1, axis=0) - a
    e_len = np.maximum(np.linalg.norm(e, axis=1), 1e-12)
    e_hat = e / e_len[:, None]
    n_hat = np.stack([-e_hat[:, 1], e_hat[:, 0]], axis=1)
    candidates = [np.full(len(a), np.inf)]
    # End discs: |o + t u - c| = margin, the smaller root (the origin is outside every disc here).
    for c in (a, a + e):
        oc = o[None] - c
        bq = (oc * u[None]).sum(1)
        disc = bq**2 - ((oc**2).sum(1) - margin**2)
        with np.errstate(invalid="ignore"):
            t = -bq - np.sqrt(disc)
        candidates.append(np.where((disc >= 0) & (t >= 0), t, np.inf))
    # Long sides: the lines at +-margin along the edge normal, hit where the foot falls within the edge.
    un = (u[None] * n_hat).sum(1)
    on = ((o[None] - a) * n_hat).sum(1)
    for side in (margin, -margin):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (side - on) / un
        hit = np.where(np.isfinite(t), t, 0.0)  # a ray parallel to the side never meets it (t is inf or nan)
        along = ((o[None] + hit[:, None] * u[None] - a) * e_hat).sum(1)
        ok = np.isfinite(t) & (t >= 0) & (along >= 0) & (along <= e_len)
        candidates.append(np.where(ok, t, np.inf))
    return float(np.min(np.stack(candidates)))
