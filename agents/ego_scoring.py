"""The ego's after-fusion work: scoring (and recording) each fused frame on a worker thread beside the
next frame's fusion, and holding off signals while the last of it and the result files are written.
"""

from __future__ import annotations

import queue
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from agents.timing import StageTimer
from v2vsim.comm.inbox import LinkEvent
from v2vsim.control.pilot import PilotStep
from v2vsim.evaluation.fuse_and_score import score_all
from v2vsim.evaluation.metrics import MethodScore
from v2vsim.perception.fuse import FusionInputs, Prediction
from v2vsim.recording.scan import Scan
from v2vsim.world.state import WorldState

if TYPE_CHECKING:  # rerun and matplotlib load only in an ego that records (ego.py)
    from v2vsim.recording.recorder import Recorder


@dataclass(frozen=True)
class FusedFrame:
    """One fused frame as handed to the scoring and recording thread."""

    k: int
    world: WorldState
    gt: dict[str, np.ndarray]
    boxes_gt: np.ndarray
    preds: dict[str, Prediction]
    inp: FusionInputs
    sent: dict[str, int]  # method -> bytes received for it this frame
    links: list[LinkEvent]  # what each sender's feature link did
    scans: dict[str, Scan]  # sender -> its scan (recording only)
    drive: PilotStep | None = None  # closed loop: what the driven vehicle planned on this frame
    flagged: frozenset[str] = frozenset()  # senders the misbehaviour check flagged (defence)
    excluded: bool = False  # ... and fused without (defence.exclude)


class AfterFusion:
    """Scores (and records) fused frames on a worker thread, in frame order, while the main thread
    fuses the next frame: neither is on the critical path of a lockstep run any more. A bounded
    queue keeps the worker at most MAX_BEHIND frames behind; its failure surfaces on the next
    `submit` or at `close`, as a crash of the frame it was working on."""

    MAX_BEHIND = 2

    def __init__(self, scores: dict[str, MethodScore], recorder: Recorder | None, timer: StageTimer) -> None:
        self.scores = scores
        self.recorder = recorder
        self.timer = timer
        self.jobs: queue.Queue[FusedFrame | None] = queue.Queue(maxsize=self.MAX_BEHIND)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._work, name="score-record", daemon=True)
        self.thread.start()

    def submit(self, frame: FusedFrame) -> None:
        self._raise()
        with self.timer.stage("wait_scoring"):
            self.jobs.put(frame)

    def close(self) -> None:
        if self.thread.is_alive():
            self.jobs.put(None)
            self.thread.join()
        self._raise()

    def _raise(self) -> None:
        if self.error is not None:
            err, self.error = self.error, None
            raise err

    def _work(self) -> None:
        while (job := self.jobs.get()) is not None:
            if self.error is not None:
                continue  # drain: the main thread raises the first failure
            try:
                with self.timer.stage("scoring"):
                    score_all(job.preds, job.gt, job.boxes_gt, self.scores, frame=job.k)
                    for m, n in job.sent.items():
                        self.scores[m].bytes.append(n)
                if self.recorder is not None:
                    with self.timer.stage("recording"):
                        self.recorder.log_frame(job.k, job.world, job.gt, job.boxes_gt, job.preds, job.inp,
                                                job.links, job.scans,
                                                {m: self.scores[m].vehicle.last_iou for m in job.preds},
                                                job.flagged, job.excluded)
                        if job.drive is not None:
                            self.recorder.log_drive(job.k, job.world, job.drive)
            except BaseException as e:  # noqa: BLE001 - handed to the main thread as is
                self.error = e


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Ignore SIGINT/SIGTERM inside (main thread only; elsewhere a no-op), then restore the handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
