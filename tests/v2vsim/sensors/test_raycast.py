"""Column ray casting against a dense brute-force reference and hand-computed hits."""

from __future__ import annotations

import math

import numpy as np

from v2vsim.sensors.raycast import cast_columns
from v2vsim.sensors.scene import (
    HIT_BUILDING,
    HIT_GROUND,
    HIT_NONE,
    HIT_VEHICLE,
    Prisms,
    build_map_assets,
    build_scene,
)
from v2vsim.world.state import Building

from ._worlds import car, rect, static_map, world


def brute_force(prisms: Prisms, o: tuple[float, float], h0: float, az: np.ndarray, tan: np.ndarray,
                max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Dense (rays x prisms x faces) Cyrus-Beck in 3D: (t, kind) per ray, t = horizontal distance."""
    a, r = np.meshgrid(az, tan, indexing="ij")
    d = np.stack([np.cos(a), np.sin(a), r], axis=-1).reshape(-1, 3)  # per unit horizontal distance
    n_rays, n_p = len(d), len(prisms)
    best_t = np.full(n_rays, np.inf)
    best_kind = np.zeros(n_rays, dtype=np.int8)
    for p in range(n_p):
        entry = np.zeros(n_rays)
        exit_ = np.full(n_rays, np.inf)
        faces = [(prisms.normals[p, k, 0], prisms.normals[p, k, 1], 0.0, prisms.offsets[p, k])
                 for k in range(prisms.normals.shape[1])]
        faces += [(0.0, 0.0, 1.0, prisms.height[p]), (0.0, 0.0, -1.0, 0.0)]
        ok = np.ones(n_rays, dtype=bool)
        for nx, ny, nz, c in faces:
            num = c - (nx * o[0] + ny * o[1] + nz * h0)
            den = d @ np.array([nx, ny, nz])
            with np.errstate(divide="ignore", invalid="ignore"):
                tt = num / den
            entry = np.where(den < 0, np.maximum(entry, tt), entry)
            exit_ = np.where(den > 0, np.minimum(exit_, tt), exit_)
            ok &= ~((den == 0) & (num < 0))
        hit = ok & (entry <= exit_) & (entry < best_t)
        best_t[hit] = entry[hit]
        best_kind[hit] = prisms.kind[p]
    tf = tan.copy()
    tg = np.where(np.broadcast_to(tf, a.shape).reshape(-1) < 0, -h0 / np.minimum(r.reshape(-1), -1e-12), np.inf)
    g = tg < best_t
    best_t[g], best_kind[g] = tg[g], HIT_GROUND
    rng = best_t * np.sqrt(1 + r.reshape(-1) ** 2)
    best_kind[rng > max_range] = HIT_NONE
    best_t[rng > max_range] = np.inf
    return best_t.reshape(a.shape), best_kind.reshape(a.shape)


def random_scene(seed: int):
    rng = np.random.default_rng(seed)
    actors = [car("ego", 0.0, 0.0, cav=True)]
    while len(actors) < 25:
        x, y = rng.uniform(-40, 40, 2)
        if math.hypot(x, y) < 6:
            continue
        ext = (float(rng.uniform(3.5, 10)), float(rng.uniform(1.6, 2.6)), float(rng.uniform(1.2, 3.5)))
        actors.append(car(f"v{len(actors)}", float(x), float(y), float(rng.uniform(-3.2, 3.2)), extent=ext))
    buildings = (
        Building("L", np.array([[10, 10], [30, 10], [30, 15], [15, 15], [15, 30], [10, 30]], float), 12.0),
        Building("r", rect(-30, 12, -18, 25), 3.0),  # taller than the sensor: no roof hits
        Building("low", rect(-25, -30, -12, -22), 1.2),  # lower than the sensor: roof visible
    )
    return world(actors, static_map(buildings))


def test_matches_dense_brute_force() -> None:
    """Every ray agrees with a dense reference (kind; t to 1e-6) except a few tangent grazes."""
    roof_hits = 0
    for seed, h0 in ((0, 1.9), (1, 4.0), (2, 2.5)):
        w = random_scene(seed)
        scene = build_scene(w, build_map_assets(w.static, res=0.5))
        keep = np.flatnonzero(scene.prisms.actor != 0)
        sub = Prisms(*(getattr(scene.prisms, f)[keep] for f in
                       ("verts", "normals", "offsets", "height", "actor", "kind", "centre", "radius")))
        az = np.linspace(-math.pi, math.pi, 721)[:-1] + 0.0013
        tan = np.tan(np.radians(np.linspace(-25, 10, 36)))
        hits = cast_columns(scene.prisms, (0.0, 0.0), h0, az, tan, max_range=60.0, exclude_actor=0)
        ref_t, ref_kind = brute_force(sub, (0.0, 0.0), h0, az, tan, 60.0)
        agree = (hits.kind == ref_kind) & (
            np.isclose(hits.t, ref_t, atol=1e-6) | (np.isinf(hits.t) & np.isinf(ref_t)))
        assert agree.mean() > 0.999, (seed, agree.mean())
        solid = hits.kind >= HIT_VEHICLE
        roofs = solid & (hits.normal[..., 2] == 1.0)
        assert (hits.kind == HIT_VEHICLE).sum() > 200 and (hits.kind == HIT_BUILDING).sum() > 200
        assert (solid & ~roofs).sum() > 1000
        roof_hits += int(roofs.sum())
    assert roof_hits > 200


def test_known_distances_side_roof_ground_sky() -> None:
    w = world([car("ego", 0, 0, cav=True), car("c", 12.0, 0.0, extent=(4.0, 2.0, 1.5))],
              static_map((Building("b", rect(20, -5, 30, 5), 10.0),)))
    scene = build_scene(w, build_map_assets(w.static, res=0.5))
    el = np.radians([-30.0, -5.0, -2.0, 0.0, 10.0, 40.0])
    hits = cast_columns(scene.prisms, (0.0, 0.0), 1.9, np.array([0.0]), np.tan(el), exclude_actor=0)
    t, kind = hits.t[0], hits.kind[0]
    assert kind.tolist() == [HIT_GROUND, HIT_VEHICLE, HIT_VEHICLE, HIT_BUILDING, HIT_BUILDING, HIT_NONE]
    assert math.isclose(t[0], 1.9 / math.tan(math.radians(30)))
    assert math.isclose(t[1], 10.0)  # rear face of the car
    assert math.isclose(t[2], 0.4 / math.tan(math.radians(2)))  # descends onto the roof
    assert hits.normal[0, 1].tolist() == [-1.0, 0.0, 0.0] and hits.normal[0, 2].tolist() == [0, 0, 1]
    assert math.isclose(t[3], 20.0) and hits.actor[0, 1] == 1 and hits.actor[0, 3] == -1
    # Without exclusion the sensor sits inside its own body: every ray hits it at once.
    own = cast_columns(scene.prisms, (0.0, 0.0), 1.2, np.array([0.0]), np.tan(el))
    assert (own.actor == 0).all()


def test_l_shaped_building_notch_is_empty() -> None:
    """A non-convex footprint: a ray through the notch of the L passes to the ground beyond it."""
    w = world([car("ego", 0, 0, cav=True)], static_map((
        Building("L", np.array([[10, -10], [20, -10], [20, 10], [15, 10], [15, -5], [10, -5]], float), 8.0),)))
    scene = build_scene(w, build_map_assets(w.static, res=0.5))
    tan = np.array([-1.9 / 30.0, 0.0])  # ground at 30 m; horizontal
    az = np.array([math.atan2(0, 1), math.atan2(-8, 10)])  # through the notch (y = 0); into the L's foot
    hits = cast_columns(scene.prisms, (0.0, 0.0), 1.9, az, tan, exclude_actor=0)
    assert hits.kind[0].tolist() == [HIT_BUILDING, HIT_BUILDING]
    assert math.isclose(hits.t[0, 1], 15.0)  # the inner wall of the notch, not x = 10
    assert hits.kind[1, 1] == HIT_BUILDING and math.isclose(hits.t[1, 1], math.hypot(10, 8))
