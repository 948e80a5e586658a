"""Column ray casting against vertical prisms and the ground plane (numpy, one thread).

Rays are grouped in columns: all rays of a column share an azimuth, so they lie in one
vertical half-plane through the sensor. A LiDAR column is one firing of all channels; for a
level pinhole camera every image column is such a plane too. Per column:

1. 2D: clip the column's horizontal ray against each convex footprint it can reach
   (Cyrus-Beck), giving the interval [t_in, t_out] of horizontal distance inside the prism.
   Only (column, prism) pairs whose azimuth span overlaps are formed: each prism's span
   from the sensor is mapped to a range of columns with one searchsorted, so the work
   is proportional to the pairs that actually hit, not columns x prisms.
2. Elevation: a ray of slope tan(el) has z(t) = h0 + t tan(el). It hits the prism's side
   face at t_in iff 0 <= z(t_in) <= height, or its top face iff it descends through the
   roof inside the interval. Both conditions are an interval of tan(el), so with the
   elevations sorted each pair covers a contiguous range of rays (two searchsorteds).
3. Distinct prisms are disjoint, so their intervals along a column are disjoint: with the
   pairs sorted by t_in the first pair covering a ray is its first hit. Rays no pair covers
   hit the ground (el < 0, at t = h0 / -tan(el)) or nothing.

The slope of ray (column a, row r) is q[r] * scale[a]: LiDAR uses scale 1 (q = tan of the
channel elevations); a pinhole camera uses q = the up-component per unit depth of its pixel
row and scale = cos of the column's angle off the optical axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from v2vsim.sensors.scene import HIT_GROUND, HIT_NONE, Prisms


@dataclass(frozen=True)
class RayHits:
    """Per ray (column a, row r), in the caller's column order.

    t: horizontal distance to the hit (inf where none); range: slant distance;
    kind: HIT_*; actor: WorldState actor index or -1; normal: world-frame unit surface normal.
    """

    t: np.ndarray  # (A, R) float64
    range: np.ndarray  # (A, R) float64
    kind: np.ndarray  # (A, R) int8
    actor: np.ndarray  # (A, R) int32
    normal: np.ndarray  # (A, R, 3) float32
    tan_el: np.ndarray  # (A, R) float64, the slope of each ray


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _column_ranges(prisms: Prisms, idx: np.ndarray, ox: float, oy: float,
                   sorted_az: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the prisms `idx`: (prism, start, stop) runs of sorted columns inside their azimuth span."""
    n_cols = len(sorted_az)
    verts = prisms.verts[idx]
    ang = np.arctan2(verts[..., 1] - oy, verts[..., 0] - ox)
    cen = prisms.centre[idx]
    cang = np.arctan2(cen[:, 1] - oy, cen[:, 0] - ox)
    rel = _wrap(ang - cang[:, None])
    eps = 1e-9
    lo = _wrap(cang + rel.min(axis=1) - eps)
    hi = lo + (rel.max(axis=1) - rel.min(axis=1)) + 2 * eps
    # A sensor inside a footprint (not its own, which is excluded) sees the prism all around.
    inside = np.all(prisms.normals[idx, :, 0] * ox + prisms.normals[idx, :, 1] * oy
                    <= prisms.offsets[idx] + 1e-9, axis=1)
    start = np.searchsorted(sorted_az, lo, side="left")
    stop = np.searchsorted(sorted_az, hi, side="right")
    start[inside], stop[inside] = 0, n_cols
    wrap = (hi >= math.pi) & ~inside
    w_stop = np.searchsorted(sorted_az, hi[wrap] - 2 * math.pi, side="right")
    pid = np.concatenate([idx, idx[wrap]])
    return pid, np.concatenate([start, np.zeros_like(w_stop)]), np.concatenate([stop, w_stop])


def cast_columns(prisms: Prisms, origin_xy: tuple[float, float], h0: float, azimuth: np.ndarray,
                 q: np.ndarray, scale: np.ndarray | None = None, max_range: float = math.inf,
                 exclude_actor: int | None = None) -> RayHits:
    """Cast A x R rays from (x, y, h0): column a at world azimuth `azimuth[a]`, slope q[r] * scale[a].

    q must be ascending and scale > 0. Hits farther than `max_range` (slant) count as none.
    `exclude_actor` drops that actor's prism (the sensing vehicle's own body).
    """
    azimuth = np.asarray(azimuth, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    n_a, n_r = len(azimuth), len(q)
    scale = np.ones(n_a) if scale is None else np.asarray(scale, dtype=np.float64)
    ox, oy = float(origin_xy[0]), float(origin_xy[1])

    az_w = _wrap(azimuth)
    order = np.argsort(az_w, kind="stable")
    saz = az_w[order]
    sscale = scale[order]
    tan = q[None, :] * sscale[:, None]  # (A, R) slopes, sorted column order

    # -- candidate prisms: not excluded, within range ------------------------------------------
    keep = np.hypot(prisms.centre[:, 0] - ox, prisms.centre[:, 1] - oy) - prisms.radius <= max_range
    if exclude_actor is not None and exclude_actor >= 0:
        keep &= prisms.actor != exclude_actor
    idx = np.flatnonzero(keep)

    pair_first = np.full((n_a, n_r), -1, dtype=np.int64)
    if len(idx):
        pid, start, stop = _column_ranges(prisms, idx, ox, oy, saz)
        cnt = np.maximum(stop - start, 0)
        total = int(cnt.sum())
    else:
        total = 0
    if total:
        # -- (column, prism) pairs --------------------------------------------------------------
        pp = np.repeat(pid, cnt)
        col = np.repeat(start - (np.cumsum(cnt) - cnt), cnt) + np.arange(total)
        # Cyrus-Beck: inside iff n_k . (o + t d) <= c_k for every edge k.
        nrm = prisms.normals[pp]  # (M, V, 2)
        num = prisms.offsets[pp] - (nrm[..., 0] * ox + nrm[..., 1] * oy)
        den = nrm[..., 0] * np.cos(saz)[col, None] + nrm[..., 1] * np.sin(saz)[col, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = num / den
        entry = np.where(den < -1e-12, ratio, -np.inf)
        exit_ = np.where(den > 1e-12, ratio, np.inf)
        blocked = np.any((np.abs(den) <= 1e-12) & (num < 0), axis=1)
        edge = np.argmax(entry, axis=1)
        t_in = np.take_along_axis(entry, edge[:, None], axis=1)[:, 0]
        t_out = exit_.min(axis=1)
        ok = (t_in <= t_out) & (t_out > 0) & ~blocked & (t_in <= max_range)
        pp, col, edge, t_in, t_out = pp[ok], col[ok], edge[ok], t_in[ok], t_out[ok]
        t_in = np.maximum(t_in, 1e-6)

        # -- which rays of the column each pair covers -----------------------------------------
        h = prisms.height[pp]
        s = sscale[col]
        side_hi = (h - h0) / t_in
        lo = -h0 / t_in
        hi = np.where(h >= h0, side_hi, (h - h0) / t_out)
        r0 = np.searchsorted(q, lo / s, side="left")
        r1 = np.searchsorted(q, hi / s, side="right")
        rs = np.searchsorted(q, side_hi / s, side="right")  # rows >= rs hit the roof
        use = r1 > r0
        pp, col, edge, t_in, h, r0, r1, rs = (a[use] for a in (pp, col, edge, t_in, h, r0, r1, rs))

        if len(pp):
            srt = np.lexsort((t_in, col))
            pp, col, edge, t_in, h, r0, r1, rs = (a[srt] for a in (pp, col, edge, t_in, h, r0, r1, rs))
            m = len(pp)
            rows = np.arange(n_r, dtype=np.int32)
            cover = (rows >= r0[:, None].astype(np.int32)) & (rows < r1[:, None].astype(np.int32))
            val = np.where(cover, np.arange(m, dtype=np.int32)[:, None], np.int32(m))
            seg = np.flatnonzero(np.concatenate([[True], col[1:] != col[:-1]]))
            first = np.minimum.reduceat(val, seg, axis=0)
            first = np.where(first == m, -1, first)
            pair_first[col[seg]] = first

    # -- resolve every ray -------------------------------------------------------------------------
    t = np.full((n_a, n_r), np.inf)
    kind = np.zeros((n_a, n_r), dtype=np.int8)
    actor = np.full((n_a, n_r), -1, dtype=np.int32)
    normal = np.zeros((n_a, n_r, 3), dtype=np.float32)
    normal[..., 2] = 1.0

    hit = pair_first >= 0
    if hit.any():
        p = pair_first[hit]
        ridx = np.nonzero(hit)[1]
        side = ridx < rs[p]
        with np.errstate(divide="ignore"):
            t_roof = (h[p] - h0) / tan[hit]
        t[hit] = np.where(side, t_in[p], t_roof)
        kind[hit] = prisms.kind[pp[p]]
        actor[hit] = prisms.actor[pp[p]]
        nside = prisms.normals[pp[p], edge[p]]
        nh = np.zeros((len(p), 3), dtype=np.float32)
        nh[:, 2] = 1.0
        nh[side, 0], nh[side, 1], nh[side, 2] = nside[side, 0], nside[side, 1], 0.0
        normal[hit] = nh
    ground = ~hit & (tan < 0)
    t[ground] = -h0 / tan[ground]
    kind[ground] = HIT_GROUND

    rng = t * np.sqrt(1.0 + tan * tan)
    far = rng > max_range
    kind[far] = HIT_NONE
    actor[far] = -1
    t[far] = np.inf
    rng[far] = np.inf

    if np.array_equal(order, np.arange(n_a)):  # columns were given sorted (LiDAR): no reorder
        return RayHits(t, rng, kind, actor, normal, tan)
    inv = np.empty_like(order)
    inv[order] = np.arange(n_a)
    return RayHits(t[inv], rng[inv], kind[inv], actor[inv], normal[inv], tan[inv])
