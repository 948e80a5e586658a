"""The Recorder's output read back with rerun's own reader: entities and archetypes, frames,
boxes where the world says (signs and axes), boxes cleared, link colours, error classes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.v2vsim.recording.rrd import Recording
from v2vsim.comm.inbox import LinkEvent
from v2vsim.config import Scenario
from v2vsim.evaluation.metrics import MethodScore
from v2vsim.perception.fuse import FusionInputs, Prediction
from v2vsim.recording import bev
from v2vsim.recording.recorder import Recorder
from v2vsim.recording.scan import Scan, image_shape, jpeg
from v2vsim.recording.world3d import OUTCOME_RGB
from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, Building, StaticMap, WorldState

METHODS = ["none", "cobevt"]
STATIC = StaticMap(roads=(np.array([[-60.0, -4.0], [60.0, -4.0], [60.0, 4.0], [-60.0, 4.0]]),),
                   lane_markings=(np.array([[-60.0, 0.0], [60.0, 0.0]]),), dashed=(True,),
                   buildings=(Building("b", np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]]), 8.0),),
                   bounds=(-60.0, -20.0, 60.0, 20.0))


def _world(frame: int) -> WorldState:
    actors = (Actor("ego", "car", True, Pose(10.0, -2.0, 0.0, math.pi / 2), (4.5, 1.8, 1.5)),
              Actor("c1", "car", True, Pose(-20.0, 2.0, 0.0, math.pi), (4.0, 1.7, 1.4)),
              Actor("v7", "truck", False, Pose(30.0, -2.0, 0.0, -0.5), (8.0, 2.5, 3.2)))
    return WorldState(time=frame * 0.1, frame=frame, actors=actors, static=STATIC)


def _gt() -> dict[str, np.ndarray]:
    z = np.zeros((256, 256), bool)
    gt = {k: z.copy() for k in ("dynamic", "visible", "road", "lane")}
    gt["visible"][10:20, 10:20] = gt["dynamic"][10:20, 10:20] = True  # a visible vehicle
    gt["dynamic"][100:110, 100:110] = True  # one nobody saw
    return gt


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    sc = Scenario()
    path = tmp_path_factory.mktemp("rec") / "recording.rrd"
    rec = Recorder(path, sc, METHODS, ["ego", "c1"], "ego", STATIC)
    rng = np.random.default_rng(0)
    for k in range(3):
        p = np.zeros((256, 256), np.float32)
        p[10:20, 10:15] = 0.9  # half the visible vehicle: TP 50 cells, FN 50
        p[200:205, 200:210] = 0.8  # FP 50
        p[100:110, 100:110] = 0.7  # on the not-visible vehicle: not scored
        maps = {"vehicle": p, "road": p, "lane": p}
        boxes = np.array([[5.0, 1.0, 4.5, 1.8, 0.3, 0.9]], np.float32) if k == 0 else np.zeros((0, 6), np.float32)
        preds = {"none": Prediction(maps, None, 1.0), "cobevt": Prediction(maps, boxes, 1.0)}
        links = [LinkEvent("c1", "delivered", 12.5)] if k == 0 else [LinkEvent("c1", "dropped")]
        cams = rng.integers(0, 255, image_shape(sc), dtype=np.uint8)
        scans = {"ego": Scan("ego", k, rng.random((50, 3)).astype(np.float32), tuple(jpeg(im) for im in cams)),
                 "c1": Scan("c1", k, rng.random((40, 3)).astype(np.float32), None)}
        score = MethodScore()  # the IoU as the ego's scoring computes it, which the recording plots
        score.add_segmentation(maps, _gt())
        rec.log_frame(k, _world(k), _gt(), np.array([[5.0, 1.0, 4.5, 1.8, 0.3]]), preds,
                      FusionInputs(["ego", "c1"], np.zeros((2, 3), np.float32)), links, scans,
                      {m: score.vehicle.last_iou for m in preds})
    rec.close()
    return Recording(path)


def test_entities_and_archetypes(recording: Recording) -> None:
    expect = {
        "/world/map/roads": "Mesh3D:vertex_positions", "/world/map/buildings": "Mesh3D:vertex_normals",
        "/world/map/markings": "LineStrips3D:strips", "/world/map/ground": "Mesh3D:vertex_positions",
        "/world/vehicles": "Boxes3D:centers", "/world/cavs": "Boxes3D:labels", "/world/ego": "Boxes3D:quaternions",
        "/world/lidar/ego": "Points3D:positions", "/world/lidar/c1": "Points3D:positions",
        "/world/links": "LineStrips3D:colors", "/world/bev_extent": "LineStrips3D:strips",
        "/world/ego_cameras/front": "EncodedImage:blob", "/world/ego_cameras/back": "Transform3D:mat3x3",
        "/bev/gt/classes": "SegmentationImage:buffer", "/bev/gt/boxes": "LineStrips2D:strips",
        "/bev/cobevt/probability": "EncodedImage:blob", "/bev/cobevt/errors": "SegmentationImage:buffer",
        "/bev/none/boxes": "LineStrips2D:strips", "/metrics/iou_vehicle/cobevt": "Scalars:scalars",
        "/links/delivered/c1": "Scalars:scalars", "/links/latency_ms/c1": "Scalars:scalars",
        "/log/fusion": "TextLog:text",
    }
    for entity, column in expect.items():
        assert column in recording.columns(entity), (entity, recording.columns(entity))
    assert recording.static("/world/ego_cameras/left", "Pinhole:image_from_camera")
    assert recording.static("/world", "ViewCoordinates:xyz")
    assert list(recording.rows("/world/ego", "Boxes3D:centers")) == [0, 1, 2]


def test_boxes_stand_where_the_world_says(recording: Recording) -> None:
    world = _world(1)
    for entity, ids in (("/world/ego", ["ego"]), ("/world/cavs", ["c1"]), ("/world/vehicles", ["v7"])):
        centres = recording.rows(entity, "Boxes3D:centers")[1]
        halves = recording.rows(entity, "Boxes3D:half_sizes")[1]
        quats = recording.rows(entity, "Boxes3D:quaternions")[1]
        for a_id, c, h, q in zip(ids, centres, halves, quats, strict=True):
            a = world.actor(a_id)
            assert c == pytest.approx([a.pose.x, a.pose.y, a.extent[2] / 2], abs=1e-4)  # standing on z = 0
            assert h == pytest.approx([e / 2 for e in a.extent], abs=1e-5)
            x, y, z, w = q  # the box's +x (its heading) rotated by q must point along yaw, counter-clockwise
            heading = [1 - 2 * (y * y + z * z), 2 * (x * y + w * z)]
            assert heading == pytest.approx([math.cos(a.pose.yaw), math.sin(a.pose.yaw)], abs=1e-5)


def test_boxes_are_cleared_on_frames_without_detections(recording: Recording) -> None:
    strips = recording.rows("/bev/cobevt/boxes", "LineStrips2D:strips")
    assert len(strips[0]) == 1 and len(strips[0][0]) == 5  # a closed outline
    assert strips[1] == [] and strips[2] == []  # logged empty, not left over from frame 0
    assert all(v == [] for v in recording.rows("/bev/none/boxes", "LineStrips2D:strips").values())


def test_links_are_coloured_by_what_the_channel_did(recording: Recording) -> None:
    def rgba(rgb: tuple[int, int, int]) -> int:
        return (rgb[0] << 24) | (rgb[1] << 16) | (rgb[2] << 8) | 0xFF

    colours = recording.rows("/world/links", "LineStrips3D:colors")
    assert colours[0] == [rgba(OUTCOME_RGB["delivered"])] and colours[1] == [rgba(OUTCOME_RGB["dropped"])]
    strip = recording.rows("/world/links", "LineStrips3D:strips")[0][0]
    assert strip[0][:2] == pytest.approx([-20.0, 2.0]) and strip[1][:2] == pytest.approx([10.0, -2.0])  # c1 -> ego
    assert recording.rows("/links/latency_ms/c1", "Scalars:scalars") == {0: [12.5]}
    assert recording.rows("/links/delivered/c1", "Scalars:scalars") == {0: [1.0], 1: [0.5], 2: [1 / 3]}


def test_error_image_and_iou_agree_with_scoring(recording: Recording) -> None:
    buf = np.asarray(recording.rows("/bev/cobevt/errors", "SegmentationImage:buffer")[0], np.uint8).ravel()
    assert buf.size == 256 * 256
    counts = np.bincount(buf, minlength=8)
    assert (counts[bev.TP], counts[bev.FP], counts[bev.FN]) == (50, 50, 50)
    assert counts[bev.HIDDEN_PREDICTED] == 100 and counts[bev.HIDDEN] == 0
    assert recording.rows("/metrics/iou_vehicle/cobevt", "Scalars:scalars")[0] == pytest.approx([50 / 150])


def test_probability_is_a_colour_map_not_a_mask() -> None:
    img = bev.probability_image(np.array([[0.0, 0.25, 0.5, 1.0]], np.float32))
    brightness = img.astype(int).sum(axis=-1)[0]
    assert (np.diff(brightness) > 0).all() and len({tuple(c) for c in img[0]}) == 4


def test_box_strips_match_geometry_corners() -> None:
    from v2vsim.world.geometry import BevGrid, box_corners

    grid = BevGrid()
    b = np.array([[10.0, -5.0, 4.5, 1.8, 0.7]])
    c = box_corners(10.0, -5.0, 0.7, 4.5, 1.8)
    expect = grid.xy_to_rc(np.vstack([c, c[:1]]))[:, ::-1]
    assert bev.box_strips(grid, b)[0] == pytest.approx(expect, abs=1e-4)
    assert bev.box_strips(grid, np.zeros((0, 6))).shape == (0, 5, 2)


def test_recording_stays_small(recording: Recording, tmp_path: Path) -> None:
    # few chunks: one per entity and component set, not one per row
    frames = [c for c in recording.chunks if not c.is_static and c.entity_path == "/world/lidar/ego"]
    assert len(frames) == 1 and frames[0].num_rows == 3
