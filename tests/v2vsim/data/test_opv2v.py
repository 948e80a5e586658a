"""OPV2V format both ways: v2vsim -> OPV2V -> v2vsim gives the same samples, and a hand-written OPV2V sample
(OpenCOOD's documented field names, CARLA's left-handed frames) reads into v2vsim's frames and units."""

from __future__ import annotations

import io
import math
import struct

import numpy as np
import pytest
import torch
import yaml
from PIL import Image, ImageDraw

from v2vsim.cli import main
from v2vsim.data.carla_frames import (
    box_from_carla,
    box_to_carla,
    camera_cords,
    camera_from_cords,
    carla_angles,
    carla_rotation,
    pose_from_carla,
    pose_to_carla,
)
from v2vsim.data.layout import DatasetError, frame_path
from v2vsim.data.opv2v_read import OPV2VStore
from v2vsim.data.opv2v_write import export_opv2v
from v2vsim.data.pcd import read_pcd, write_pcd
from v2vsim.data.torch_dataset import CooperativeDataset, open_store

RUN = "intersection_s700"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """`v2vsim dataset --format opv2v`: 3 frames, 2 CAVs, cameras. Then one vehicle of frame 1 is made unseen by
    every CAV in the v2vsim recording (so hidden boxes cross too) and the run is exported again."""
    out = tmp_path_factory.mktemp("opv2v") / "ds"
    argv = ["dataset", "scenarios/intersection.yaml", "--seeds", "700", "--frames", "3", "--out", str(out),
            "--format", "opv2v", "--cameras", "--set", "cavs.count=2"]
    assert main(argv) == 0
    native = out / "v2vsim"
    path = frame_path(native / RUN, 1)
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    cavs = [str(c) for c in arrays["cavs"]]
    target = next(str(b) for c in cavs for b in arrays[f"boxids_{c}"] if not str(b).startswith("cav"))
    for c in cavs:
        arrays[f"seen_{c}"] = np.array([s for s in arrays[f"seen_{c}"] if str(s) != target], dtype=str)
        arrays[f"boxvis_{c}"] = np.array([str(b) != target for b in arrays[f"boxids_{c}"]], dtype=bool)
    np.savez_compressed(path, **arrays)
    (out / "train" / RUN / "data_protocol.yaml").unlink()  # a partial export: written again
    export_opv2v(native, out, log=io.StringIO())
    return out, target


def _sorted_boxes(boxes: torch.Tensor) -> np.ndarray:
    b = boxes.numpy().astype(np.float64)
    return b[np.lexsort(b.T[::-1])] if len(b) else b


def test_v2vsim_to_opv2v_to_v2vsim_gives_the_same_samples(exported) -> None:
    out, target = exported
    scen = out / "train" / RUN
    assert (scen / "data_protocol.yaml").is_file()
    cav_dirs = sorted(p.name for p in scen.iterdir() if p.is_dir())
    assert len(cav_dirs) == 2 and all(d.lstrip("-").isdigit() for d in cav_dirs)
    for name in ("000001.pcd", "000001.yaml", "000001_camera3.png", "000001_bev_dynamic.png",
                 "000001_bev_static.png", "000001_bev_lane.png", "000001_bev_visibility.png",
                 "000001_bev_visibility_corp.png"):
        assert (scen / cav_dirs[0] / name).is_file(), name
    assert isinstance(open_store(out), OPV2VStore)

    kw = dict(max_agents=4, with_images=True, delays=(1,))
    native = CooperativeDataset(out / "v2vsim", "train", **kw)
    back = CooperativeDataset(out, "train", **kw)
    assert len(native) == len(back) == 6
    hidden = 0
    for i in range(len(native)):
        a, b = native[i], back[i]
        assert (a["key"].frame, a["key"].ego) == (b["key"].frame, b["key"].ego)
        assert a["agents"] == b["agents"] and a["agent_frames"] == b["agent_frames"]
        for pa, pb in zip(a["points"], b["points"], strict=True):
            assert pa.shape == pb.shape and torch.allclose(pa, pb, atol=1e-5)
        assert torch.allclose(a["rel_poses"], b["rel_poses"], atol=1e-5)
        for k in ("vehicle", "dynamic", "visible_self", "road", "lane"):
            assert torch.equal(a[k], b[k]), k
        for k in ("boxes", "boxes_hidden", "boxes_self", "boxes_self_hidden"):
            assert a[k].shape == b[k].shape, k
            assert np.allclose(_sorted_boxes(a[k]), _sorted_boxes(b[k]), atol=1e-4), k
        hidden += len(b["boxes_hidden"])
        for ia, ib in zip(a["images"], b["images"], strict=True):
            assert torch.equal(ia, ib)
        for k in ("intrinsics", "extrinsics"):
            for ma, mb in zip(a[k], b[k], strict=True):
                assert torch.allclose(ma, mb, atol=1e-5), k
    assert hidden > 0, f"{target} (unseen in frame 1) should be a hidden box on some grid"


def test_an_export_lists_in_vehicles_only_what_the_cav_saw(exported) -> None:
    """OPV2V's `vehicles`: the vehicles the CAV's LiDAR hit, never itself; the frame-1 vehicle nobody saw is
    only under our own `v2vsim` key, which OpenCOOD does not read."""
    out, target = exported
    scen = out / "train" / RUN
    proto = yaml.safe_load((scen / "data_protocol.yaml").read_text())["v2vsim"]
    ids = {str(v): int(k) for k, v in proto["actor_ids"].items()}
    for d in (p for p in scen.iterdir() if p.is_dir()):
        doc = yaml.safe_load((d / "000001.yaml").read_text())
        assert int(d.name) not in doc["vehicles"] and ids[target] not in doc["vehicles"]
        for key in ("lidar_pose", "true_ego_pos", "predicted_ego_pos"):
            assert len(doc[key]) == 6
        assert doc["lidar_pose"][2] == pytest.approx(doc["true_ego_pos"][2] + 1.9)
    assert any(ids[target] in yaml.safe_load((d / "000001.yaml").read_text())["v2vsim"]["unseen_vehicles"]
               for d in scen.iterdir() if d.is_dir())


def test_an_opv2v_out_folder_must_be_new_or_ours(tmp_path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    argv = ["dataset", "scenarios/intersection.yaml", "--seeds", "700", "--frames", "1", "--out", str(tmp_path),
            "--format", "opv2v"]
    assert main(argv) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


# ------------------------------------------------------------------ a hand-written OPV2V sample

PPM = 256 / 100.0  # OPV2V / CoBEVT BEV maps: 256 px over 100 m


def _packed_red(r: int) -> str:
    """PCL/Open3D `rgb`: the bits 0x00RRGGBB read as a float32, printed as Open3D's ASCII writer does."""
    return f"{struct.unpack('<f', struct.pack('<I', r << 16))[0]:.10g}"


def _pcd_text(rows: list[tuple[float, float, float, int]]) -> str:
    head = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\n"
            f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {len(rows)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {len(rows)}\nDATA ascii\n")
    return head + "".join(f"{x} {y} {z} {_packed_red(r)}\n" for x, y, z, r in rows)


def _vehicle(x: float, y: float, yaw_deg: float, half=(2.0, 1.0, 0.75)) -> dict:
    return {"location": [x, y, 0.0], "center": [0.0, 0.0, half[2]], "extent": list(half),
            "angle": [0.0, yaw_deg, 0.0], "speed": 20.0}


def _camera(cords: list[float]) -> dict:
    return {"cords": cords, "extrinsic": np.eye(4).tolist(),
            "intrinsic": [[335.64, 0.0, 400.0], [0.0, 335.64, 300.0], [0.0, 0.0, 1.0]]}


def _opv2v_raster(corners_ego_carla: np.ndarray) -> list[tuple[float, float]]:
    """OPV2V's BEV drawing rule (logreplay map_manager): image x (column) = y * ppm + 128,
    image y (row) = -x * ppm + 128, with (x, y) in the ego's CARLA frame (x forward, y right)."""
    return [(float(y) * PPM + 128, -float(x) * PPM + 128) for x, y in corners_ego_carla]


@pytest.fixture
def hand_written(tmp_path):
    """train/2021_08_22_21_41_24/{1732,1741}/000068.*: CAV 1732 at the CARLA origin heading +x (east), CAV 1741
    at (20, 5) heading yaw 90 (CARLA: clockwise, i.e. south); vehicle 500 at CARLA (10, 5), yaw 30 deg."""
    scen = tmp_path / "train" / "2021_08_22_21_41_24"
    a, b = scen / "1732", scen / "1741"
    a.mkdir(parents=True)
    b.mkdir()
    (scen / "data_protocol.yaml").write_text("world:\n  sync_mode: true\n  fixed_delta_seconds: 0.05\n  seed: 11\n")
    cam_a = {f"camera{i}": _camera([1.5, 0.0, 1.6, 0.0, yaw, 0.0]) for i, yaw in enumerate((0.0, 90.0, -90.0, 180.0))}
    doc_a = {"lidar_pose": [0.0, 0.0, 1.9, 0.0, 0.0, 0.0], "true_ego_pos": [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
             "predicted_ego_pos": [0.1, 0.0, 0.0, 0.0, 0.0, 0.0], "ego_speed": 18.0, **cam_a,
             "vehicles": {500: _vehicle(10.0, 5.0, 30.0)}}
    doc_b = {"lidar_pose": [20.0, 5.0, 1.9, 0.0, 90.0, 0.0], "true_ego_pos": [20.0, 5.0, 0.0, 0.0, 90.0, 0.0],
             "predicted_ego_pos": [20.0, 5.0, 0.0, 0.0, 90.0, 0.0], "ego_speed": 10.0, **cam_a,
             "vehicles": {500: _vehicle(10.0, 5.0, 30.0), 1732: _vehicle(0.0, 0.0, 0.0)}}
    (a / "000068.yaml").write_text(yaml.safe_dump(doc_a))
    (b / "000068.yaml").write_text(yaml.safe_dump(doc_b))
    # LiDAR frames, CARLA axes: CAV 1732 sees a point 5 m ahead, 2 m to its right, on the ground (1.9 m below it)
    (a / "000068.pcd").write_text(_pcd_text([(5.0, 2.0, -1.9, 128), (0.0, 0.0, 0.0, 255)]))
    (b / "000068.pcd").write_text(_pcd_text([(1.0, 0.0, 0.0, 0)]))
    for d in (a, b):
        for i in range(4):
            Image.fromarray(np.full((6, 8, 3), (40 * i, 100, 200), dtype=np.uint8)).save(d / f"000068_camera{i}.png")
        lane = np.zeros((256, 256), dtype=np.uint8)
        lane[:, 120:124] = 255
        Image.fromarray(np.full((256, 256), 255, dtype=np.uint8)).save(d / "000068_bev_static.png")
        Image.fromarray(lane).save(d / "000068_bev_lane.png")
    # CAV 1732's dynamic map, drawn by OPV2V's rule: vehicle 500 in 1732's CARLA frame is at (10, 5), yaw 30 deg.
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    local = np.array([[2.0, 1.0], [2.0, -1.0], [-2.0, -1.0], [-2.0, 1.0]])
    corners = local @ np.array([[c, -s], [s, c]]).T + [10.0, 5.0]
    dyn = Image.new("L", (256, 256), 0)
    ImageDraw.Draw(dyn).polygon(_opv2v_raster(corners), fill=255)
    dyn.save(a / "000068_bev_dynamic.png")
    Image.new("L", (256, 256), 0).save(b / "000068_bev_dynamic.png")
    return tmp_path


def test_carla_conventions_on_a_hand_computed_case() -> None:
    """CARLA (10, 5), yaw 30 deg (clockwise, y to the south) is v2vsim (10, -5), yaw -30 deg in radians."""
    assert pose_from_carla([10.0, 5.0, 0.3, 0.0, 30.0, 0.0]) == pytest.approx((10.0, -5.0, 0.3, -math.pi / 6))
    assert pose_to_carla(10.0, -5.0, 0.3, -math.pi / 6) == pytest.approx([10.0, 5.0, 0.3, 0.0, 30.0, 0.0])
    x, y, z, yaw, length, width, height = box_from_carla(_vehicle(10.0, 5.0, 30.0))
    assert (x, y, z, yaw, length, width, height) == pytest.approx((10.0, -5.0, 0.0, -math.pi / 6, 4.0, 2.0, 1.5))
    assert box_from_carla(box_to_carla(x, y, z, yaw, length, width, height)) == pytest.approx((x, y, z, yaw, 4, 2, 1.5))
    # CARLA yaw 90 turns +x onto +y (south); pitch 10 lifts the nose (+z); angles come back
    assert carla_rotation(0, 90, 0) @ [1, 0, 0] == pytest.approx([0, 1, 0], abs=1e-12)
    assert carla_rotation(0, 0, 10)[2, 0] == pytest.approx(math.sin(math.radians(10)))
    assert carla_angles(carla_rotation(3.0, -40.0, 7.0)) == pytest.approx((3.0, -40.0, 7.0))
    cam = camera_from_cords([1.0, 2.0, 1.5, 0.0, 90.0, 0.0])  # OpenCV camera -> v2vsim world
    assert cam[:3, 2] == pytest.approx([0, -1, 0], abs=1e-12)  # optical axis: CARLA +y (south) = v2vsim -y
    assert cam[:3, 3] == pytest.approx([1.0, -2.0, 1.5])
    assert camera_cords(cam) == pytest.approx([1.0, 2.0, 1.5, 0.0, 90.0, 0.0], abs=1e-9)


def test_a_hand_written_opv2v_sample_reads_into_v2vsim_frames(hand_written) -> None:
    ds = CooperativeDataset(hand_written, "train", max_agents=5, with_images=True)
    assert [(k.frame, k.ego) for k in ds.items] == [(0, "1732"), (0, "1741")]
    s = ds[0]
    assert s["agents"] == ["1732", "1741"]
    # CAV 1741: CARLA (20, 5) heading yaw 90 = v2vsim (20, -5) heading -pi/2, seen from 1732 at the origin
    assert s["rel_poses"][1].numpy() == pytest.approx([20.0, -5.0, -math.pi / 2], abs=1e-6)
    # points in the body frame (z from the ground): CARLA (5, 2, -1.9) below a 1.9 m LiDAR -> (5, -2, 0);
    # intensity from the red channel of `rgb`
    assert s["points"][0].numpy() == pytest.approx(np.array([[5.0, -2.0, 0.0, 128 / 255], [0, 0, 1.9, 1.0]]),
                                                   abs=1e-6)
    # 1 m ahead of 1741's LiDAR is 1 m ahead in its body frame, whatever its heading
    assert s["points"][1].numpy() == pytest.approx(np.array([[1.0, 0.0, 1.9, 0.0]]), abs=1e-6)
    # vehicle 500: v2vsim (10, -5), yaw -30 deg, 4 x 2 m (extent is half sizes); listed by 1732: visible, own
    assert s["boxes"].numpy() == pytest.approx(np.array([[10.0, -5.0, 4.0, 2.0, -math.pi / 6]]), abs=1e-5)
    assert len(s["boxes_hidden"]) == 0 and len(s["boxes_self"]) == 1
    # masks: the PNGs as drawn (same orientation as v2vsim's grid: row 0 ahead, column 0 to the left) ...
    assert s["road"].all() and s["lane"][:, 120:124].all() and s["lane"].sum() == 256 * 4
    dyn = s["dynamic"].numpy()
    assert dyn[102, 140] and not dyn[102, 115]  # (10 m ahead, 5 m right): row 128 - 25.6, column 128 + 12.8
    # ... and the visible masks, absent here, derived from the `vehicles` lists: they land on the same cells
    # (1741 lists 1732, so the ego's own footprint is there too: compare ahead of it, rows above 118)
    vis = s["vehicle"].numpy()
    assert vis[128, 128] and (vis[:118] & dyn[:118]).sum() / (vis[:118] | dyn[:118]).sum() > 0.8
    assert torch.equal(s["vehicle"], s["visible_self"])
    # seen from 1741 (heading south): vehicle 500 is 10 m to its right, turned +60 deg; 1732 listed by 1741
    t = ds[1]
    boxes = {tuple(np.round(b, 4)) for b in t["boxes"].numpy().tolist()}
    assert boxes == {(0.0, -10.0, 4.0, 2.0, round(math.pi / 3, 4)), (-5.0, -20.0, 4.0, 2.0, round(math.pi / 2, 4))}
    # cameras: OpenCV axes to the body; camera0 looks ahead from (1.5, 0, 1.6), camera1 (CARLA yaw +90) right
    ext, intr = s["extrinsics"][0].numpy(), s["intrinsics"][0].numpy()
    assert ext[0, :3, 3] == pytest.approx([1.5, 0.0, 1.6], abs=1e-6)
    assert ext[0, :3, 2] == pytest.approx([1, 0, 0], abs=1e-6) and ext[0, :3, 1] == pytest.approx([0, 0, -1], abs=1e-6)
    assert ext[1, :3, 2] == pytest.approx([0, -1, 0], abs=1e-6)
    assert intr[0, 0, 2] == pytest.approx(399.5) and intr[0, 1, 2] == pytest.approx(299.5)
    assert s["images"][0].shape == (4, 3, 6, 8) and s["images"][0][2, :, 0, 0].tolist() == [80, 100, 200]


def test_opv2v_without_bev_maps_is_refused_with_what_is_missing(hand_written) -> None:
    for p in hand_written.glob("train/*/*/*_bev_static.png"):
        p.unlink()
    with pytest.raises(DatasetError, match=r"bev_static\.png.*road"):
        CooperativeDataset(hand_written, "train")
    assert len(open_store(hand_written).keys("train")) == 2  # the sensor data alone still reads (feature cache)


def test_pcd_round_trip_binary_and_ascii(tmp_path) -> None:
    pts = np.random.default_rng(1).normal(size=(50, 4)).astype(np.float32)
    pts[:, 3] = np.abs(pts[:, 3]) % 1
    for binary in (True, False):
        write_pcd(tmp_path / "a.pcd", pts, binary=binary)
        assert np.array_equal(read_pcd(tmp_path / "a.pcd"), pts)
