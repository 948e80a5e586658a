"""The recording's side channel from each CAV to the egos (control kind `scan`): a downsampled
LiDAR sweep in the world frame and, from an ego's own CAV, its four camera images.

Sent only when output.rerun is on. It is review material between our own processes, never
fused or scored, so a malformed one is dropped without a count; its size is bounded by
`max_scan_bytes` before it is parsed.
"""

from __future__ import annotations

import io
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from v2vsim.config import Scenario
from v2vsim.geometry import Pose
from v2vsim.sensors.camera import camera_rig

MAX_POINTS = 4000  # per CAV and frame (of ~30 k): enough to see the scene, ~48 KB per sweep


@dataclass(frozen=True)
class Scan:
    sender: str
    frame: int
    points: np.ndarray | None  # (N, 3) float32 world frame, N <= MAX_POINTS
    images: np.ndarray | None  # (4, h, w, 3) uint8 in camera_rig order (front, right, left, back)


def world_points(points: np.ndarray, pose: Pose, lidar_height_m: float, seed: int, frame: int, cav_id: str,
                 max_points: int = MAX_POINTS) -> np.ndarray:
    """(P, >=3) LiDAR-frame points -> a reproducible random subset of at most `max_points`, as
    (N, 3) float32 world coordinates. A random subset, not a stride: a stride through the
    (azimuth, channel) order keeps whole rings and drops others."""
    if len(points) > max_points:
        rng = np.random.default_rng([seed, frame, zlib.crc32(cav_id.encode()), 7])
        points = points[np.sort(rng.choice(len(points), max_points, replace=False))]
    c, s = np.cos(pose.yaw), np.sin(pose.yaw)
    out = np.empty((len(points), 3), np.float32)
    out[:, 0] = pose.x + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = pose.y + s * points[:, 0] + c * points[:, 1]
    out[:, 2] = pose.z + lidar_height_m + points[:, 2]
    return out


_FRAME = struct.Struct("<q")  # the frame index comes first, so a receiver can file it unparsed


def encode_scan(frame: int, points: np.ndarray | None, images: np.ndarray | None) -> bytes:
    arrays = {}
    if points is not None:
        arrays["points"] = np.ascontiguousarray(points, np.float32)
    if images is not None:
        arrays["images"] = np.ascontiguousarray(images, np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return _FRAME.pack(frame) + buf.getvalue()


def scan_frame(data: bytes) -> int | None:
    try:
        return int(_FRAME.unpack_from(data)[0])
    except struct.error:
        return None


def image_shape(sc: Scenario) -> tuple[int, int, int, int]:
    rig = camera_rig(sc.sensors.cameras)
    return (len(rig.names), rig.height, rig.width, 3)


def max_scan_bytes(sc: Scenario) -> int:
    """The longest scan this scenario can produce (npz headers included)."""
    return MAX_POINTS * 12 + int(np.prod(image_shape(sc))) + 4096


def decode_scan(data: bytes, sender: str, sc: Scenario) -> Scan:
    """Raises ValueError when `data` is not a scan this scenario could produce."""
    frame = scan_frame(data)
    if frame is None:
        raise ValueError(f"scan from {sender}: no frame index")
    try:
        with np.load(io.BytesIO(data[_FRAME.size:]), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k in ("points", "images")}
    except Exception as e:  # noqa: BLE001 - zipfile/format errors of every kind mean "not a scan"
        raise ValueError(f"scan from {sender}: not an npz archive ({type(e).__name__})") from e
    points, images = arrays.get("points"), arrays.get("images")
    if points is not None and (points.dtype != np.float32 or points.ndim != 2 or points.shape[1] != 3
                               or len(points) > MAX_POINTS or not np.isfinite(points).all()):
        raise ValueError(f"scan from {sender}: points must be (N <= {MAX_POINTS}, 3) finite float32")
    if images is not None and (images.dtype != np.uint8 or images.shape != image_shape(sc)):
        raise ValueError(f"scan from {sender}: images must be uint8 {image_shape(sc)}")
    return Scan(sender, frame, points, images)
