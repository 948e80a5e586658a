"""Pinhole cameras: rig conventions, projection of known boxes, occlusion, image content."""

from __future__ import annotations

import math

import numpy as np
import pytest

from v2vsim.config import CamerasConfig
from v2vsim.sensors.camera import camera_rig, render_cameras, vehicle_colour
from v2vsim.sensors.scene import GROUND_MARKING, build_map_assets, build_scene
from v2vsim.world.state import Building

from ._worlds import car, rect, static_map, world

CFG = CamerasConfig()


def project(rig, cam: int, p_body: np.ndarray) -> tuple[float, float, float]:
    """Body-frame point -> (u, v, depth) in camera `cam` using the rig's own matrices."""
    p_cam = np.linalg.inv(rig.extrinsics[cam]) @ np.append(p_body, 1.0)
    uvw = rig.intrinsics[cam] @ p_cam[:3]
    return uvw[0] / uvw[2], uvw[1] / uvw[2], p_cam[2]


def test_rig_shapes_and_conventions() -> None:
    rig = camera_rig(CFG)
    assert (rig.width, rig.height) == (200, 150)
    assert rig.intrinsics.shape == (4, 3, 3) and rig.extrinsics.shape == (4, 4, 4)
    assert rig.names == ("front", "right", "left", "back")
    f = rig.intrinsics[0, 0, 0]
    assert math.isclose(2 * math.degrees(math.atan(rig.width / 2 / f)), CFG.fov_deg)
    for k, fwd in enumerate(([1, 0, 0], [0, -1, 0], [0, 1, 0], [-1, 0, 0])):
        assert np.allclose(rig.extrinsics[k, :3, 2], fwd)  # camera z = viewing direction
        assert np.allclose(rig.extrinsics[k, :3, 1], [0, 0, -1])  # camera y = down
        assert np.allclose(rig.extrinsics[k, :3, 3], [0, 0, CFG.height_m])
        assert np.allclose(np.linalg.det(rig.extrinsics[k, :3, :3]), 1.0)
    # A point 10 m ahead and 2 m left at camera height lands left of centre on the horizon row.
    u, v, d = project(rig, 0, np.array([10.0, 2.0, CFG.height_m]))
    assert u < (rig.width - 1) / 2 and math.isclose(v, (rig.height - 1) / 2) and math.isclose(d, 10.0)


def test_box_centre_projects_onto_its_pixels() -> None:
    """Project each box centre with the returned intrinsics/extrinsics: the rendered actor-index
    image shows that box at that pixel (front, right, left and back cameras)."""
    yaw = 0.4
    ego = car("ego", 3.0, -2.0, yaw, cav=True)
    placements = {"front": (14.0, 3.0, 0), "right": (-2.0, -11.0, 1), "left": (1.5, 9.0, 2),
                  "back": (-13.0, -1.0, 3)}
    actors = [ego]
    c, s = math.cos(yaw), math.sin(yaw)
    for name, (bx, by, _) in placements.items():
        actors.append(car(name, 3.0 + c * bx - s * by, -2.0 + s * bx + c * by, yaw + 0.3))
    w = world(actors)
    fr = render_cameras(w, "ego", CFG)
    assert fr.images.shape == (4, 150, 200, 3) and fr.images.dtype == np.uint8
    assert fr.actor_index.shape == (4, 150, 200) and fr.actor_index.dtype == np.int32
    for i, (bx, by, cam) in enumerate(placements.values(), start=1):
        u, v, depth = project(fr.rig, cam, np.array([bx, by, 0.75]))
        assert depth > 0 and 0 <= u < fr.rig.width and 0 <= v < fr.rig.height
        assert fr.actor_index[cam, int(round(v)), int(round(u))] == i, (cam, u, v)
        # ... and nowhere in the opposite camera.
        assert not (fr.actor_index[3 - cam] == i).any()
    assert not (fr.actor_index == 0).any()  # the own body is never rendered


def test_vehicle_behind_building_gets_no_pixels() -> None:
    for with_building in (True, False):
        b = (Building("wall", rect(8.0, -8.0, 12.0, 8.0), 10.0),) if with_building else ()
        w = world([car("ego", 0.0, 0.0, cav=True), car("hidden", 20.0, 0.0)], static_map(b))
        fr = render_cameras(w, "ego", CFG)
        assert (fr.pixels_per_actor(2)[1] > 10) == (not with_building)


def test_ground_classes_sky_and_shading() -> None:
    """Road grey, marking white, off-road green below the horizon; sky above; car in its colour."""
    w = world([car("ego", 0.0, 0.0, cav=True), car("c", 12.0, -6.0, 0.0)],
              static_map(roads=(rect(-60, -4, 60, 4),), markings=(np.array([[-60.0, 0.0], [60.0, 0.0]]),),
                         dashed=(False,), buildings=(Building("b", rect(30, 10, 40, 20), 12.0),)))
    scene = build_scene(w, build_map_assets(w.static))
    fr = render_cameras(w, "ego", CFG, scene=scene)
    img = fr.images[0].astype(int)
    rig = fr.rig

    def px(p: list[float]) -> np.ndarray:
        u, v, _ = project(rig, 0, np.array(p))
        return img[int(round(v)), int(round(u))]

    road, mark, grass = px([8.0, 2.0, 0.0]), px([8.0, 0.0, 0.0]), px([8.0, 8.0, 0.0])
    assert abs(road[0] - road[1]) < 10 and abs(road[1] - road[2]) < 10 and 60 < road[0] < 160  # grey
    assert mark.min() > 200  # white paint
    assert grass[1] > grass[0] and grass[1] > grass[2]  # green
    sky = img[0, 100]
    assert sky[2] > sky[0] + 60  # blue
    car_px = fr.actor_index[0] == 1
    assert car_px.sum() > 50
    paint = vehicle_colour("c")
    # Shaded paint (glass band aside): the paint's hue, at more than one brightness (faces differ).
    body = img[car_px]
    body = body[body.sum(axis=1) > 200].astype(float)
    cos = body @ paint / (np.linalg.norm(body, axis=1) * np.linalg.norm(paint))
    assert len(body) > 10 and cos.min() > 0.97
    assert np.ptp(body.sum(axis=1)) > 30
    assert (fr.depth[0][car_px] < 20).all() and np.isinf(fr.depth[0][0, 100])


def test_marking_coverage_conserves_paint_across_footprints() -> None:
    """Integrated across a 0.15 m line, the filtered coverage stays ~0.15 m at every pyramid level
    (distant lines fade rather than vanish or thicken), and a fine footprint sees paint exactly."""
    w = world([car("ego", 0.0, 0.0, cav=True)],
              static_map(roads=(rect(-60, -4, 60, 4),), markings=(np.array([[-60.0, 1.03], [60.0, 1.03]]),),
                         dashed=(False,)))
    ground = build_map_assets(w.static).ground
    ys = np.arange(-2.0, 4.0, 0.01)
    xy = np.stack([np.full_like(ys, 7.3), ys], axis=-1)
    painted = ((ground.sample(xy) & GROUND_MARKING) > 0).sum() * 0.01
    assert abs(painted - 0.15) <= ground.res  # 0.15 m within one raster cell
    for fp in (0.05, 0.2, 0.4, 0.8, 1.6, 3.2):
        cov = ground.marking_coverage(xy, np.full(len(ys), fp))
        assert 0.0 <= cov.min() and cov.max() <= 1.0
        assert abs(cov.sum() * 0.01 - painted) < 0.01, (fp, cov.sum() * 0.01)
        assert ys[np.argmax(cov)] == pytest.approx(1.03, abs=max(fp, 0.1))
    fine = ground.marking_coverage(xy, np.full(len(ys), 0.05))
    assert fine[np.abs(ys - 1.03) < 0.1].max() == 1.0 and fine[np.abs(ys - 1.03) > 0.3].max() == 0.0
