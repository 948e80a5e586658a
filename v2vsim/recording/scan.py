"""The recording's side channel from each CAV to the egos (control kind `scan`): a downsampled
LiDAR sweep in the world frame and, from an ego's own CAV, its four camera images as JPEG
(encoded by the CAV, so the ego's recording thread only stores them).

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
from PIL import Image

from v2vsim.config import Scenario
from v2vsim.sensors.camera import camera_rig
from v2vsim.world.geometry import Pose

MAX_POINTS = 3000  # per CAV and frame (of ~30 k): enough to see the scene, 36 KB per sweep


@dataclass(frozen=True)
class Scan:
    sender: str
    frame: int
    points: np.ndarray | None  # (N, 3) float32 world frame, N <= MAX_POINTS
    jpegs: tuple[bytes, ...] | None  # one JPEG per camera, camera_rig order (front, right, left, back)


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


JPEG_QUALITY = 85


def jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image, np.uint8)).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def encode_scan(frame: int, points: np.ndarray | None, images: np.ndarray | None) -> bytes:
    """images: (4, h, w, 3) uint8, sent as four JPEGs."""
    arrays = {}
    if points is not None:
        arrays["points"] = np.ascontiguousarray(points, np.float32)
    if images is not None:
        blobs = [jpeg(im) for im in images]
        arrays["jpeg"] = np.frombuffer(b"".join(blobs), np.uint8)
        arrays["jpeg_sizes"] = np.array([len(b) for b in blobs], np.int64)
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
    """A bound on any scan this scenario produces: points, and JPEGs no larger than the raw pixels
    (plus headers); a 4 KB allowance for the npz framing."""
    n_cams = image_shape(sc)[0]
    return MAX_POINTS * 12 + max_jpeg_bytes(sc) * n_cams + 4096


def max_jpeg_bytes(sc: Scenario) -> int:
    _, h, w, c = image_shape(sc)
    return h * w * c + 2048


def decode_scan(data: bytes, sender: str, sc: Scenario) -> Scan:
    """Raises ValueError when `data` is not a scan this scenario could produce."""
    frame = scan_frame(data)
    if frame is None:
        raise ValueError(f"scan from {sender}: no frame index")
    try:
        with np.load(io.BytesIO(data[_FRAME.size:]), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k in ("points", "jpeg", "jpeg_sizes")}
    except Exception as e:  # noqa: BLE001 - zipfile/format errors of every kind mean "not a scan"
        raise ValueError(f"scan from {sender}: not an npz archive ({type(e).__name__})") from e
    points = arrays.get("points")
    if points is not None and (points.dtype != np.float32 or points.ndim != 2 or points.shape[1] != 3
                               or len(points) > MAX_POINTS or not np.isfinite(points).all()):
        raise ValueError(f"scan from {sender}: points must be (N <= {MAX_POINTS}, 3) finite float32")
    return Scan(sender, frame, points, _jpegs(arrays, sender, sc))


def _jpegs(arrays: dict[str, np.ndarray], sender: str, sc: Scenario) -> tuple[bytes, ...] | None:
    blob, sizes = arrays.get("jpeg"), arrays.get("jpeg_sizes")
    if blob is None and sizes is None:
        return None
    n_cams = image_shape(sc)[0]
    if (blob is None or sizes is None or blob.dtype != np.uint8 or blob.ndim != 1 or sizes.dtype != np.int64
            or sizes.shape != (n_cams,) or (sizes <= 0).any() or (sizes > max_jpeg_bytes(sc)).any()
            or int(sizes.sum()) != len(blob)):
        raise ValueError(f"scan from {sender}: camera images must be {n_cams} JPEGs")
    ends = np.cumsum(sizes)
    out = tuple(blob[e - n:e].tobytes() for e, n in zip(ends, sizes, strict=True))
    if not all(b[:3] == b"\xff\xd8\xff" for b in out):
        raise ValueError(f"scan from {sender}: camera images must be {n_cams} JPEGs")
    return out
