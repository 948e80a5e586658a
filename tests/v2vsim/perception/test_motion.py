"""Model-free latency compensation of late-fusion outputs (v2vsim.perception.motion)."""

from __future__ import annotations

import math

import numpy as np

from v2vsim.perception.motion import (
    OutputMessage,
    box_velocities,
    compensate_outputs,
    move_boxes,
    move_vehicle_map,
)
from v2vsim.world.geometry import BevGrid, Pose, body_to_world, world_to_body, wrap_angle

GRID = BevGrid(100.0, 256)


def _rot(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


def _boxes_in(pose: Pose, world: np.ndarray) -> np.ndarray:
    """World boxes [K, 6] (x, y, l, w, yaw, score) -> the body frame of `pose`."""
    out = world.copy()
    out[:, :2] = world_to_body(world[:, :2], pose)
    out[:, 4] = wrap_angle(world[:, 4] - pose.yaw)
    return out


def _footprint(box: np.ndarray, value: float = 0.9) -> np.ndarray:
    """A vehicle probability map [S, S] with `value` on the cells whose centres lie in the box."""
    xy = GRID.cell_centres()
    d = xy - box[:2]
    c, s = math.cos(box[4]), math.sin(box[4])
    along, across = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    inside = (np.abs(along) <= box[2] / 2) & (np.abs(across) <= box[3] / 2)
    return np.where(inside, value, 0.0).astype(np.float32)


def _centroid(p: np.ndarray) -> np.ndarray:
    r, c = np.indices(p.shape)
    m = p.astype(np.float64)
    return np.array([(r * m).sum(), (c * m).sum()]) / m.sum()


def test_box_moves_by_v_dt_in_world_frame_with_a_rotated_sender():
    pose = Pose(30.0, -12.0, 1.5, 2.3)
    boxes = np.array([[10.0, 4.0, 4.5, 2.0, 0.4, 0.8], [-6.0, 1.0, 4.0, 1.8, -1.2, 0.6]])
    vel = np.array([[8.0, -3.0], [0.0, 12.0]])
    dt = 0.3
    moved = move_boxes(boxes, pose, vel, dt)
    before = body_to_world(boxes[:, :2], pose)
    after = body_to_world(moved[:, :2], pose)
    np.testing.assert_allclose(after - before, vel * dt, atol=1e-12)
    np.testing.assert_array_equal(moved[:, 2:], boxes[:, 2:])  # size, yaw and score unchanged
    np.testing.assert_array_equal(boxes[0, :2], [10.0, 4.0])  # input untouched


def test_velocities_from_two_messages_with_different_sender_poses():
    world_old = np.array(
        [
            [50.0, 20.0, 4.5, 2.0, 0.1, 0.9],
            [60.0, 25.0, 4.2, 1.9, 1.6, 0.8],
            [45.0, 30.0, 4.0, 1.8, -0.5, 0.7],  # parked
        ]
    )
    v_true = np.array([[12.0, 1.0], [-0.5, -9.0], [0.0, 0.0]])
    dt = 0.1
    world_new = world_old.copy()
    world_new[:, :2] += v_true * dt
    old_pose, new_pose = Pose(40.0, 18.0, 0.0, 0.3), Pose(41.2, 18.5, 0.0, 0.45)
    order = [2, 0, 1]  # the old message lists them in another order
    old = _boxes_in(old_pose, world_old[order])
    new = _boxes_in(new_pose, world_new)
    vel = box_velocities(new, new_pose, 5.1, old, old_pose, 5.0)
    np.testing.assert_allclose(vel, v_true, atol=1e-9)
    assert np.all(vel[2] == 0.0)
    # Tuples work as poses, and dt <= 0 gives no motion.
    vel_t = box_velocities(new, new_pose.as_tuple(), 5.1, old, old_pose.as_tuple(), 5.0)
    np.testing.assert_allclose(vel_t, v_true, atol=1e-9)
    assert not np.any(box_velocities(new, new_pose, 5.0, old, old_pose, 5.0))
    assert not np.any(box_velocities(new, new_pose, 4.9, old, old_pose, 5.0))


def test_unmatched_box_does_not_move():
    pose = Pose(0.0, 0.0, 0.0, 0.7)
    old = np.array([[10.0, 0.0, 4.5, 2.0, 0.0, 0.9]])
    new = np.array([[11.0, 0.0, 4.5, 2.0, 0.0, 0.9], [-20.0, 15.0, 4.5, 2.0, 0.0, 0.9]])  # second one is new
    vel = box_velocities(new, pose, 1.1, old, pose, 1.0)
    assert np.linalg.norm(vel[0]) > 9.0
    np.testing.assert_array_equal(vel[1], [0.0, 0.0])
    moved = move_boxes(new, pose, vel, 0.2)
    np.testing.assert_array_equal(moved[1], new[1])
    # Beyond the gate (40 m/s * 0.1 s + 1 m = 5 m) nothing matches.
    far = np.array([[16.0, 0.0, 4.5, 2.0, 0.0, 0.9]])
    assert not np.any(box_velocities(far, pose, 1.1, old, pose, 1.0))
    assert np.any(box_velocities(far, pose, 1.1, old, pose, 1.0, gate_m=7.0))
    # Empty messages.
    assert box_velocities(np.zeros((0, 6)), pose, 1.1, old, pose, 1.0).shape == (0, 2)
    assert not np.any(box_velocities(new, pose, 1.1, np.zeros((0, 6)), pose, 1.0))


def test_vehicle_blob_moves_by_the_right_number_of_cells():
    pose = Pose(5.0, 7.0, 0.0, 0.5)
    box = np.array([10.0, 5.0, 4.5, 2.0, 0.2, 0.9])
    other = np.array([-20.0, -15.0, 4.5, 2.0, 1.0, 0.8])  # static
    p = np.maximum(_footprint(box), _footprint(other, 0.7))
    dt = 0.2
    shift_cells = np.array([3, -2])  # rows (towards -x), columns (towards -y)
    body_shift = -shift_cells * GRID.res
    v_world = _rot(pose.yaw) @ body_shift / dt
    vel = np.stack([v_world, np.zeros(2)])
    out = move_vehicle_map(p, np.stack([box, other]), pose, vel, dt, bev_size_m=100.0)
    expected = np.maximum(np.roll(_footprint(box), tuple(shift_cells), axis=(0, 1)), _footprint(other, 0.7))
    np.testing.assert_allclose(out, expected, atol=1e-5)
    assert out.dtype == p.dtype
    # A fractional shift moves the centroid of the blob by exactly v * dt (in cells).
    d = np.array([2.3, 1.6])
    v_world = _rot(pose.yaw) @ (-d * GRID.res) / dt
    out = move_vehicle_map(_footprint(box), box[None], pose, v_world[None], dt)
    np.testing.assert_allclose(_centroid(out) - _centroid(_footprint(box)), d, atol=1e-6)
    np.testing.assert_allclose(out.sum(), _footprint(box).sum(), rtol=1e-6)


def test_neighbour_core_is_not_carried_away():
    pose = Pose(0.0, 0.0, 0.0, 0.0)
    mover = np.array([10.0, 0.0, 4.0, 2.0, 0.0, 0.9])
    parked = np.array([10.0, 2.4, 4.0, 2.0, 0.0, 0.9])  # 0.4 m gap: inside the mover's dilation
    p = np.maximum(_footprint(mover), _footprint(parked, 0.8))
    out = move_vehicle_map(p, np.stack([mover, parked]), pose, np.array([[10.0, 0.0], [0.0, 0.0]]), 0.2)
    core = _footprint(parked) > 0
    np.testing.assert_array_equal(out[core], p[core])


def test_age_zero_or_no_old_message_returns_the_inputs():
    rng = np.random.default_rng(0)
    maps = rng.random((3, 256, 256)).astype(np.float32)
    boxes = np.array([[10.0, 0.0, 4.5, 2.0, 0.0, 0.9]], dtype=np.float32)
    new = OutputMessage(maps, boxes, Pose(0.0, 0.0, 0.0, 0.0), 1.0)
    old = (maps, boxes - np.array([1.0, 0, 0, 0, 0, 0], dtype=np.float32), (0.0, 0.0, 0.0, 0.0), 0.9)
    m, b = compensate_outputs(new, old, 0.0)
    assert m is maps and b is boxes
    m, b = compensate_outputs(new, None, 0.3)
    assert m is maps and b is boxes


def test_static_scene_is_unchanged():
    world = np.array([[50.0, 20.0, 4.5, 2.0, 0.1, 0.9], [62.0, 26.0, 4.2, 1.9, 1.6, 0.8]])
    old_pose, new_pose = Pose(40.0, 18.0, 0.0, 0.3), Pose(42.0, 19.0, 0.0, 0.5)  # the sender drives
    new_boxes = _boxes_in(new_pose, world)
    maps = np.stack([np.maximum(_footprint(new_boxes[0]), _footprint(new_boxes[1])), *np.zeros((2, 256, 256))])
    new = OutputMessage(maps.astype(np.float32), new_boxes, new_pose, 2.0)
    old = OutputMessage(maps.astype(np.float32), _boxes_in(old_pose, world), old_pose, 1.9)
    m, b = compensate_outputs(new, old, 0.15)
    np.testing.assert_array_equal(m, new.maps)
    np.testing.assert_array_equal(b, new.boxes)


def test_compensate_outputs_moves_boxes_and_vehicle_map_together():
    old_pose, new_pose = Pose(0.0, 0.0, 0.0, 0.4), Pose(1.0, 0.5, 0.0, 0.4)
    world_old = np.array([[20.0, 10.0, 4.5, 2.0, 0.4, 0.9]])
    v = np.array([10.0, 4.0])
    world_new = world_old.copy()
    world_new[:, :2] += v * 0.1
    new_boxes = _boxes_in(new_pose, world_new)
    rng = np.random.default_rng(1)
    maps = np.stack([_footprint(new_boxes[0]), rng.random((256, 256)), rng.random((256, 256))]).astype(np.float32)
    new = OutputMessage(maps, new_boxes, new_pose, 3.1)
    old = OutputMessage(maps, _boxes_in(old_pose, world_old), old_pose, 3.0)
    age = 0.25
    m, b = compensate_outputs(new, old, age)
    np.testing.assert_allclose(body_to_world(b[:, :2], new_pose), world_new[:, :2] + v * age, atol=1e-9)
    np.testing.assert_array_equal(m[1:], maps[1:])  # road and lane unchanged
    expected_shift = np.array([-1.0, -1.0]) * (_rot(-new_pose.yaw) @ (v * age)) / GRID.res  # (rows, cols)
    np.testing.assert_allclose(_centroid(m[0]) - _centroid(maps[0]), expected_shift, atol=1e-4)
