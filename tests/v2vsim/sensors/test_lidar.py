"""LiDAR sweeps: frame, exact ranges, occlusion, own-body exclusion, noise, dropout, intensity."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from v2vsim.config import LidarConfig
from v2vsim.sensors.lidar import lidar_sweep
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.world.state import Building

from ._worlds import car, rect, static_map, world

CFG = LidarConfig(channels=16, points_per_channel=720, range_m=80.0, vertical_fov_deg=(-15.0, 0.0),
                  height_m=1.9, noise_std_m=0.0, dropout=0.0)


def test_box_face_straight_ahead_at_known_range() -> None:
    """A 3 m tall box whose rear face is 10 m ahead along the (rotated) heading: the level forward
    beam returns x = 10, y = 0, z = 0 in the LiDAR frame exactly (noise 0), labelled with the box."""
    yaw = 0.7
    c, s = math.cos(yaw), math.sin(yaw)
    ego = car("ego", 5.0, -3.0, yaw, cav=True)
    box = car("box", 5.0 + 12.0 * c, -3.0 + 12.0 * s, yaw, extent=(4.0, 2.0, 3.0))
    sw = lidar_sweep(world([ego, box]), "ego", CFG, np.random.default_rng(0))
    fwd = np.flatnonzero((np.abs(sw.points[:, 1]) < 1e-6) & (np.abs(sw.points[:, 2]) < 1e-6)
                         & (sw.points[:, 0] > 0))
    assert len(fwd) == 1
    assert np.allclose(sw.points[fwd[0], :3], [10.0, 0.0, 0.0], atol=1e-4)
    assert sw.hit_actor[fwd[0]] == 1
    assert sw.hits_per_actor(2).tolist() == [0, int((sw.hit_actor == 1).sum())]
    assert sw.points.dtype == np.float32 and sw.points.shape[1] == 4 and sw.hit_actor.dtype == np.int32


def test_ground_points_at_minus_height_and_own_body_excluded() -> None:
    cfg = dataclasses.replace(CFG, vertical_fov_deg=(-25.0, -1.0))
    sw = lidar_sweep(world([car("ego", 1.0, 2.0, 0.3, cav=True)]), "ego", cfg, np.random.default_rng(0))
    assert len(sw.points) > 0.9 * cfg.channels * cfg.points_per_channel
    assert np.allclose(sw.points[:, 2], -cfg.height_m, atol=1e-5)
    assert (sw.hit_actor == -1).all()
    horiz = np.hypot(sw.points[:, 0], sw.points[:, 1])
    assert horiz.min() > cfg.height_m / math.tan(math.radians(25.0)) - 1e-3  # nothing on the own roof
    assert np.sqrt(horiz**2 + cfg.height_m**2).max() <= cfg.range_m + 1e-6


def occlusion_world(with_building: bool):
    b = (Building("wall", rect(8.0, -8.0, 12.0, 8.0), 10.0),) if with_building else ()
    return world([car("ego", 0.0, 0.0, cav=True), car("hidden", 20.0, 0.0)], static_map(b))


def test_vehicle_behind_building_gets_no_points() -> None:
    for with_building, expect_hidden in ((True, False), (False, True)):
        w = occlusion_world(with_building)
        sw = lidar_sweep(w, "ego", CFG, np.random.default_rng(0))
        assert (sw.hits_per_actor(2)[1] > 20) == expect_hidden


def test_noise_dropout_and_intensity() -> None:
    w = world([car("ego", 0.0, 0.0, cav=True), car("c", 15.0, 4.0, 0.5)],
              static_map(roads=(rect(-60, -5, 60, 5),), markings=(np.array([[-60.0, -1.0], [60.0, -1.0]]),),
                         dashed=(False,)))
    scene = build_scene(w, build_map_assets(w.static))
    clean = lidar_sweep(w, "ego", CFG, np.random.default_rng(1), scene=scene)
    noisy = lidar_sweep(w, "ego", dataclasses.replace(CFG, noise_std_m=0.05), np.random.default_rng(1),
                        scene=scene)
    rdiff = np.linalg.norm(noisy.points[:, :3], axis=1) - np.linalg.norm(clean.points[:, :3], axis=1)
    assert len(noisy.points) == len(clean.points)
    assert 0.04 < rdiff.std() < 0.06 and abs(rdiff.mean()) < 0.005
    dropped = lidar_sweep(w, "ego", dataclasses.replace(CFG, dropout=0.3), np.random.default_rng(2),
                          scene=scene)
    assert abs(len(dropped.points) / len(clean.points) - 0.7) < 0.02
    inten = clean.points[:, 3]
    assert inten.min() >= 0.0 and inten.max() <= 1.0
    ground = clean.hit_actor == -1
    y = clean.points[:, 1]
    marking = ground & (np.abs(y + 1.0) < 0.05) & (np.abs(clean.points[:, 0]) > 5)
    road = ground & (np.abs(y - 2.5) < 1.0) & (np.abs(clean.points[:, 0]) > 5)
    assert marking.sum() > 3 and road.sum() > 20
    # Retro-reflective paint returns far more than asphalt at similar incidence.
    assert np.median(inten[marking]) > 3 * np.median(inten[road])
    assert np.median(inten[clean.hit_actor == 1]) > np.median(inten[road])


def test_a_pole_sees_over_a_van_that_hides_a_car_from_a_roof_but_not_through_a_building() -> None:
    """Issue 68's roadside unit: from 1.9 m a 2.6 m van 8 m ahead hides a car 16 m ahead (every ray that could reach
    the car passes the van below its roof); from a 5 m pole at the same spot the car is hit; a 10 m wall in between
    still hides it from the pole."""
    from v2vsim.sensors.lidar import sweep_from

    cfg = dataclasses.replace(CFG, channels=32, vertical_fov_deg=(-25.0, 5.0))
    van = car("van", 8.0, 0.0, extent=(5.0, 2.0, 2.6))
    target = car("car", 16.0, 0.0)

    def hits(height: float, wall: bool) -> int:
        b = (Building("wall", rect(11.0, -8.0, 12.0, 8.0), 10.0),) if wall else ()
        scene = build_scene(world([van, target], static_map(b)))
        sw = sweep_from(scene, "rsu0", (0.0, 0.0, 0.0), dataclasses.replace(cfg, height_m=height),
                        np.random.default_rng(0))
        return int(sw.hits_per_actor(2)[1])

    assert hits(1.9, wall=False) == 0
    assert hits(5.0, wall=False) > 20
    assert hits(5.0, wall=True) == 0
