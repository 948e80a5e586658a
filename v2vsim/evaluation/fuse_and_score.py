"""Fuse, decode and score one frame with every method: the one prediction path.

The ego process (agents/ego.py) and validation during training (v2vsim.training) both call
`fuse_and_score`, so a metric printed by `v2vsim train` and one in a run's metrics.json come from
the same code given the same FusionInputs (the ego calls its two halves, `predict_all` and
`score_all`, apart so that scoring can run beside the next frame's fusion).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import Executor
from functools import partial

import numpy as np
import torch
from torch import nn

from models.nms import rotated_iou_matrices, rotated_iou_matrix
from v2vsim.evaluation.metrics import MethodScore
from v2vsim.perception.fuse import FusionInputs, Prediction, fusion_key, predict
from v2vsim.perception.precision import Precision


def fuse_and_score(models: dict[str, nn.Module], inp: FusionInputs, cells: int, gt: dict[str, np.ndarray],
                   boxes_gt: np.ndarray, scores: dict[str, MethodScore], frame: int | None = None
                   ) -> dict[str, Prediction]:
    """Predict with every method that has input and add its scores; returns the predictions.

    gt: "dynamic", "visible", "road", "lane" masks on the ego grid; boxes_gt [K, 5] scored boxes; frame: the
    frame's key (see `score_all`)."""
    preds = predict_all(models, inp, cells)
    score_all(preds, gt, boxes_gt, scores, frame)
    return preds


PredictionMemo = Callable[[str, nn.Module, bytes, Callable[[], "Prediction | None"]], "Prediction | None"]
"""memo(method, model, fusion_key, compute) -> compute()'s value, or the one computed before for the same method,
model and key (agents.ego_replay.ReplayBus.prediction_memo: replays of one recording in one process)."""


def predict_all(models: dict[str, nn.Module], inp: FusionInputs, cells: int,
                precision: Precision = "fp32", memo: PredictionMemo | None = None,
                pool: Executor | None = None, cost: Mapping[str, float] | None = None) -> dict[str, Prediction]:
    """Every method's prediction for one frame (methods without input are left out), in `models`' order. With
    `memo`, a prediction from the same model and fusion inputs (fusion_key) is taken from it; its `ms` is that
    computation's. With `pool`, the methods run side by side on its threads (torch releases the GIL inside an
    op): each method's forward pass is the same sequence of ops on the same inputs, so every prediction is
    bit-identical to a serial run's; only its `ms` (wall time, shared cores) differs. `cost`: each method's expected
    ms (e.g. its mean so far), so that the pool starts the longest first and no thread is left with a long one at
    the end (the returned dict keeps `models`' order either way)."""
    digests: dict[int, bytes] = {}  # each input array hashed once for every method's fusion_key
    jobs: dict[str, Callable[[], Prediction | None]] = {}
    for m, model in models.items():
        if memo is None:
            jobs[m] = partial(predict, m, model, inp, cells, precision)
        else:  # keys hashed here, in this thread: `digests` is shared by the methods
            jobs[m] = partial(memo, m, model, fusion_key(m, inp, digests),
                              partial(predict, m, model, inp, cells, precision))
    if pool is None:
        done = {m: job() for m, job in jobs.items()}
    else:
        costs = cost or {}
        first = sorted(jobs, key=lambda m: -costs.get(m, 0.0))  # stable: models' order among equals
        futures = {m: pool.submit(jobs[m]) for m in first}
        done = {m: futures[m].result() for m in jobs}
    return {m: pred for m, pred in done.items() if pred is not None}


def score_all(preds: dict[str, Prediction], gt: dict[str, np.ndarray], boxes_gt: np.ndarray,
              scores: dict[str, MethodScore], frame: int | None = None) -> None:
    """Add one frame's predictions to the running scores (segmentation IoU, AP, fusion time). Only the
    methods in `preds` are scored (one without input on this frame is not), so `frame`, the frame's key,
    is what pairs methods frame by frame afterwards; None: each method counts its own scored frames."""
    for m, pred in preds.items():
        s = scores[m]
        s.add_segmentation(pred.probs, gt, frame)
        s.fusion_ms.append(pred.ms)
        if s.boxes is not None and pred.boxes is not None:
            s.boxes.add(pred.boxes[:, :5], pred.boxes[:, 5], boxes_gt)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotated BEV IoU matrix of (x, y, l, w, yaw) boxes, the IoU that AP is scored with. `box_iou.many` (below):
    the same for many pairs at once, which ApAccumulator.aps uses."""
    return rotated_iou_matrix(_boxes(a), _boxes(b)).numpy()


def box_ious(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[np.ndarray]:
    """box_iou of every (a, b) pair, computed together (models.nms.rotated_iou_matrices)."""
    return [m.numpy() for m in rotated_iou_matrices([(_boxes(a), _boxes(b)) for a, b in pairs])]


def _boxes(a: np.ndarray) -> torch.Tensor:
    """float32 copy of a box array (which may be read-only: a replay shares its predictions and ground truth)."""
    return torch.tensor(a, dtype=torch.float32)


box_iou.many = box_ious  # type: ignore[attr-defined]
