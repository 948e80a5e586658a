"""CARLA (OPV2V) <-> v2vsim coordinates: small pure functions, each the inverse of its partner.

CARLA's world and local frames are left-handed: x forward (east on a map), y right (south), z up; angles
in degrees, yaw clockwise seen from above. v2vsim's are right-handed (DESIGN.md "Frames and units"): x
forward (east), y left (north), z up; radians, yaw counter-clockwise. The two differ by the mirror
F = diag(1, -1, 1) applied on both sides:

    point          p_v = F p_c                  (x, y, z) <-> (x, -y, z)
    yaw            yaw_v = -radians(yaw_c)
    rigid motion   T_v = F4 T_c F4              (F4 = diag(1, -1, 1, 1); its own inverse)

A CARLA pose is [x, y, z, roll, yaw, pitch] (degrees; OPV2V's `lidar_pose`, `true_ego_pos`, camera `cords`,
and a vehicle's `location` + `angle`), turned into a matrix as CARLA and OpenCOOD do:
R = Rz(yaw) . Ry(-pitch) . Rx(-roll) (CARLA's pitch and roll are left-handed too).

Cameras: OPV2V's camera frame uses CARLA's axes (x forward along the optical axis, y right, z up; the
intrinsic projects (y, -z, x)), v2vsim's is OpenCV's (x right, y down, z forward): p_ue = C p_cv.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

F3 = np.diag([1.0, -1.0, 1.0])
F4 = np.diag([1.0, -1.0, 1.0, 1.0])
# OpenCV camera axes -> CARLA (Unreal) camera axes: x_ue = z_cv, y_ue = x_cv, z_ue = -y_cv.
CV_TO_UE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
CV_TO_UE4 = np.eye(4)
CV_TO_UE4[:3, :3] = CV_TO_UE


def carla_rotation(roll: float, yaw: float, pitch: float) -> np.ndarray:
    """(3, 3) rotation of CARLA angles in degrees (local axes -> world axes, both CARLA's)."""
    r, y, p = (math.radians(a) for a in (roll, yaw, pitch))
    cr, sr, cy, sy, cp, sp = math.cos(r), math.sin(r), math.cos(y), math.sin(y), math.cos(p), math.sin(p)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]])  # Ry(-pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, sr], [0.0, -sr, cr]])  # Rx(-roll)
    return rz @ ry @ rx


def carla_angles(rot: np.ndarray) -> tuple[float, float, float]:
    """(roll, yaw, pitch) in degrees of a CARLA-frame rotation: the inverse of carla_rotation."""
    pitch = math.asin(max(-1.0, min(1.0, float(rot[2, 0]))))
    yaw = math.atan2(float(rot[1, 0]), float(rot[0, 0]))
    roll = math.atan2(-float(rot[2, 1]), float(rot[2, 2]))
    return math.degrees(roll), math.degrees(yaw), math.degrees(pitch)


def carla_pose_matrix(pose: Sequence[float]) -> np.ndarray:
    """(4, 4) local-to-world transform of a CARLA pose [x, y, z, roll, yaw, pitch] (CARLA frames)."""
    x, y, z, roll, yaw, pitch = (float(v) for v in pose)
    out = np.eye(4)
    out[:3, :3] = carla_rotation(roll, yaw, pitch)
    out[:3, 3] = (x, y, z)
    return out


def carla_matrix_pose(mat: np.ndarray) -> list[float]:
    """CARLA pose [x, y, z, roll, yaw, pitch] of a (4, 4) CARLA-frame transform (inverse of carla_pose_matrix)."""
    roll, yaw, pitch = carla_angles(mat[:3, :3])
    return [float(mat[0, 3]), float(mat[1, 3]), float(mat[2, 3]), roll, yaw, pitch]


def mirror_transform(mat: np.ndarray) -> np.ndarray:
    """A rigid transform between two frames, re-expressed in the other handedness: F4 . T . F4.

    CARLA local-to-world -> v2vsim local-to-world and back (both frames mirrored); its own inverse."""
    return F4 @ np.asarray(mat, dtype=np.float64) @ F4


def pose_to_carla(x: float, y: float, z: float, yaw: float) -> list[float]:
    """A v2vsim pose (metres, yaw in radians, counter-clockwise) -> CARLA [x, y, z, roll, yaw, pitch]
    (degrees, clockwise; roll and pitch 0: v2vsim's vehicles stay level)."""
    return [float(x), -float(y), float(z), 0.0, -math.degrees(yaw), 0.0]


def pose_from_carla(pose: Sequence[float]) -> tuple[float, float, float, float]:
    """CARLA [x, y, z, roll, yaw, pitch] -> v2vsim (x, y, z, yaw): y and yaw change sign, yaw in radians.
    Roll and pitch are dropped (v2vsim's poses are planar; OPV2V's are within a few tenths of a degree)."""
    return float(pose[0]), -float(pose[1]), float(pose[2]), -math.radians(float(pose[4]))


def planar_pose_matrix(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    """(4, 4) body-to-world transform of a v2vsim pose (right-handed)."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.eye(4)
    out[:2, :2] = ((c, -s), (s, c))
    out[:3, 3] = (x, y, z)
    return out


def points_to_carla(points: np.ndarray) -> np.ndarray:
    """(P, >=3) points in a right-handed frame -> the same points in its left-handed twin (y negated).
    Extra columns (intensity) pass through. Returns a new array."""
    out = np.array(points, dtype=np.float64, copy=True)
    out[:, 1] *= -1.0
    return out


def points_from_carla(points: np.ndarray) -> np.ndarray:
    """Inverse of points_to_carla (the mirror is its own inverse)."""
    return points_to_carla(points)


def box_to_carla(x: float, y: float, z: float, yaw: float, length: float, width: float, height: float
                 ) -> dict[str, list[float]]:
    """A v2vsim vehicle (footprint centre on the ground at (x, y, z), yaw, full length/width/height) -> an
    OPV2V `vehicles` entry: `location` (the vehicle's origin), `center` (box centre minus location, added in
    world axes as OpenCOOD does), `extent` (half sizes) and `angle` [roll, yaw, pitch] in degrees."""
    return {"location": [float(x), -float(y), float(z)], "center": [0.0, 0.0, float(height) / 2],
            "extent": [float(length) / 2, float(width) / 2, float(height) / 2],
            "angle": [0.0, -math.degrees(yaw), 0.0]}


def box_from_carla(vehicle: dict) -> tuple[float, float, float, float, float, float, float]:
    """An OPV2V `vehicles` entry -> v2vsim (x, y, z, yaw, length, width, height) in the world: the box centre is
    `location` + `center` (OpenCOOD adds them in world axes), z its bottom (centre z - half height)."""
    loc, ctr, ext, ang = (vehicle[k] for k in ("location", "center", "extent", "angle"))
    cx, cy, cz = (float(loc[i]) + float(ctr[i]) for i in range(3))
    hl, hw, hh = (float(v) for v in ext)
    return cx, -cy, cz - hh, -math.radians(float(ang[1])), 2 * hl, 2 * hw, 2 * hh


def world_boxes_to_body(boxes: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """(K, 5) world boxes (x, y, l, w, yaw) -> the same in the body frame of the pose (x, y, yaw); yaw wrapped
    to [-pi, pi) as v2vsim's ground-truth boxes are."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = boxes[:, 0] - x, boxes[:, 1] - y
    wrapped = (boxes[:, 4] - yaw + math.pi) % (2 * math.pi) - math.pi
    return np.stack([c * dx + s * dy, -s * dx + c * dy, boxes[:, 2], boxes[:, 3], wrapped], axis=-1)


def camera_cords(cam_to_world: np.ndarray) -> list[float]:
    """A v2vsim camera pose (OpenCV camera axes -> right-handed world, 4x4) -> OPV2V `cords`
    [x, y, z, roll, yaw, pitch] (CARLA camera axes in CARLA's world)."""
    return carla_matrix_pose(F4 @ np.asarray(cam_to_world, dtype=np.float64) @ CV_TO_UE4.T)


def camera_from_cords(cords: Sequence[float]) -> np.ndarray:
    """OPV2V `cords` -> (4, 4) OpenCV-camera-to-world transform in v2vsim's world (inverse of camera_cords)."""
    return F4 @ carla_pose_matrix(cords) @ CV_TO_UE4


def intrinsic_to_carla(k: np.ndarray) -> np.ndarray:
    """v2vsim intrinsics (pixel centres at integer coordinates: principal point (w-1)/2) -> CARLA's (pixel
    corners at integers: principal point w/2): the principal point moves by +0.5 px."""
    out = np.array(k, dtype=np.float64, copy=True)
    out[0, 2] += 0.5
    out[1, 2] += 0.5
    return out


def intrinsic_from_carla(k: Sequence[Sequence[float]]) -> np.ndarray:
    """Inverse of intrinsic_to_carla."""
    out = np.array(k, dtype=np.float64, copy=True)
    out[0, 2] -= 0.5
    out[1, 2] -= 0.5
    return out
