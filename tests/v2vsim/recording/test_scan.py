"""The recording's side channel: LiDAR points into the world frame, encode/decode, bounds."""

from __future__ import annotations

import io
import math
import struct

import numpy as np
import pytest
from PIL import Image

from v2vsim.config import Scenario
from v2vsim.recording.scan import MAX_POINTS, decode_scan, encode_scan, image_shape, max_scan_bytes, world_points
from v2vsim.world.geometry import Pose


def test_points_go_to_the_world_frame_with_the_sensor_height() -> None:
    # LiDAR frame: x forward, y left, z up from the sensor; the CAV faces north (yaw +90 deg)
    pts = np.array([[1.0, 0.0, 0.0, 0.5], [0.0, 2.0, -1.9, 0.5]], np.float32)
    out = world_points(pts, Pose(10.0, 20.0, 0.5, math.pi / 2), 1.9, 0, 0, "c")
    assert out == pytest.approx(np.array([[10.0, 21.0, 2.4], [8.0, 20.0, 0.5]]), abs=1e-5)


def test_points_are_a_reproducible_subset() -> None:
    pts = np.random.default_rng(0).random((3 * MAX_POINTS, 4)).astype(np.float32)
    a = world_points(pts, Pose(0, 0, 0, 0), 1.9, 5, 3, "c")
    assert a.shape == (MAX_POINTS, 3) and np.array_equal(a, world_points(pts, Pose(0, 0, 0, 0), 1.9, 5, 3, "c"))
    assert not np.array_equal(a, world_points(pts, Pose(0, 0, 0, 0), 1.9, 5, 4, "c"))


def test_round_trip_and_size_bound() -> None:
    sc = Scenario()
    pts = np.random.default_rng(1).random((MAX_POINTS, 3)).astype(np.float32)
    imgs = np.zeros(image_shape(sc), np.uint8)
    data = encode_scan(7, pts, imgs)
    assert len(data) <= max_scan_bytes(sc)
    scan = decode_scan(data, "c1", sc)
    assert scan.frame == 7 and scan.sender == "c1" and np.array_equal(scan.points, pts)
    assert len(scan.jpegs) == 4 and all(Image.open(io.BytesIO(j)).size == imgs.shape[2:0:-1] for j in scan.jpegs)
    only = decode_scan(encode_scan(8, None, None), "c1", sc)
    assert only.points is None and only.jpegs is None


def _npz(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.parametrize("bad", [
    b"", b"\x01\x00\x00\x00\x00\x00\x00\x00not an npz",
    encode_scan(1, np.zeros((MAX_POINTS + 1, 3), np.float32), None),
    struct.pack("<q", 1) + _npz(points=np.zeros((5, 3), np.float64)),  # encode_scan would cast it
    encode_scan(1, np.full((5, 3), np.nan, np.float32), None),
    encode_scan(1, None, np.zeros((3, 10, 10, 3), np.uint8)),  # three cameras, not four
    struct.pack("<q", 1) + _npz(jpeg=np.zeros(40, np.uint8), jpeg_sizes=np.full(4, 10, np.int64)),  # not JPEG
    struct.pack("<q", 1) + _npz(jpeg=np.zeros(40, np.uint8), jpeg_sizes=np.array([10, 10, 10, 11])),  # sizes
    struct.pack("<q", 1) + _npz(jpeg=np.zeros(40, np.uint8)),  # no sizes
])
def test_malformed_scans_are_refused(bad: bytes) -> None:
    with pytest.raises(ValueError, match="scan from c1"):
        decode_scan(bad, "c1", Scenario())
