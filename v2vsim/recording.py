"""The Rerun recording of a run (`recording.rrd`): per frame, the world from above, the ego's
ground-truth BEV and every method's prediction as segmentation images with boxes, and per-frame
vehicle IoU as scalars. Open it with `rerun recording.rrd`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from v2vsim.config import Scenario
from v2vsim.geometry import BevGrid, box_corners
from v2vsim.perception import FusionInputs, Prediction
from v2vsim.world import WorldState

CLASSES = [(0, "background", (20, 20, 20)), (1, "road", (90, 90, 90)), (2, "lane", (230, 230, 230)),
           (3, "vehicle", (255, 80, 60)), (4, "vehicle (not visible)", (120, 60, 160))]


def class_image(road: np.ndarray, lane: np.ndarray, vehicle: np.ndarray,
                hidden: np.ndarray | None = None) -> np.ndarray:
    img = np.zeros(road.shape, np.uint8)
    img[road] = 1
    img[lane] = 2
    if hidden is not None:
        img[hidden] = 4
    img[vehicle] = 3
    return img


class Recorder:
    def __init__(self, path: Path, sc: Scenario, methods: list[str]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.grid = BevGrid(sc.bev.size_m, sc.bev.cells)
        self.methods = methods
        self.rec = rr.RecordingStream("v2vsim", recording_id=f"{sc.name}-{sc.seed}")
        views = [rrb.Spatial2DView(origin="world", name="world")]
        views += [rrb.Spatial2DView(origin=f"bev/{m}", name=m) for m in ["gt", *methods]]
        blueprint = rrb.Blueprint(rrb.Vertical(rrb.Grid(*views), rrb.TimeSeriesView(origin="metrics", name="IoU"),
                                               row_shares=[3, 1]))
        self.rec.save(path, default_blueprint=blueprint)
        self.rec.log("bev", rr.AnnotationContext(CLASSES), static=True)

    def _bev_boxes(self, boxes: np.ndarray) -> rr.LineStrips2D:
        """(K, >=5) ego-frame boxes -> closed outlines in BEV pixel coordinates (u = column, v = row)."""
        strips = []
        for b in boxes:
            c = box_corners(float(b[0]), float(b[1]), float(b[4]), float(b[2]), float(b[3]))
            rc = self.grid.xy_to_rc(np.vstack([c, c[:1]]))
            strips.append(rc[:, ::-1])
        return rr.LineStrips2D(strips, colors=(255, 220, 0))

    def log_frame(self, k: int, world: WorldState, ego: str, gt: dict[str, np.ndarray],
                  preds: dict[str, Prediction], inp: FusionInputs) -> None:
        rec = self.rec
        rec.set_time("frame", sequence=k)
        rec.set_time("sim_time", duration=world.time)
        strips = [np.vstack([a.footprint(), a.footprint()[:1]]) for a in world.actors]
        colors = [(0, 200, 255) if a.cav else (200, 200, 200) for a in world.actors]
        rec.log("world/actors", rr.LineStrips2D(strips, colors=colors, labels=[a.id if a.cav else "" for a in
                                                                                world.actors]))
        rec.log("world/received", rr.TextLog(f"fused senders: {', '.join(inp.senders)}"))
        hidden = gt["dynamic"] & ~gt["visible"]
        rec.log("bev/gt", rr.SegmentationImage(class_image(gt["road"], gt["lane"], gt["visible"], hidden)))
        for m, p in preds.items():
            veh = p.probs["vehicle"] >= 0.5
            rec.log(f"bev/{m}", rr.SegmentationImage(class_image(p.probs["road"] >= 0.5, p.probs["lane"] >= 0.5,
                                                                 veh)))
            if p.boxes is not None and len(p.boxes):
                rec.log(f"bev/{m}/boxes", self._bev_boxes(p.boxes))
            inter = np.count_nonzero(veh & gt["visible"] & ~hidden)
            union = np.count_nonzero((veh | gt["visible"]) & ~hidden)
            if union:
                rec.log(f"metrics/iou_vehicle/{m}", rr.Scalars(inter / union))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
