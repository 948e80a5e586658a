"""Metrics: AP under both detection sortings (hand-computed), neighbour counting and shares,
and what metrics.json / report.md say about them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from v2vsim.comm.stats import CommStats
from v2vsim.config import ConfigError, scenario_from_dict
from v2vsim.evaluation.metrics import ApAccumulator, MethodScore, cavs_in_range, neighbour_shares
from v2vsim.evaluation.metrics_doc import metrics_json
from v2vsim.evaluation.report_md import report_md
from v2vsim.evaluation.run_summary import RunSummary
from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, StaticMap, WorldState


def _centre_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """1 where two boxes share a centre, else 0: matching is then exact and easy to follow by hand."""
    return (np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=-1) < 0.5).astype(float)


def _box(x: float) -> list[float]:
    return [x, 0.0, 4.5, 1.9, 0.0]


def _two_frames(sort: str) -> ApAccumulator:
    """Frame 1: ground truth g1, detection a (0.3) on it. Frame 2: ground truth g2, detections
    b (0.9, on nothing) and c (0.8, on g2)."""
    acc = ApAccumulator(sort=sort)
    acc.add(np.array([_box(0.0)]), np.array([0.3]), np.array([_box(0.0)]))
    acc.add(np.array([_box(50.0), _box(10.0)]), np.array([0.9, 0.8]), np.array([_box(10.0)]))
    return acc


def test_ap_global_and_per_frame_sorting_differ_as_computed_by_hand() -> None:
    # global: b FP, c TP, a TP -> recall 0, 1/2, 1 at precision 0, 1/2, 2/3; the envelope is 2/3
    # on both recall steps: AP = 1/2 * 2/3 + 1/2 * 2/3 = 2/3.
    assert _two_frames("global").ap(0.5, _centre_iou) == pytest.approx(2 / 3)
    # per frame (frame order, each frame by score): a TP, b FP, c TP -> recall 1/2, 1/2, 1 at
    # precision 1, 1/2, 2/3: AP = 1/2 * 1 + 1/2 * 2/3 = 5/6.
    assert _two_frames("per_frame").ap(0.5, _centre_iou) == pytest.approx(5 / 6)
    # within a frame the order is by score even if the detector hands them over unsorted
    acc = ApAccumulator(sort="per_frame")
    acc.add(np.array([_box(0.0)]), np.array([0.3]), np.array([_box(0.0)]))
    acc.add(np.array([_box(10.0), _box(50.0)]), np.array([0.8, 0.9]), np.array([_box(10.0)]))
    assert acc.ap(0.5, _centre_iou) == pytest.approx(5 / 6)


def test_several_thresholds_at_once_equal_each_alone_and_compute_each_iou_matrix_once() -> None:
    rng = np.random.default_rng(0)
    acc = ApAccumulator()
    for _ in range(6):
        n, g = int(rng.integers(0, 6)), int(rng.integers(0, 4))
        acc.add(np.array([_box(float(x)) for x in rng.uniform(0, 30, n)]).reshape(-1, 5), rng.uniform(size=n),
                np.array([_box(float(x)) for x in rng.uniform(0, 30, g)]).reshape(-1, 5))
    calls = []

    def soft_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        calls.append(1)
        return np.exp(-np.abs(a[:, None, 0] - b[None, :, 0]))

    both = acc.aps((0.5, 0.7), soft_iou)
    assert len(calls) == sum(len(d) > 0 and len(g) > 0 for d, _, g in acc.frames)
    assert both == [acc.ap(0.5, soft_iou), acc.ap(0.7, soft_iou)] and both[0] >= both[1]


def test_ap_sortings_agree_when_frame_order_is_score_order() -> None:
    acc = {s: ApAccumulator(sort=s) for s in ("global", "per_frame")}
    for a in acc.values():
        a.add(np.array([_box(0.0), _box(30.0)]), np.array([0.9, 0.7]), np.array([_box(0.0)]))
        a.add(np.array([_box(10.0)]), np.array([0.5]), np.array([_box(10.0), _box(20.0)]))
    assert acc["global"].ap(0.5, _centre_iou) == pytest.approx(acc["per_frame"].ap(0.5, _centre_iou))
    with pytest.raises(ValueError, match="per_frame"):
        ApAccumulator(sort="by_score")


def _world(*actors: tuple[str, bool, float, float]) -> WorldState:
    static = StaticMap(roads=(), lane_markings=(), dashed=())
    return WorldState(time=0.0, frame=0, static=static, actors=tuple(
        Actor(id=i, kind="car", cav=cav, pose=Pose(x, y, 0.0, 0.3), extent=(4.5, 1.9, 1.5))
        for i, cav, x, y in actors))


def test_cavs_in_range_counts_other_cavs_by_centre_distance() -> None:
    w = _world(("cav0", True, 10.0, 5.0), ("cav1", True, 10.0, 75.0),  # 70 m: on the edge counts
               ("cav2", True, 80.0, 5.01 + 1.0), ("cav3", True, -20.0, 5.0),  # 70.007 m: out; 30 m: in
               ("veh0", False, 11.0, 5.0))  # background vehicles are not neighbours
    assert cavs_in_range(w, "cav0", 70.0) == 2
    assert cavs_in_range(w, "cav3", 70.0) == 1  # cav0 only (cav1 at 76 m, cav2 at 100 m)
    assert cavs_in_range(w, "cav9", 70.0) is None


def test_neighbour_shares_sum_to_one_and_cover_every_count() -> None:
    shares = neighbour_shares([0, 1, 2, 2, 3, 3, 3, 3], cavs=4)
    assert shares == {"0": 0.125, "1": 0.125, "2": 0.25, "3": 0.5}
    assert sum(shares.values()) == pytest.approx(1.0)
    assert neighbour_shares([1, 1, 1], cavs=5) == {"0": 0.0, "1": 1.0, "2": 0.0, "3": 0.0, "4": 0.0}
    assert neighbour_shares([], cavs=4) == {}
    thirds = neighbour_shares([0, 1, 2], cavs=3)
    assert sum(thirds.values()) == pytest.approx(1.0, abs=1e-3)


def _summary(ap_sort: str | None = None, modality: str = "lidar", rerun: bool = True) -> RunSummary:
    raw = {"traffic": {"backend": "highway-env"}, "cavs": {"count": 4}, "output": {"rerun": rerun}}
    if modality == "camera":
        raw["perception"] = {"modality": "camera", "encoder": "sinbevt"}
    if ap_sort is not None:
        raw["evaluation"] = {"ap_sort": ap_sort}
    sc = scenario_from_dict(raw)
    return RunSummary(scenario=sc, ego="cav0", methods=["none"], untrained=True, frames=4, wall_s=1.0,
                      neighbours=[0, 2, 3, 3])


def test_metrics_json_and_report_carry_neighbour_shares_and_ap_sort() -> None:
    scores = {"none": MethodScore(boxes=_two_frames("per_frame"))}
    summary = _summary("per_frame", rerun=False)
    doc = metrics_json(summary, scores, CommStats(), {}, _centre_iou)
    assert doc["neighbours_in_range"] == {"0": 0.25, "1": 0.0, "2": 0.25, "3": 0.5}
    assert sum(doc["neighbours_in_range"].values()) == pytest.approx(1.0)
    assert doc["ap_sort"] == "per_frame"
    assert doc["methods"]["none"]["ap50"] == pytest.approx(5 / 6, abs=1e-4)
    md = report_md(doc, summary)
    assert "within each frame" in md and "per_frame" in md
    assert "| CAVs in range | 0 | 1 | 2 | 3 |" in md and "| share of frames | 25.0 % | 0.0 % | 25.0 % | 50.0 % |" in md
    assert "at least two in 75.0 %" in md
    default = _summary()
    assert default.scenario.evaluation.ap_sort == "global"
    default_md = report_md(metrics_json(default, {}, CommStats(), {}, None), default)
    assert "sorted over the whole run" in default_md
    # the report points at the recording only where the run wrote one
    assert "Recording: `recording.rrd`" in default_md and "No recording" in md


def test_ap_sort_is_checked_in_the_scenario() -> None:
    with pytest.raises(ConfigError, match=r"evaluation\.ap_sort.*'global' \| 'per_frame'"):
        scenario_from_dict({"traffic": {"backend": "highway-env"}, "evaluation": {"ap_sort": "perframe"}})


def test_per_frame_vehicle_counts_add_up_to_the_dataset_iou() -> None:
    s = MethodScore()
    z = np.zeros((4, 4), bool)
    for hit in (2, 0, 1):  # frame 1: nothing predicted, nothing there (union 0)
        gt = {"dynamic": z.copy(), "visible": z.copy(), "road": z, "lane": z}
        p = np.zeros((4, 4), np.float32)
        if hit:
            gt["visible"][0, :2] = gt["dynamic"][0, :2] = True
            p[0, :hit] = 0.9
        s.add_segmentation({"vehicle": p}, gt)
    j = s.to_json(None)
    assert j["iou_vehicle_counts"] == [[2, 2], [0, 0], [1, 2]]
    i, u = np.sum(j["iou_vehicle_counts"], axis=0)
    assert j["iou_vehicle"] == pytest.approx(i / u) and j["iou_vehicle_frame_mean"] == pytest.approx(0.75)


def test_report_and_plot_of_link_states_under_tr37885(tmp_path) -> None:
    from v2vsim.comm.channel import Delivery
    from v2vsim.evaluation.run_plots import plot

    comm = CommStats()
    comm.track_link_states()
    for state, dist, ok in [("los", 10, True), ("los", 30, True), ("los", 30, False), ("nlos", 60, False)]:
        comm.record_channel(Delivery(ok, "ok" if ok else "dropped", 0.1 if ok else math.inf, 0.0, state=state), dist)
    summary = _summary()
    scores = {"none": MethodScore()}
    doc = metrics_json(summary, scores, comm, {}, None)
    assert (doc["comm"]["los"], doc["comm"]["nlos"], doc["comm"]["nlosv"]) == (3, 1, 0)
    md = report_md(doc, summary)
    assert "| link state | 0-25 m | 25-50 m | 50-75 m |" in md
    assert "| los | 1.00 (1) | 0.50 (2) | - |" in md and "| nlos | - | - | 0.00 (1) |" in md
    assert "`delivery_by_distance.png`" in md
    assert (tmp_path / "delivery_by_distance.png") in plot(tmp_path, doc, scores)
    plain = metrics_json(summary, scores, CommStats(), {}, None)
    assert "los" not in plain["comm"] and "link state" not in report_md(plain, summary)


def test_camera_report_puts_the_run_beside_the_papers_camera_table() -> None:
    summary = _summary(modality="camera")
    doc = metrics_json(summary, {"none": MethodScore(boxes=_two_frames("global"))}, CommStats(), {}, _centre_iou)
    doc["methods"]["none"].update(iou_vehicle=0.25, iou_road=0.5, iou_lane=0.125)
    md = report_md(doc, summary)
    assert "Beside the CoBEVT paper's camera table" in md and "different dataset" in md
    assert "| none | 25.0 / 50.0 / 12.5 | 37.7 / 57.8 / 43.7 |" in md
    assert "| cobevt | - | 60.4 / 63.0 / 53.0 |" in md  # a paper row this run did not have
    assert "LiDAR AP@0.7" not in md
    lidar = _summary()
    assert "LiDAR AP@0.7" in report_md(metrics_json(lidar, {}, CommStats(), {}, None), lidar)


def test_vehicle_iou_by_range_scores_each_ring_on_its_own() -> None:
    from v2vsim.evaluation.metrics import MethodScore, ring_masks

    rings = ring_masks((64, 64), 100.0)
    assert list(rings) == ["0-20", "20-35", "35-50"]
    assert not (rings["0-20"] & rings["20-35"]).any() and not rings["35-50"][0, 0]  # disjoint; corners out
    s = MethodScore(size_m=100.0)
    gt = {"dynamic": np.zeros((64, 64), bool), "visible": np.zeros((64, 64), bool)}
    near, far = (32, 33), (5, 32)  # about 1 m and 41 m from the ego (1.5625 m cells)
    for cell in (near, far):
        gt["visible"][cell] = gt["dynamic"][cell] = True
    probs = {"vehicle": np.zeros((64, 64))}
    probs["vehicle"][near] = 1.0  # the near one found, the far one missed
    s.add_segmentation(probs, gt)
    doc = s.to_json(None)
    assert doc["iou_vehicle_by_range"] == {"0-20": 1.0, "20-35": None, "35-50": 0.0}
    assert doc["iou_vehicle"] == 0.5
