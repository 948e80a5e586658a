"""Scores for one fusion method over a run (DESIGN.md "metrics.json").

IoU is dataset-level (summed intersections / summed unions over frames, threshold 0.5) with the
per-frame mean beside it. Vehicle IoU is scored on visible vehicles as in the OPV2V camera track:
cells of vehicles no CAV saw are left out of both prediction and truth. AP is BEV rotated-box AP
at IoU 0.5 / 0.7 (all-point interpolation) with detections sorted over the whole run, or per frame
with `evaluation.ap_sort: per_frame` (see ApAccumulator).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from v2vsim.world.state import WorldState

THRESHOLD = 0.5


def cavs_in_range(world: WorldState, ego: str, range_m: float) -> int | None:
    """Other CAVs whose pose (footprint centre) is within `range_m` of the ego's, in this world;
    None if the ego is not in it. Geometry only: the channel's drop, latency and loss play no part."""
    me = world.actor(ego)
    if me is None:
        return None
    return sum(1 for a in world.cavs
               if a.id != ego and math.hypot(a.pose.x - me.pose.x, a.pose.y - me.pose.y) <= range_m)


def neighbour_shares(counts: Sequence[int], cavs: int) -> dict[str, float]:
    """{"0": share, "1": share, ...}: share of the frames with that many other CAVs in range, one key
    for every count from 0 to cavs - 1 (and beyond, if a frame saw more); empty without frames."""
    if not counts:
        return {}
    hist = np.bincount(np.asarray(counts, dtype=np.int64), minlength=max(cavs, 1))
    return {str(i): round(float(h) / len(counts), 4) for i, h in enumerate(hist)}


@dataclass
class IouAccumulator:
    """Sums intersections and unions of boolean masks over frames."""

    inter: int = 0
    union: int = 0
    per_frame: list[float] = field(default_factory=list)  # IoU of each frame with a non-empty union
    counts: list[tuple[int, int]] = field(default_factory=list)  # (intersection, union) of every frame
    frame_ids: list[int] = field(default_factory=list)  # the frame each entry of `counts` belongs to

    def add(self, pred: np.ndarray, truth: np.ndarray, ignore: np.ndarray | None = None,
            frame: int | None = None) -> None:
        """Add one frame; `frame`: its key (the ego's frame index), by default the number of frames added
        before it. Methods are paired frame by frame on these keys (`paired_counts`)."""
        if ignore is not None:
            keep = ~ignore
            pred, truth = pred & keep, truth & keep
        i = int(np.count_nonzero(pred & truth))
        u = int(np.count_nonzero(pred | truth))
        self.inter += i
        self.union += u
        self.counts.append((i, u))
        self.frame_ids.append(len(self.frame_ids) if frame is None else frame)
        if u:
            self.per_frame.append(i / u)

    @property
    def iou(self) -> float | None:
        return self.inter / self.union if self.union else None

    @property
    def last_iou(self) -> float | None:
        """The latest frame's IoU (None when that frame's union was empty or nothing was added)."""
        if not self.counts or not self.counts[-1][1]:
            return None
        i, u = self.counts[-1]
        return i / u

    @property
    def frame_mean(self) -> float | None:
        return float(np.mean(self.per_frame)) if self.per_frame else None


def paired_counts(a: IouAccumulator, b: IouAccumulator) -> tuple[np.ndarray, np.ndarray]:
    """(intersection, union) per frame of `a` and of `b` on the frames both scored, in frame order: [n, 2]
    each, row t of both the same frame. A method without input on a frame (predict() gave None, e.g. the
    ego's own message missing in a realtime run) is not scored on it, so position alone does not pair."""
    ca, cb = dict(zip(a.frame_ids, a.counts, strict=True)), dict(zip(b.frame_ids, b.counts, strict=True))
    common = sorted(ca.keys() & cb.keys())
    return (np.array([ca[k] for k in common], dtype=np.int64).reshape(-1, 2),
            np.array([cb[k] for k in common], dtype=np.int64).reshape(-1, 2))


AP_SORTS = ("global", "per_frame")


@dataclass
class ApAccumulator:
    """Collects scored BEV boxes (x, y, l, w, yaw) and ground truth per frame; AP at any IoU threshold.

    sort="global": every detection of the run is ranked by score before the cumulative sums
    (OpenCOOD's --global_sort_detections; DESIGN.md). sort="per_frame": detections are ranked by
    score within each frame and the frames' true/false positives are concatenated in frame order,
    without a global re-sort (OpenCOOD's default). Matching is the same in both: within a frame,
    detections in descending score each take the best still-free ground truth box."""

    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)  # (det, scores, gt)
    sort: str = "global"

    def __post_init__(self) -> None:
        if self.sort not in AP_SORTS:
            raise ValueError(f"ApAccumulator sort {self.sort!r}; allowed: {', '.join(AP_SORTS)}")

    def add(self, det_boxes: np.ndarray, det_scores: np.ndarray, gt_boxes: np.ndarray) -> None:
        self.frames.append((np.asarray(det_boxes, dtype=np.float64).reshape(-1, 5),
                            np.asarray(det_scores, dtype=np.float64).reshape(-1),
                            np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 5)))

    def ap(self, iou_threshold: float, iou_fn: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> float | None:
        return self.aps((iou_threshold,), iou_fn)[0]

    def aps(self, thresholds: Sequence[float], iou_fn: Callable[[np.ndarray, np.ndarray], np.ndarray]
            ) -> list[float | None]:
        """AP at each IoU threshold; each frame's IoU matrix (the costly part: rotated boxes) is computed once, and
        every frame's at once when `iou_fn` has a batched form `iou_fn.many(pairs) -> matrices`."""
        n_gt = sum(len(g) for _, _, g in self.frames)
        if n_gt == 0:
            return [None] * len(thresholds)
        ranked = []
        for det, sc, gt in self.frames:
            if len(det):
                order = np.argsort(-sc, kind="stable")
                ranked.append((det[order], sc[order], gt))
        many = getattr(iou_fn, "many", None)
        with_gt = [(d, g) for d, _, g in ranked if len(g)]
        matrices = iter(many(with_gt) if many is not None else [iou_fn(d, g) for d, g in with_gt])
        scores: list[float] = []
        hits: list[list[bool]] = [[] for _ in thresholds]
        for det, sc, gt in ranked:
            ious = next(matrices) if len(gt) else np.zeros((len(det), 0))
            scores.extend(sc)
            for t, threshold in enumerate(thresholds):
                taken = np.zeros(len(gt), dtype=bool)
                for k in range(len(det)):
                    hit = False
                    if ious.shape[1]:
                        cand = np.where(taken, -1.0, ious[k])
                        j = int(np.argmax(cand))
                        if cand[j] >= threshold:
                            taken[j] = hit = True
                    hits[t].append(hit)
        return [self._ap(scores, h, n_gt) for h in hits]

    def _ap(self, scores: list[float], hits: list[bool], n_gt: int) -> float:
        """All-point interpolated AP of detections in frame order, `hits` marking the true positives."""
        if not scores:
            return 0.0
        hits_arr = np.asarray(hits)
        if self.sort == "global":
            hits_arr = hits_arr[np.argsort(-np.asarray(scores), kind="stable")]
        tp = np.cumsum(hits_arr)
        fp = np.cumsum(~hits_arr)
        recall = tp / n_gt
        precision = tp / np.maximum(tp + fp, 1)
        # all-point interpolation: precision envelope integrated over recall
        mrec = np.concatenate([[0.0], recall, [1.0]])
        mpre = np.concatenate([[0.0], precision, [0.0]])
        mpre = np.maximum.accumulate(mpre[::-1])[::-1]
        steps = np.where(mrec[1:] != mrec[:-1])[0]
        return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


def visible_vehicle_masks(p_vehicle: np.ndarray, gt: dict[str, np.ndarray]
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(prediction, truth, ignore) of the visible-vehicle IoU: vehicles no CAV saw are left out of both."""
    return p_vehicle >= THRESHOLD, gt["visible"], gt["dynamic"] & ~gt["visible"]


def vehicle_iou(p_vehicle: np.ndarray, gt: dict[str, np.ndarray]) -> float | None:
    """One frame's visible-vehicle IoU (None when prediction and truth are both empty)."""
    acc = IouAccumulator()
    pred, truth, ignore = visible_vehicle_masks(p_vehicle, gt)
    acc.add(pred, truth, ignore=ignore)
    return acc.last_iou


# Rings of distance from the ego (m, on the default 100 m grid; scaled with bev.size_m): where a vehicle is decides
# how many LiDAR points it gets and who else sees it, so the visible-vehicle IoU is also reported per ring.
RANGE_RINGS = ((0.0, 0.2), (0.2, 0.35), (0.35, 0.5))  # as shares of the grid's side


def ring_masks(shape: tuple[int, ...], size_m: float) -> dict[str, np.ndarray]:
    """{"0-20": bool mask of `shape`, ...}: the cells whose centre lies in each ring around the grid's centre (the
    ego), keyed by the ring's metres (the grid's first axis spans size_m); the last ring keeps the grid's corners out
    (a circle, not the square)."""
    cell = size_m / shape[0]
    rows = (np.arange(shape[0]) + 0.5 - shape[0] / 2) * cell
    cols = (np.arange(shape[1]) + 0.5 - shape[1] / 2) * cell
    dist = np.hypot(rows[:, None], cols[None, :])
    return {f"{lo * size_m:g}-{hi * size_m:g}": (dist >= lo * size_m) & (dist < hi * size_m) for lo, hi in RANGE_RINGS}


@dataclass
class MethodScore:
    """Everything metrics.json reports for one method. `size_m`: the BEV grid's side (the range rings' scale)."""

    vehicle: IouAccumulator = field(default_factory=IouAccumulator)
    vehicle_all: IouAccumulator = field(default_factory=IouAccumulator)
    road: IouAccumulator = field(default_factory=IouAccumulator)
    lane: IouAccumulator = field(default_factory=IouAccumulator)
    boxes: ApAccumulator | None = None
    fusion_ms: list[float] = field(default_factory=list)
    bytes: list[int] = field(default_factory=list)
    frames: int = 0
    size_m: float = 100.0
    vehicle_by_range: dict[str, IouAccumulator] = field(default_factory=dict)
    _rings: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def add_segmentation(self, probs: dict[str, np.ndarray], gt: dict[str, np.ndarray],
                         frame: int | None = None) -> None:
        """probs: 'vehicle', 'road', 'lane' probability maps; gt: 'dynamic', 'visible', 'road', 'lane' masks;
        frame: the frame's key, by default the number of frames this method scored before it (which pairs
        methods only if every method is scored on every frame)."""
        key = self.frames if frame is None else frame
        self.frames += 1
        veh = probs["vehicle"] >= THRESHOLD
        pred, truth, ignore = visible_vehicle_masks(probs["vehicle"], gt)
        self.vehicle.add(pred, truth, ignore, frame=key)
        if not self._rings or next(iter(self._rings.values())).shape != pred.shape:
            self._rings = ring_masks(pred.shape, self.size_m)
        for name, ring in self._rings.items():
            self.vehicle_by_range.setdefault(name, IouAccumulator()).add(pred & ring, truth & ring, ignore, frame=key)
        self.vehicle_all.add(veh, gt["dynamic"], frame=key)
        if "road" in probs:
            self.road.add(probs["road"] >= THRESHOLD, gt["road"], frame=key)
        if "lane" in probs:
            self.lane.add(probs["lane"] >= THRESHOLD, gt["lane"], frame=key)

    def to_json(self, iou_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None) -> dict:
        def r(v: float | None) -> float | None:
            return None if v is None else round(v, 4)

        ap50 = ap70 = None
        if self.boxes is not None and iou_fn is not None:
            ap50, ap70 = self.boxes.aps((0.5, 0.7), iou_fn)
        return {
            "iou_vehicle": r(self.vehicle.iou),
            "iou_vehicle_frame_mean": r(self.vehicle.frame_mean),
            "iou_vehicle_all": r(self.vehicle_all.iou),
            # visible-vehicle IoU per ring of distance from the ego (m): where the gap is (near or far)
            "iou_vehicle_by_range": {k: r(acc.iou) for k, acc in self.vehicle_by_range.items()},
            "iou_road": r(self.road.iou),
            "iou_lane": r(self.lane.iou),
            "ap50": r(ap50),
            "ap70": r(ap70),
            "fusion_ms": r(float(np.mean(self.fusion_ms))) if self.fusion_ms else None,
            "bytes_per_frame": int(np.mean(self.bytes)) if self.bytes else 0,
            "frames": self.frames,
            # per fused frame, in order: what a study needs to resample frames (v2vsim sweep's bootstrap)
            "iou_vehicle_counts": [list(c) for c in self.vehicle.counts],
            # the frame index of each entry above: methods pair on these (one may miss a frame it had no input for)
            "iou_vehicle_frames": list(self.vehicle.frame_ids),
        }
