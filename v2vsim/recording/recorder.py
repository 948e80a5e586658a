"""Writes one ego's `recording.rrd`: the map once, then per frame the 3D world (vehicles, LiDAR,
V2V links, camera frusta), the BEV ground truth, every method's probability, errors and boxes,
the per-frame IoU and link plots, and a fusion log line. Entity paths:

    world/map/{ground,roads,markings,buildings}   static meshes and lines
    world/{vehicles,cavs,ego}                     Boxes3D (CAVs labelled, the ego solid)
    world/lidar/<cav>  world/links  world/bev_extent  world/ego_cameras/<name>
    bev/gt/{classes,boxes}   bev/<method>/{probability,errors,boxes}
    metrics/iou_vehicle/<method>   links/{latency_ms,age_ms,delivered}/<cav>   log/fusion
    closed loop: world/drive/{path,obstacles,leader,events}   drive/{speed,planned_speed,min_gap_m}   log/drive

Rows are batched into few large chunks (the batcher flushes every 30 s or 16 MB, not every
few milliseconds), and things that never change are logged once as static.
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import rerun as rr

from v2vsim.comm.inbox import LinkEvent
from v2vsim.comm.misbehaviour import liars
from v2vsim.config import Scenario
from v2vsim.control.pilot import PilotStep
from v2vsim.perception.fuse import FusionInputs, Prediction
from v2vsim.recording import bev, world3d
from v2vsim.recording.blueprint import default_blueprint
from v2vsim.recording.scan import Scan, jpeg
from v2vsim.sensors.camera import camera_rig
from v2vsim.world.geometry import BevGrid
from v2vsim.world.state import StaticMap, WorldState

BATCHING = rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=30), flush_num_bytes=16 << 20, flush_num_rows=1 << 20)
METHOD_PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                  (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]


class Recorder:
    def __init__(self, path: Path, sc: Scenario, methods: list[str], cavs: list[str], ego: str,
                 static: StaticMap, types: dict[str, str] | None = None) -> None:
        """`types`: a mixed fleet's CAV id -> agent type label; each CAV is then coloured and labelled by type."""
        path.parent.mkdir(parents=True, exist_ok=True)
        self.grid = BevGrid(sc.bev.size_m, sc.bev.cells)
        self.bev_size_m = sc.bev.size_m
        self.methods = methods
        self.cavs = sorted(cavs)
        self.types = types or {}
        self.liars = liars(sc.misbehaviour)  # a lying CAV is marked (misbehaviour)
        self.ego = ego
        self.rig = camera_rig(sc.sensors.cameras)
        self.delivered: dict[str, list[int]] = {}  # sender -> [delivered, events]
        self.rec = rr.RecordingStream("v2vsim", recording_id=f"{sc.name}-{sc.seed}-{ego}", batcher_config=BATCHING)
        self.rec.save(path, default_blueprint=default_blueprint(methods, list(self.rig.names), static,
                                                                closed_loop=sc.control is not None))
        self._last_ttc: float | None = None  # closed loop: the SSM reading logged last (log_drive marks changes)
        self._log_static(static, sc)

    def _log_static(self, static: StaticMap, sc: Scenario) -> None:
        log = self.rec.log
        log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        log("world/map/ground", world3d.ground_mesh(static), static=True)
        if (roads := world3d.road_mesh(static)) is not None:
            log("world/map/roads", roads, static=True)
        log("world/map/markings", world3d.marking_strips(static), static=True)
        if (buildings := world3d.building_mesh(static)) is not None:
            log("world/map/buildings", buildings, static=True)
        for i, name in enumerate(self.rig.names):
            log(f"world/ego_cameras/{name}", world3d.camera_pinhole(self.rig, i), static=True)
        log("bev/gt", rr.AnnotationContext(bev.GT_CLASSES), static=True)
        for i, m in enumerate(self.methods):
            log(f"bev/{m}", rr.AnnotationContext(bev.ERROR_CLASSES), static=True)
            log(f"metrics/iou_vehicle/{m}", rr.SeriesLines(colors=METHOD_PALETTE[i % len(METHOD_PALETTE)], names=m,
                                                          widths=2.0), static=True)
        if sc.control is not None:  # the closed loop's plots (log_drive)
            for name, colour in (("speed", (44, 160, 44)), ("planned_speed", (255, 127, 14)),
                                 ("min_gap_m", (214, 39, 40))):
                log(f"drive/{name}", rr.SeriesLines(colors=colour, names=name, widths=2.0), static=True)
        for cav in self.cavs:
            colour = world3d.cav_colour(self.cavs, cav, self.types)
            log(f"links/latency_ms/{cav}", rr.SeriesPoints(colors=colour, names=cav, markers="circle",
                                                           marker_sizes=2.0), static=True)
            log(f"links/age_ms/{cav}", rr.SeriesPoints(colors=colour, names=cav, markers="circle",
                                                       marker_sizes=2.0), static=True)
            log(f"links/delivered/{cav}", rr.SeriesLines(colors=colour, names=cav, widths=2.0), static=True)

    def log_frame(self, k: int, world: WorldState, gt: dict[str, np.ndarray], boxes_gt: np.ndarray,
                  preds: dict[str, Prediction], inp: FusionInputs, links: list[LinkEvent],
                  scans: dict[str, Scan], ious: dict[str, float | None],
                  flagged: frozenset[str] = frozenset(), excluded: bool = False) -> None:
        """ious: each method's visible-vehicle IoU of this frame as scoring computed it (None: empty union);
        flagged: the senders the misbehaviour check flagged this frame (`defence`), excluded from fusion or not."""
        rec = self.rec
        rec.set_time("frame", sequence=k)
        rec.set_time("sim_time", duration=world.time)
        self._log_world(world, links, scans)
        rec.log("bev/gt/classes", rr.SegmentationImage(bev.gt_image(gt)))
        rec.log("bev/gt/boxes", rr.LineStrips2D(bev.box_strips(self.grid, boxes_gt), colors=bev.GT_BOX_RGB,
                                                radii=0.4))
        for m, p in preds.items():
            veh = p.probs["vehicle"]
            rec.log(f"bev/{m}/probability", rr.EncodedImage(contents=jpeg(bev.probability_image(veh)),
                                                            media_type="image/jpeg"))
            rec.log(f"bev/{m}/errors", rr.SegmentationImage(bev.error_image(veh, gt)))
            # Always logged, empty when there are none, so last frame's boxes never linger.
            boxes = p.boxes if p.boxes is not None else np.zeros((0, 6), np.float32)
            rec.log(f"bev/{m}/boxes", rr.LineStrips2D(bev.box_strips(self.grid, boxes), colors=bev.PRED_BOX_RGB,
                                                      radii=0.6))
            if (iou := ious.get(m)) is not None:
                rec.log(f"metrics/iou_vehicle/{m}", rr.Scalars(iou))
        self._log_links(links)
        fates = ", ".join(f"{e.sender} {e.outcome.replace('_', ' ')}"
                          + (f" (fused age {e.age_ms:.0f} ms)" if e.age_ms is not None else "")
                          for e in links) or "no V2V messages"
        # what reached the fusion: a sender the defence left out (flagged, or unjudged) has no payload left
        fused = [s for s in inp.senders if s in inp.features or s in inp.outputs or s in inp.points]
        check = (f" | FLAGGED by the misbehaviour check: {', '.join(sorted(flagged))}"
                 + (" (fused without)" if excluded else "")) if flagged else ""
        rec.log("log/fusion", rr.TextLog(f"frame {k}: fused {', '.join(fused)} | links: {fates}{check}",
                                         level=rr.TextLogLevel.WARN if flagged else rr.TextLogLevel.INFO))

    def _label(self, cav: str) -> str:
        label = f"{cav} {self.types[cav]}" if cav in self.types else cav
        return f"{label} LIES: {self.liars[cav]}" if cav in self.liars else label

    def _log_world(self, world: WorldState, links: list[LinkEvent], scans: dict[str, Scan]) -> None:
        rec = self.rec
        ego = world.actor(self.ego)
        others = [a for a in world.actors if not a.cav]
        cavs = [a for a in world.actors if a.cav and a.id != self.ego]
        rec.log("world/vehicles", world3d.vehicle_boxes(others, [world3d.OTHER_VEHICLE_RGB] * len(others)))
        colours = [world3d.cav_colour(self.cavs, a.id, self.types) for a in cavs]
        rec.log("world/cavs", world3d.vehicle_boxes(cavs, colours, labels=[self._label(a.id) for a in cavs]))
        if ego is None:
            return
        rec.log("world/ego", world3d.vehicle_boxes([ego], [world3d.cav_colour(self.cavs, ego.id, self.types)],
                                                   labels=[f"ego {self._label(ego.id)}"], solid=True))
        rec.log("world/bev_extent", world3d.bev_extent(ego.pose, self.bev_size_m))
        rec.log("world/links", world3d.link_lines(links, ego.pose, {a.id: a.pose for a in cavs}))
        for cav in self.cavs:
            scan = scans.get(cav)
            pts = scan.points if scan is not None and scan.points is not None else np.zeros((0, 3), np.float32)
            rec.log(f"world/lidar/{cav}", rr.Points3D(pts, colors=world3d.cav_colour(self.cavs, cav, self.types),
                                                           radii=rr.components.Radius.ui_points(1.5)))
        own = scans.get(self.ego)
        if own is not None and own.jpegs is not None:
            for i, name in enumerate(self.rig.names):
                rec.log(f"world/ego_cameras/{name}", world3d.camera_pose(self.rig, i, ego.pose),
                        rr.EncodedImage(contents=own.jpegs[i], media_type="image/jpeg"))

    def _log_links(self, links: list[LinkEvent]) -> None:
        for e in links:
            n = self.delivered.setdefault(e.sender, [0, 0])
            if e.age_ms is not None:
                self.rec.log(f"links/age_ms/{e.sender}", rr.Scalars(e.age_ms))
            if e.outcome in ("in_flight", "reused"):
                continue  # its fate is told when it is fused (or goes stale); reused: an earlier one fused again
            n[0] += e.outcome == "delivered"
            n[1] += 1
            self.rec.log(f"links/delivered/{e.sender}", rr.Scalars(n[0] / n[1]))
            if e.outcome == "delivered" and e.latency_ms is not None:
                self.rec.log(f"links/latency_ms/{e.sender}", rr.Scalars(e.latency_ms))

    def log_drive(self, k: int, world: WorldState, step: PilotStep) -> None:
        """The closed loop at frame k (after log_frame, same time): the route the planner followed, the tracks it
        planned on (the one it braked for in red), its speed against the planned one, and every collision and SSM
        reading marked in 3D and on the timeline."""
        rec = self.rec
        state = next((d for d in world.driven if d.id == self.ego), None)
        if state is not None:
            rec.log("world/drive/path", rr.LineStrips3D([np.c_[state.path, np.full(len(state.path), 0.1)]],
                                                        colors=(250, 220, 40), radii=0.15))
        tracks = step.tracks
        rec.log("world/drive/obstacles", rr.Boxes3D(
            centers=[(t.x, t.y, 0.8) for t in tracks], half_sizes=[(t.length / 2, t.width / 2, 0.8) for t in tracks],
            rotation_axis_angles=[rr.RotationAxisAngle(axis=(0, 0, 1), radians=t.yaw) for t in tracks],
            colors=[(255, 60, 60) if step.plan.obstacle is not None and t.id == step.plan.obstacle.id
                    else (255, 170, 60) for t in tracks],
            labels=[f"track {t.id} {np.hypot(t.vx, t.vy):.1f} m/s" for t in tracks]))
        log = step.logged
        rec.log("drive/speed", rr.Scalars(log.speed))
        rec.log("drive/planned_speed", rr.Scalars(step.plan.speed))
        if log.min_gap_m is not None:
            rec.log("drive/min_gap_m", rr.Scalars(log.min_gap_m))
        events = []
        if log.collisions:
            events.append(f"COLLISION with {', '.join(log.collisions)}")
        if log.phantom:
            events.append("phantom braking (no vehicle near the obstacle)")
        ttc = log.ssm[0]
        if ttc is not None and self._last_ttc != ttc:
            events.append(f"SSM min TTC now {ttc:.2f} s")
        self._last_ttc = ttc
        rec.log("world/drive/events", rr.Points3D([(log.x, log.y, 3.0)] if events else np.zeros((0, 3)),
                                                  colors=(255, 0, 0), radii=1.0, labels=events[:1] or None))
        rec.log("log/drive", rr.TextLog(
            f"frame {k}: {step.plan.reason}, planned {step.plan.speed:.1f} m/s (speed {log.speed:.1f})"
            + (f" for track {step.plan.obstacle.id}" if step.plan.obstacle is not None else "")
            + (" | " + "; ".join(events) if events else ""),
            level=rr.TextLogLevel.WARN if log.collisions or log.phantom else rr.TextLogLevel.INFO))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
