"""The free-space checks (v2vsim/perception/evidence_check.py) on hand-made grids: a phantom in space another agent
sees free, a removed car the ego sees, a removed car only the liar's own rays hit, and a liar whose evidence agrees
with its lie where nobody else sees (not caught, by design)."""

from __future__ import annotations

import numpy as np
import torch

from v2vsim.perception.evidence import FREE, OCCUPIED, UNKNOWN
from v2vsim.perception.evidence_check import check_evidence

SIZE, F, G = 100.0, 64, 128
CAV1 = np.array([20.0, 0.0, 0.0], np.float32)  # 20 m ahead of the ego, same heading
EGO = np.zeros(3, np.float32)


def _rows_cols(cells: int, x0: float, x1: float, y0: float, y1: float) -> tuple[slice, slice]:
    """The cells of a body-frame box x0..x1 (forward), y0..y1 (left) on a cells x cells grid."""
    c = SIZE / cells
    return (slice(int((SIZE / 2 - x1) // c), int(np.ceil((SIZE / 2 - x0) / c))),
            slice(int((SIZE / 2 - y1) // c), int(np.ceil((SIZE / 2 - y0) / c))))


def _evidence(free: tuple | None = None, occupied: tuple | None = None) -> np.ndarray:
    g = np.full((F, F), UNKNOWN, np.uint8)
    if free:
        g[_rows_cols(F, *free)] = FREE
    if occupied:
        g[_rows_cols(F, *occupied)] = OCCUPIED
    return g


def _vehicle(*boxes: tuple) -> np.ndarray:
    v = np.zeros((G, G), np.float32)
    for b in boxes:
        v[_rows_cols(G, *b)] = 1.0
    return v


def test_a_phantom_where_the_ego_sees_free_road_is_caught_and_a_real_car_is_not() -> None:
    ego_ev = _evidence(free=(0.0, 45.0, -8.0, 8.0))  # the ego's rays pass down the open road ahead
    phantom = check_evidence({"ego": _vehicle(), "cav1": _vehicle((7.7, 12.3, -1.0, 1.0))},  # a car at ego x = 30
                             {"ego": ego_ev, "cav1": _evidence()}, {"ego": EGO, "cav1": CAV1}, SIZE, G)
    assert phantom["cav1"].phantom_m2 > 6.0 and phantom["cav1"].witnessed_m2 > 6.0
    # a real car there: the ego's rays stop at its rear face, nothing behind it is free
    real_ev = _evidence(free=(0.0, 26.0, -8.0, 8.0), occupied=(27.0, 28.6, -1.0, 1.0))
    honest = check_evidence({"ego": _vehicle((27.7, 32.3, -1.0, 1.0)), "cav1": _vehicle((7.7, 12.3, -1.0, 1.0))},
                            {"ego": real_ev, "cav1": _evidence(occupied=(6.0, 8.0, -1.0, 1.0))},
                            {"ego": EGO, "cav1": CAV1}, SIZE, G)
    assert honest["cav1"].phantom_m2 == 0.0 and honest["ego"].phantom_m2 == 0.0


def test_a_car_removed_where_the_ego_sees_it_is_caught() -> None:
    car = (27.7, 32.3, 4.0, 6.0)  # ego frame; cav1 at x = 20 reaches it too (its rays stop on its side)
    ego_ev = _evidence(free=(0.0, 26.0, 0.0, 8.0), occupied=(27.0, 29.0, 4.0, 6.0))
    liar_ev = _evidence(free=(0.0, 6.0, 0.0, 8.0), occupied=(7.0, 9.0, 4.0, 6.0))  # honest rays, in its frame
    v = check_evidence({"ego": _vehicle(car), "cav1": _vehicle()}, {"ego": ego_ev, "cav1": liar_ev},
                       {"ego": EGO, "cav1": CAV1}, SIZE, G)
    assert v["cav1"].removed_m2 > 2.0 and v["ego"].removed_m2 == 0.0


def test_a_car_only_the_liar_sees_is_caught_by_its_own_rays_unless_it_lies_in_them_too() -> None:
    road = np.zeros((G, G), bool)
    road[_rows_cols(G, -50.0, 50.0, -4.0, 8.0)] = True  # the drivable area of the ego's map, ego frame
    nobody = _evidence()  # the ego sees nothing there (a building between)
    honest_rays = _evidence(occupied=(12.0, 14.0, 4.0, 6.0))
    caught = check_evidence({"ego": _vehicle(), "cav1": _vehicle()}, {"ego": nobody, "cav1": honest_rays},
                            {"ego": EGO, "cav1": CAV1}, SIZE, G, road_map=road)
    assert caught["cav1"].unclaimed_m2 > 2.0
    consistent = check_evidence({"ego": _vehicle(), "cav1": _vehicle()}, {"ego": nobody, "cav1": _evidence()},
                                {"ego": EGO, "cav1": CAV1}, SIZE, G, road_map=road)
    assert consistent["cav1"] == type(consistent["cav1"])(0.0, 0.0, 0.0, 0.0)  # by design: nobody else sees


def _walls_world() -> tuple[np.ndarray, np.ndarray]:
    """The map's buildings on the ego grid (a block on the left, one ahead) and the hits an honest sender at the
    ego's own pose has on their faces, at the evidence grid (128 x 128 over 100 m)."""
    from v2vsim.perception.evidence import OCCUPIED as HIT

    e = 128
    buildings = np.zeros((e, e), bool)
    buildings[_rows_cols(e, -40.0, 40.0, 8.0, 30.0)] = True
    buildings[_rows_cols(e, 25.0, 45.0, -30.0, 5.0)] = True
    ev = np.full((e, e), UNKNOWN, np.uint8)
    c = SIZE / e
    def cell(x: float, y: float) -> tuple[int, int]:
        return int((SIZE / 2 - x) // c), int((SIZE / 2 - y) // c)

    for x in np.arange(-30.0, 24.0, c / 2):
        ev[cell(x, 8.2)] = HIT  # the left block's face
    for y in np.arange(-25.0, 4.0, c / 2):
        ev[cell(25.2, y)] = HIT  # the face ahead
    return buildings, ev


def test_a_pose_told_two_metres_or_five_degrees_off_is_corrected_against_the_map_and_a_true_one_is_not() -> None:
    from v2vsim.perception.evidence_check import pose_check

    buildings, ev = _walls_world()
    honest = pose_check(ev, EGO, buildings, SIZE)
    assert honest is not None and honest.shift_m < 0.8 and honest.turn_deg == 0.0 and honest.on_map > 0.9
    moved = pose_check(ev, np.array([2.0, 0.0, 0.0], np.float32), buildings, SIZE)  # claims 2 m ahead of the truth
    assert moved is not None and 1.5 <= moved.shift_m <= 2.5 and moved.on_map < 0.7 < moved.on_map_corrected
    turned = pose_check(ev, np.array([0.0, 0.0, np.radians(5.0)], np.float32), buildings, SIZE)
    assert turned is not None and turned.turn_deg in (-4.0, -6.0) and turned.on_map_corrected > turned.on_map
    assert pose_check(np.full_like(ev, UNKNOWN), EGO, buildings, SIZE) is None  # no hits: nothing to judge


def _road() -> torch.Tensor:
    """A straight road, 8 m wide along the ego's x axis, on the comparison grid."""
    r = np.zeros((G, G), bool)
    r[_rows_cols(G, -50.0, 50.0, -4.0, 4.0)] = True
    return torch.from_numpy(r)


def test_the_egos_later_view_finds_a_phantom_gone_from_its_own_free_road_and_forgives_a_car_that_moved_on() -> None:
    from v2vsim.perception.evidence_check import later_claims, later_view_check, on_ego_grid

    road, reach = _road(), 15.0 * 0.4  # 15 m/s over 3 frames and one more at 10 Hz
    # then (ego at the world origin): cav1, 20 m ahead, claims a car at ego x = 32..36 (cav1 x = 12..16)
    then = on_ego_grid({"ego": _vehicle(), "cav1": _vehicle((12.0, 16.0, -1.0, 1.0))},
                       {"ego": _evidence(), "cav1": _evidence()}, {"ego": EGO, "cav1": CAV1}, SIZE, G)
    claims = later_claims(then, {"ego": EGO, "cav1": CAV1}, 3, (0.0, 0.0, 0.0), SIZE)
    # now the ego has moved 3 m on (world x = 3): its rays reach the whole road out to 45 m, and clear
    ego_pose = (3.0, 0.0, 0.0)
    free_road = on_ego_grid({"ego": _vehicle()}, {"ego": _evidence(free=(-5.0, 45.0, -5.0, 5.0))}, {"ego": EGO},
                            SIZE, G)
    gone = later_view_check(claims["cav1"], free_road, ego_pose, road, reach, SIZE)
    assert gone.frame == 3 and gone.phantom_m2 > 5.0 and gone.removed_m2 == 0.0
    # the car was real and drove 4 m on: the ego now sees it at world x = 36..40 (its x = 33..37)
    moved = on_ego_grid({"ego": _vehicle((33.0, 37.0, -1.0, 1.0))},
                        {"ego": _evidence(free=(-5.0, 32.5, -5.0, 5.0), occupied=(33.0, 37.0, -1.0, 1.0))},
                        {"ego": EGO}, SIZE, G)
    assert later_view_check(claims["cav1"], moved, ego_pose, road, reach, SIZE).phantom_m2 == 0.0
    # the ego's rays never reached there (unknown past 20 m): nothing to judge by
    short = on_ego_grid({"ego": _vehicle()}, {"ego": _evidence(free=(-5.0, 20.0, -5.0, 5.0))}, {"ego": EGO}, SIZE, G)
    assert later_view_check(claims["cav1"], short, ego_pose, road, reach, SIZE).phantom_m2 == 0.0


def test_the_egos_later_view_finds_a_car_where_a_sender_vouched_the_road_empty_but_not_where_its_rays_did_not_reach(
) -> None:
    from v2vsim.perception.evidence_check import later_claims, later_view_check, on_ego_grid

    road, reach = _road(), 15.0 * 0.4
    # then: cav1 claims nothing; its rays cleared the road from 0 to 30 m ahead of it (ego x = 20..50)
    liar = on_ego_grid({"ego": _vehicle(), "cav1": _vehicle()},
                       {"ego": _evidence(), "cav1": _evidence(free=(0.0, 30.0, -5.0, 5.0))},
                       {"ego": EGO, "cav1": CAV1}, SIZE, G)
    blind = on_ego_grid({"ego": _vehicle(), "cav1": _vehicle()}, {"ego": _evidence(), "cav1": _evidence()},
                        {"ego": EGO, "cav1": CAV1}, SIZE, G)
    poses = {"ego": EGO, "cav1": CAV1}
    # now (ego 3 m on) the ego's rays stop on a car at world x = 35..39 that it maps (its x = 32..36)
    now = on_ego_grid({"ego": _vehicle((32.0, 36.0, -1.0, 1.0))},
                      {"ego": _evidence(free=(-5.0, 31.5, -5.0, 5.0), occupied=(32.0, 36.0, -1.0, 1.0))},
                      {"ego": EGO}, SIZE, G)
    removed = later_view_check(later_claims(liar, poses, 0, (0.0, 0.0, 0.0), SIZE)["cav1"], now, (3.0, 0.0, 0.0),
                               road, reach, SIZE)
    assert removed.removed_m2 > 3.0 and removed.phantom_m2 == 0.0
    unseen = later_view_check(later_claims(blind, poses, 0, (0.0, 0.0, 0.0), SIZE)["cav1"], now, (3.0, 0.0, 0.0),
                              road, reach, SIZE)
    assert unseen.removed_m2 == 0.0
