"""Free-space evidence from a sweep's points (v2vsim/perception/evidence.py) on hand-made rays: what a ray crosses low
is free, what it hits above the ground is occupied, what it never crosses is unknown; the packing round-trips."""

from __future__ import annotations

import numpy as np
import pytest

from v2vsim.perception.evidence import FREE, OCCUPIED, UNKNOWN, evidence_grid, pack, unpack

H, EXTENT, CELLS = 1.9, 100.0, 64
CELL = EXTENT / CELLS


def _cell(x: float, y: float) -> tuple[int, int]:
    return int(np.floor((EXTENT / 2 - x) / CELL)), int(np.floor((EXTENT / 2 - y) / CELL))


def _ray_to(x: float, y: float, above_ground: float) -> np.ndarray:
    return np.array([[x, y, above_ground - H, 0.5]], dtype=np.float32)


def test_a_wall_ahead_frees_the_road_before_it_and_hides_what_is_behind() -> None:
    wall = np.concatenate([_ray_to(20.0, 0.0, hgt) for hgt in (0.5, 1.0, 1.5)])
    g = evidence_grid(wall, H, EXTENT, CELLS)
    assert g[_cell(20.0, 0.0)] == OCCUPIED
    # the ray to 0.5 m passes below a roof (1.4 m) from 7.1 m on; nearer, every ray is above it: no evidence there
    assert all(g[_cell(x, 0.0)] == FREE for x in (8.0, 12.0, 15.0, 18.0)) and g[_cell(3.0, 0.0)] == UNKNOWN
    assert g[_cell(30.0, 0.0)] == UNKNOWN and g[_cell(0.0, 20.0)] == UNKNOWN


def test_a_ground_return_frees_its_own_cell_and_a_high_ray_frees_nothing() -> None:
    g = evidence_grid(_ray_to(12.0, -6.0, 0.0), H, EXTENT, CELLS)
    assert g[_cell(12.0, -6.0)] == FREE and g[_cell(6.0, -3.0)] == FREE
    # a ray from 1.9 m climbing to a roof 5 m up never passes low enough to rule a car out, and hits no vehicle
    assert not evidence_grid(_ray_to(30.0, 0.0, 5.0), H, EXTENT, CELLS).any()


def test_occupied_wins_over_a_ray_that_passed_the_cell() -> None:
    pts = np.concatenate([_ray_to(10.0, 0.0, 1.0), _ray_to(10.0 + CELL / 4, 0.0, 0.0)])  # a car, the ground past
    assert evidence_grid(pts, H, EXTENT, CELLS)[_cell(10.0, 0.0)] == OCCUPIED


def test_pack_round_trips_in_a_kilobyte_and_refuses_a_wrong_size() -> None:
    rng = np.random.default_rng(0)
    g = rng.integers(0, 3, (CELLS, CELLS)).astype(np.uint8)
    data = pack(g)
    assert len(data) == 1024 and np.array_equal(unpack(data, CELLS), g)
    with pytest.raises(ValueError, match="1023 bytes, expected 1024"):
        unpack(data[:-1], CELLS)
    assert not evidence_grid(np.zeros((0, 4), np.float32), H, EXTENT, CELLS).any()


def test_a_real_sweep_sees_the_near_car_the_free_road_around_it_and_not_the_car_it_hides() -> None:
    from tests.v2vsim.sensors._worlds import car, world
    from v2vsim.config import LidarConfig
    from v2vsim.sensors.lidar import lidar_sweep

    cfg = LidarConfig(noise_std_m=0.0)  # the shipped sensor: 32 channels, -25 to +5 degrees, 1.9 m up
    w = world([car("ego", 0.0, 0.0, cav=True), car("near", 12.0, 0.0), car("hidden", 22.0, 0.0)])
    g = evidence_grid(lidar_sweep(w, "ego", cfg, np.random.default_rng(0)).points, cfg.height_m, EXTENT, CELLS)
    assert g[_cell(10.0, 0.0)] == OCCUPIED  # the near car's rear face
    assert g[_cell(22.0, 0.0)] == UNKNOWN  # the hidden car: in the near car's shadow, neither seen nor ruled out
    assert g[_cell(12.0, 8.0)] == FREE and g[_cell(-10.0, 0.0)] == FREE  # open road beside and behind
    # a phantom claimed on the open road beside the near car lies in cells this agent saw free
    assert (g[_cell(12.0, 8.0)[0] - 1:_cell(12.0, 8.0)[0] + 2, _cell(12.0, 8.0)[1]] == FREE).all()
