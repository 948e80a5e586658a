"""Ego fusion process: receives every CAV's messages, puts them through the channel model, warps
them into its own frame with the sender's pose at capture time, fuses with every method under
test, and scores each against ground truth. Writes metrics.json, report.md, plots and the Rerun
recording when the run ends, is interrupted, or loses agents.

lockstep: frame k is fused once every live CAV's frame-k messages are in (a CAV that dies is
noticed through zenoh liveliness within milliseconds, or after HANG_TIMEOUT_S if it hangs).
realtime: frame k is fused when its world arrives, with whatever has arrived by then.
"""

from __future__ import annotations

import json
import struct
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from agents.cav import read_key
from agents.common import START_TIMEOUT_S, AgentArgs, Bus, Stop, parse_agent_args, progress_line, run_agent
from v2vsim.comm.codec import RejectedMessage, decode
from v2vsim.comm.inbox import Inbox, distance
from v2vsim.comm.stats import CommStats
from v2vsim.evaluate import box_iou, fuse_and_score
from v2vsim.geometry import Pose, relative_pose
from v2vsim.gt import bev_ground_truth, gt_boxes
from v2vsim.metrics import ApAccumulator, MethodScore, cavs_in_range
from v2vsim.perception import (
    FusionInputs,
    build_agent_encoder,
    build_compressor,
    build_method_models,
    decompress,
    method_checkpoints,
    runnable_methods,
)
from v2vsim.recording import Recorder
from v2vsim.report import RunSummary, write_outputs
from v2vsim.sensors.scene import build_map_assets
from v2vsim.world import WorldState
from v2vsim.world_io import static_from_bytes, world_from_bytes

HANG_TIMEOUT_S = 60.0  # a live CAV that sends nothing for this long is treated as lost


class Mailbox:
    """Raw messages by (kind, frame, sender), filled on zenoh's thread, read on the main thread."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.raw: dict[tuple[str, int], list[tuple[str, bytes]]] = defaultdict(list)  # (sender key, bytes)
        self.unframed: list[tuple[str, str, bytes]] = []  # could not even read a frame number
        self.worlds: dict[int, bytes] = {}
        self.done = False

    def put(self, kind: str, sender: str, data: bytes) -> None:
        frame = _peek_frame(kind, data)
        with self.cond:
            if frame is None:
                self.unframed.append((kind, sender, data))
            else:
                self.raw[(kind, frame)].append((sender, data))
            self.cond.notify_all()


def _peek_frame(kind: str, data: bytes) -> int | None:
    """The frame a message claims, without validating it (validation happens at decode)."""
    if kind == "vis":
        try:
            return int(json.loads(data)["frame"])
        except (ValueError, KeyError, TypeError):
            return None
    try:
        return int(struct.unpack_from("<I", data, 12)[0])  # codec fixed header: frame after 12 bytes
    except struct.error:
        return None


def ego_loop(args: AgentArgs, bus: Bus) -> int:
    torch.set_num_threads(1)
    sc = args.scenario
    me = args.cav
    methods = sc.perception.methods
    lidar = sc.perception.modality == "lidar"
    key = read_key(sc.comm.auth.key_file)
    kinds = ["features"] + (["points"] if "early" in methods and lidar else []) + (
        ["outputs"] if "late" in methods else [])
    encoder = build_agent_encoder(sc)
    models = build_method_models(sc, encoder, runnable_methods(sc))
    static = static_from_bytes(bus.fetch("static", "main", START_TIMEOUT_S))
    assets = build_map_assets(static)
    c, f = encoder.out_channels, encoder.out_cells
    compressor = build_compressor(sc, c)
    shapes = {"features": {"features": (c // sc.comm.channel_compression, f, f)}, "points": {"points": (None, 4)},
              "outputs": {"outputs": (3, 8 * f, 8 * f), "outputs.boxes": (None, 6)}}  # decoder: 8x upsampling

    box = Mailbox()
    for kind in [*kinds, "vis"]:
        bus.subscribe(kind, lambda sender, data, kind=kind: box.put(kind, sender, data))
    bus.subscribe("world", lambda sender, data: _put_world(box, data))
    bus.subscribe("done", lambda sender, data: _set_done(box))
    lost: dict[str, int] = {}
    bus.on_lost(lambda who: _notify(box))

    stats = CommStats()
    inboxes = {k: Inbox(sc.comm, sc.seed, me, k, stats if k == "features" else CommStats()) for k in kinds}
    scores = {m: MethodScore(boxes=ApAccumulator(sort=sc.evaluation.ap_sort) if lidar else None) for m in models}
    ego_poses: dict[int, Pose] = {}
    out_dir = Path(args.out) / ("" if me == args.egos[0] else f"ego_{me}")
    recorder = Recorder(out_dir / "recording.rrd", sc, list(models)) if sc.output.rerun else None
    checkpoints = method_checkpoints(sc, tuple(models))
    summary = RunSummary(scenario=sc, ego=me, methods=list(models),
                         untrained=all(v is None for v in checkpoints.values()), checkpoints=checkpoints,
                         skipped=[m for m in methods if m not in models])
    bus.ready()
    t_start = time.monotonic()
    frames_done = 0
    status = "complete"
    realtime = sc.transport.clock == "realtime"
    k = -1
    try:
        while k + 1 < args.frames:
            got = _wait_world(box, k + 1, realtime)
            if got is None:
                status = f"ended early: the driver finished after frame {k}" if not realtime else status
                break
            k, data = got
            world = world_from_bytes(data, static)
            ego_actor = world.actor(me)
            if ego_actor is None:
                status = f"ego {me} left the simulation at frame {k}"
                break
            ego_poses[k] = ego_actor.pose
            near = cavs_in_range(world, me, sc.comm.range_m)
            present = [a.id for a in world.cavs if a.id in args.cavs]
            if not realtime:
                _wait_messages(box, bus, k, present, kinds, lost)
            for cav in present:
                if cav not in lost and bus.was_alive(f"cav.{cav}") and not bus.is_alive(f"cav.{cav}"):
                    lost[cav] = k
            for cav in lost:
                stats.record_lost_agent(cav)
            inp, visible = _collect(box, k, world, me, kinds, inboxes, ego_poses, key, args, shapes)
            inp.features = {s: decompress(compressor, v) for s, v in inp.features.items()}
            gt = bev_ground_truth(world, me, sc.bev, visible, assets=assets)
            boxes_gt, ids = gt_boxes(world, me, sc.bev)
            boxes_gt = boxes_gt[[i in visible for i in ids]] if len(ids) else boxes_gt
            preds = fuse_and_score(models, inp, sc.bev.cells, gt, boxes_gt, scores)
            for m in preds:
                scores[m].bytes.append(_bytes_for(m, inboxes))
            for ib in inboxes.values():
                ib.take_bytes()
            if recorder is not None:
                recorder.log_frame(k, world, me, gt, preds, inp)
            frames_done += 1
            summary.neighbours.append(near)
            if not realtime:
                bus.put("ack", json.dumps({"ego": me, "frame": k}).encode())
            progress_line(f"ego {me}", k + 1, args.frames, t_start)
    except Stop:
        status = f"interrupted after {frames_done} frames"
        raise
    finally:
        _reject_leftovers(box, kinds, inboxes, key, args)
        summary.frames = frames_done
        summary.sim_s = (k + 1) / sc.rate_hz
        summary.status = status
        summary.wall_s = time.monotonic() - t_start
        summary.lost_agents = dict(lost)
        write_outputs(out_dir, summary, scores, stats, {kind: ib.stats for kind, ib in inboxes.items()}, box_iou)
        if recorder is not None:
            recorder.close()
    return 0


def _reject_leftovers(box: Mailbox, kinds: list[str], inboxes: dict[str, Inbox], key: bytes | None,
                      args: AgentArgs) -> None:
    """Messages never fused (e.g. claiming a frame the run never reached) still get validated and counted."""
    with box.cond:
        leftovers = [(kind, data) for (kind, _f), table in box.raw.items() if kind in kinds for _s, data in table]
        leftovers += [(kind, data) for kind, _s, data in box.unframed if kind in kinds]
        box.raw.clear()
        box.unframed.clear()
    for kind, data in leftovers:
        try:
            decode(data, key=key, known_senders=args.cavs, run_id=args.run_id)
        except RejectedMessage as e:
            _count_rejected(inboxes, kind, e.reason)


def _count_rejected(inboxes: dict[str, Inbox], kind: str, reason: str) -> None:
    """Per kind, and every kind also in comm.rejected (the features inbox's stats)."""
    inboxes[kind].stats.record_rejected(reason)
    if kind != "features":
        inboxes["features"].stats.record_rejected(reason)


def _bytes_for(method: str, inboxes: dict[str, Inbox]) -> int:
    kind = {"early": "points", "late": "outputs", "none": None}.get(method, "features")
    return 0 if kind is None else inboxes[kind].bytes_this_frame


def _put_world(box: Mailbox, data: bytes) -> None:
    try:
        frame = int(json.loads(data)["frame"])
    except (ValueError, KeyError, TypeError):
        return
    with box.cond:
        box.worlds[frame] = data
        box.cond.notify_all()


def _set_done(box: Mailbox) -> None:
    with box.cond:
        box.done = True
        box.cond.notify_all()


def _notify(box: Mailbox) -> None:
    with box.cond:
        box.cond.notify_all()


def _wait_world(box: Mailbox, k: int, realtime: bool) -> tuple[int, bytes] | None:
    """World k (lockstep), or the newest world from k on (realtime: frames we fell behind on are skipped)."""
    with box.cond:
        while True:
            ready = [f for f in box.worlds if f >= k]
            if ready and (realtime or k in box.worlds):
                f = max(ready) if realtime else k
                data = box.worlds[f]
                for old in [x for x in box.worlds if x <= f]:
                    del box.worlds[old]
                return f, data
            if box.done:
                return None
            box.cond.wait(0.5)


def _wait_messages(box: Mailbox, bus: Bus, k: int, present: list[str], kinds: list[str],
                   lost: dict[str, int]) -> None:
    """Lockstep: wait until every live CAV's frame-k messages are in (or it is lost)."""
    deadline = time.monotonic() + HANG_TIMEOUT_S
    with box.cond:
        while True:
            missing = [c for c in present if c not in lost and not all(
                any(s == c for s, _ in box.raw.get((kind, k), ())) for kind in [*kinds, "vis"])]
            dead = [c for c in missing if bus.was_alive(f"cav.{c}") and not bus.is_alive(f"cav.{c}")]
            for c in dead:
                lost[c] = k
                print(f"v2vsim-ego: CAV {c} is gone at frame {k}; fusing the others", file=sys.stderr)
            if not [c for c in missing if c not in dead]:
                return
            if time.monotonic() > deadline:
                for c in missing:
                    lost[c] = k
                    print(f"v2vsim-ego: CAV {c} sent nothing for {HANG_TIMEOUT_S:g} s at frame {k}; "
                          "treating it as lost", file=sys.stderr)
                return
            box.cond.wait(0.2)


def _collect(box: Mailbox, k: int, world: WorldState, me: str, kinds: list[str], inboxes: dict[str, Inbox],
             ego_poses: dict[int, Pose], key: bytes | None, args: AgentArgs,
             shapes: dict[str, dict]) -> tuple[FusionInputs, set[str]]:
    """Decode frame k's messages, pass them through the channel, and gather what is fusable now."""
    realtime = args.scenario.transport.clock == "realtime"
    now = world.time
    with box.cond:
        raw = {kind: box.raw.pop((kind, k), []) for kind in [*kinds, "vis"]}
        # messages of earlier frames that came late (realtime, or a rogue sender): judged now
        for (kind, f), table in list(box.raw.items()):
            if f < k:
                if kind in kinds:
                    raw[kind] += table
                del box.raw[(kind, f)]
        unframed, box.unframed = box.unframed, []
    for kind, _sender, _data in unframed:
        if kind in kinds:
            _count_rejected(inboxes, kind, "truncated")
    visible: set[str] = set()
    for _sender, data in raw["vis"]:
        try:
            visible.update(str(i) for i in json.loads(data)["ids"])
        except (ValueError, KeyError, TypeError):
            pass  # ground-truth side channel between our own processes, not a V2V message
    for kind in kinds:
        for _sender, data in raw[kind]:
            try:
                msg = decode(data, key=key, known_senders=args.cavs, expected=shapes[kind], run_id=args.run_id)
            except RejectedMessage as e:
                _count_rejected(inboxes, kind, e.reason)
                continue
            ego_then = ego_poses.get(msg.frame, ego_poses[k])
            send_time = now if realtime else msg.capture_time
            inboxes[kind].offer(msg, len(data), send_time, distance(msg.sender_pose, ego_then.as_tuple()))
    ego_pose = ego_poses[k]
    fusable = {kind: inboxes[kind].ready(now) for kind in kinds}
    senders = [me] + sorted({s for table in fusable.values() for s in table} - {me})
    rel = np.zeros((len(senders), 3), np.float32)
    inp = FusionInputs(senders=senders, rel_poses=rel)
    for kind, table in fusable.items():
        for s, msg in table.items():
            i = senders.index(s)
            x, y, z, yaw = inboxes[kind].sender_pose(msg)
            rel[i] = relative_pose(ego_pose, Pose(x, y, z, yaw))
            if kind == "features":
                inp.features[s] = msg.payload  # float16 [C/r, F, F]; decompress() makes it float32 [C, F, F]
            elif kind == "points":
                inp.points[s] = msg.payload.astype(np.float32)
            else:
                inp.outputs[s] = (msg.payload.astype(np.float32), msg.extras["boxes"].astype(np.float32))
    return inp, visible


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("ego", argv)
    return run_agent(args, "ego", args.cav, lambda bus: ego_loop(args, bus))


if __name__ == "__main__":
    sys.exit(main())
