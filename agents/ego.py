"""Ego fusion process: receives every CAV's messages, puts them through the channel model, warps
them into its own frame with the sender's pose at capture time, fuses with every method under
test, and scores each against ground truth. Writes metrics.json, report.md, plots and the Rerun
recording when the run ends, is interrupted, or loses agents.

lockstep: frame k is fused once every live CAV's frame-k messages are in (a CAV that dies is
noticed through zenoh liveliness within milliseconds, or after HANG_TIMEOUT_S if it hangs).
realtime: frame k is fused when its world arrives, with whatever has arrived by then.

Every received V2V message goes through one decode path (v2vsim.comm.wire_spec.EgoDecoder, with
the scenario's exact shapes and bounds); a rejected one is counted, never fatal. metrics.json
`status` says how the run ended: complete, ended early (the driver finished or stopped), driver
died (its liveliness token dropped without a bye: the ego stops within seconds), interrupted,
or crashed at frame k (the exception is re-raised, exit 1).
"""

from __future__ import annotations

import json
import queue
import signal
import struct
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from agents.common import (
    DONE_GRACE_S,
    DRIVER,
    DRIVER_GRACE_S,
    START_TIMEOUT_S,
    AgentArgs,
    Bus,
    Stop,
    parse_agent_args,
    read_key,
    run_agent,
)
from agents.progress import report_progress
from agents.timing import StageTimer
from v2vsim.comm.inbox import Inbox, LinkEvent, distance
from v2vsim.comm.share import dense_payload
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import EgoDecoder, ego_wire_spec, message_kind
from v2vsim.evaluation.fuse_and_score import box_iou, predict_all, score_all
from v2vsim.evaluation.gt import bev_ground_truth, gt_boxes
from v2vsim.evaluation.metrics import ApAccumulator, MethodScore, cavs_in_range
from v2vsim.evaluation.report import RunSummary, write_outputs
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_method_models,
    decompress,
    method_checkpoints,
    runnable_methods,
)
from v2vsim.perception.fuse import FusionInputs, Prediction
from v2vsim.recording.recorder import Recorder
from v2vsim.recording.scan import Scan, decode_scan, max_scan_bytes, scan_frame
from v2vsim.sensors.scene import build_map_assets
from v2vsim.world.geometry import Pose, relative_pose
from v2vsim.world.serialize import static_from_bytes, world_from_bytes
from v2vsim.world.state import WorldState

HANG_TIMEOUT_S = 60.0  # a live CAV that sends nothing for this long is treated as lost
MAX_VIS_BYTES = 1 << 20  # the visible-ids side channel: a few hundred ids
# Side channels between our own processes, not V2V messages: not channel-modelled, not counted.
SIDE_KINDS = ("vis", "scan")


class Mailbox:
    """Raw messages by (kind, frame, sender), filled on zenoh's thread, read on the main thread.

    limits: kind -> the longest message that could be accepted; longer ones are not kept, only
    counted (`rejected`), so a flood of oversized messages cannot pile up unread."""

    def __init__(self, limits: dict[str, int] | None = None) -> None:
        self.cond = threading.Condition()
        self.raw: dict[tuple[str, int], list[tuple[str, bytes]]] = defaultdict(list)  # (sender key, bytes)
        self.unframed: list[tuple[str, str, bytes]] = []  # could not even read a frame number
        self.rejected: list[tuple[str, str]] = []  # (kind, reason) decided on arrival
        self.worlds: dict[int, bytes] = {}
        self.done = False
        self.done_at = 0.0  # time.monotonic() of the first done
        self.last_world = 0.0  # time.monotonic() of the latest world
        self.limits = dict(limits or {})

    def put(self, kind: str, sender: str, data: bytes) -> None:
        limit = self.limits.get(kind, 0)
        if limit and len(data) > limit:
            if kind not in SIDE_KINDS:
                with self.cond:
                    self.rejected.append((kind, "size_mismatch"))
            return
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
    if kind == "scan":
        return scan_frame(data)
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
    decoder = EgoDecoder(ego_wire_spec(sc, c, f), args.run_id, frozenset(args.cavs), key)

    side = ["vis", "scan"] if sc.output.rerun else ["vis"]
    box = Mailbox({kind: decoder.max_bytes(kind) for kind in kinds} | {"vis": MAX_VIS_BYTES,
                                                                       "scan": max_scan_bytes(sc)})
    for kind in [*kinds, *side]:
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
    recorder = Recorder(out_dir / "recording.rrd", sc, list(models), list(args.cavs), me,
                        static) if sc.output.rerun else None
    checkpoints = method_checkpoints(sc, tuple(models))
    summary = RunSummary(scenario=sc, ego=me, methods=list(models),
                         untrained=all(v is None for v in checkpoints.values()), checkpoints=checkpoints,
                         skipped=[m for m in methods if m not in models])
    timer = StageTimer()
    after = AfterFusion(scores, recorder, timer)
    bus.ready()
    t_start = time.monotonic()
    frames_done = 0
    status = "complete"
    realtime = sc.transport.clock == "realtime"
    k = -1
    working = 0  # the frame being waited for or worked on (for a crash's status)
    code = 0
    try:
        while k + 1 < args.frames:
            working = k + 1
            with timer.stage("wait"):
                got = _wait_world(box, bus, k + 1, realtime)
            if got == "done":
                status = f"ended early: the driver finished {_after(k)}" if not realtime else status
                break
            if got == "died":
                status, code = f"driver died {_after(k)}", 1
                print(f"v2vsim-ego {me}: the driver died {_after(k)}; writing results and stopping",
                      file=sys.stderr, flush=True)
                break
            if got == "interrupted":  # Ctrl-C reached the driver before it reached us
                status = f"interrupted after {frames_done} frames"
                break
            if isinstance(got, str):
                status = f"ended early: the driver stopped {_after(k)} ({got})"
                break
            k, data = got
            working = k
            with timer.stage("comm"):
                world = world_from_bytes(data, static)
            ego_actor = world.actor(me)
            if ego_actor is None:
                status = f"ego {me} left the simulation at frame {k}"
                break
            ego_poses[k] = ego_actor.pose
            near = cavs_in_range(world, me, sc.comm.range_m)
            present = [a.id for a in world.cavs if a.id in args.cavs]
            if not realtime:
                with timer.stage("wait"):
                    _wait_messages(box, bus, k, present, [*kinds, *side], lost)
            else:  # lockstep marks a CAV lost at the first frame whose messages it never sent (above);
                # the driver and CAVs may be frames ahead, so a CAV gone by now may have sent frame k
                for cav in present:
                    if cav not in lost and _died(bus, cav):
                        lost[cav] = k
            for cav in lost:
                stats.record_lost_agent(cav)
            with timer.stage("comm"):
                inp, visible, scans = _collect(box, k, world, me, kinds, inboxes, ego_poses, decoder, args)
                events = {kind: ib.take_events() for kind, ib in inboxes.items()}
                links = events["features"]  # the message every method fuses: what the links show
                inp.features = {s: decompress(compressor, v) for s, v in inp.features.items()}
            with timer.stage("ground_truth"):
                gt = bev_ground_truth(world, me, sc.bev, visible, assets=assets)
                boxes_gt, ids = gt_boxes(world, me, sc.bev)
                boxes_gt = boxes_gt[[i in visible for i in ids]] if len(ids) else boxes_gt
            preds = predict_all(models, inp, sc.bev.cells)
            for m, pred in preds.items():
                timer.add(f"fusion.{m}", pred.ms - pred.decode_ms)
                timer.add(f"decoding.{m}", pred.decode_ms)
            sent = {m: _bytes_for(m, inboxes) for m in preds}
            for ib in inboxes.values():
                ib.take_bytes()
            # Scoring and recording run beside the next frame's fusion; frames stay in order.
            after.submit(FusedFrame(k, world, gt, boxes_gt, preds, inp, sent, links, scans))
            frames_done += 1
            summary.neighbours.append(near)
            timer.frame_done()
            if not realtime:
                with timer.stage("comm"):
                    bus.put("ack", json.dumps({"ego": me, "frame": k}).encode())
            report_progress(f"ego.{me}", k + 1, args.frames, delivered=stats.delivered, dropped=stats.dropped,
                            out_of_range=stats.out_of_range)
    except Stop:
        # The runner stops everyone when the driver dies: say so rather than "interrupted".
        died = bus.driver_gone() and bus.farewell(DRIVER) is None
        status = f"driver died {_after(k)}" if died else f"interrupted after {frames_done} frames"
        raise
    except Exception as e:
        status = _crashed(f"at frame {working}", e)
        raise
    finally:
        with _signals_deferred():  # a second Ctrl-C or the runner's SIGINT must not cut the files short
            late_error: BaseException | None = None
            try:
                after.close()  # every fused frame scored (and recorded) before the files are written
            except Exception as e:
                status = _crashed(f"after frame {k}", e)
                late_error, code = e, 1
            _reject_leftovers(box, kinds, inboxes, decoder)
            summary.timing = timer.to_json()
            summary.frames = frames_done
            summary.sim_s = (k + 1) / sc.rate_hz
            summary.status = status
            summary.wall_s = time.monotonic() - t_start
            summary.lost_agents = dict(lost)
            by_kind = {kind: ib.stats for kind, ib in inboxes.items()}
            by_kind["control"] = _control_rejections(bus, stats)
            write_outputs(out_dir, summary, scores, stats, by_kind, box_iou)
            if recorder is not None:
                recorder.close()
        if late_error is not None:
            raise late_error
    return code


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
                    score_all(job.preds, job.gt, job.boxes_gt, self.scores)
                    for m, n in job.sent.items():
                        self.scores[m].bytes.append(n)
                if self.recorder is not None:
                    with self.timer.stage("recording"):
                        self.recorder.log_frame(job.k, job.world, job.gt, job.boxes_gt, job.preds, job.inp,
                                                job.links, job.scans,
                                                {m: self.scores[m].vehicle.last_iou for m in job.preds})
            except BaseException as e:  # noqa: BLE001 - handed to the main thread as is
                self.error = e


def _crashed(where: str, e: BaseException) -> str:
    """metrics.json status of a crash: where, the exception type and its message on one line."""
    return f"crashed {where}: {type(e).__name__}: {' '.join(str(e).split())[:300]}"


def _after(k: int) -> str:
    return f"after frame {k}" if k >= 0 else "before frame 0"


@contextmanager
def _signals_deferred() -> Iterator[None]:
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


def _control_rejections(bus: Bus, total: CommStats) -> CommStats:
    """The control messages (done, world, vis, ...) the bus dropped, also counted in comm.rejected."""
    control = CommStats()
    for (_kind, reason), n in bus.control_rejections().items():
        control.rejected_reasons[reason] += n
        total.rejected_reasons[reason] += n
    return control


def _reject_leftovers(box: Mailbox, kinds: list[str], inboxes: dict[str, Inbox], decoder: EgoDecoder) -> None:
    """Messages never fused (e.g. claiming a frame the run never reached) still get validated and counted."""
    with box.cond:
        leftovers = [(kind, s, data) for (kind, _f), table in box.raw.items() if kind in kinds for s, data in table]
        leftovers += [(kind, s, data) for kind, s, data in box.unframed if kind in kinds]
        early, box.rejected = box.rejected, []
        box.raw.clear()
        box.unframed.clear()
    for kind, reason in early:
        _count_rejected(inboxes, kind, reason)
    for kind, sender, data in leftovers:
        decoder.receive(kind, data, sender, _stats_for(inboxes, kind))


def _stats_for(inboxes: dict[str, Inbox], kind: str) -> list[CommStats]:
    """Where a rejection of `kind` is counted: per kind, and every kind also in comm.rejected (the
    features inbox's stats)."""
    return [inboxes[kind].stats] + ([inboxes["features"].stats] if kind != "features" else [])


def _count_rejected(inboxes: dict[str, Inbox], kind: str, reason: str) -> None:
    for s in _stats_for(inboxes, kind):
        s.record_rejected(reason)


def _bytes_for(method: str, inboxes: dict[str, Inbox]) -> int:
    kind = message_kind(method)
    return 0 if kind is None else inboxes[kind].bytes_this_frame


def _put_world(box: Mailbox, data: bytes) -> None:
    try:
        frame = int(json.loads(data)["frame"])
    except (ValueError, KeyError, TypeError):
        return
    with box.cond:
        box.worlds[frame] = data
        box.last_world = time.monotonic()
        box.cond.notify_all()


def _set_done(box: Mailbox) -> None:
    with box.cond:
        if not box.done:
            box.done, box.done_at = True, time.monotonic()
        box.cond.notify_all()


def _notify(box: Mailbox) -> None:
    with box.cond:
        box.cond.notify_all()


def _wait_world(box: Mailbox, bus: Bus, k: int, realtime: bool) -> tuple[int, bytes] | str:
    """World k (lockstep), or the newest world from k on (realtime: frames we fell behind on are skipped),
    or why none will come: "done" (the driver finished), "died" (its token dropped without a bye or
    done), "interrupted" (it was stopped by SIGINT: the run's Ctrl-C), or the reason it gave in its bye."""
    gone_at = None
    with box.cond:
        while True:
            ready = [f for f in box.worlds if f >= k]
            if ready and (realtime or k in box.worlds):
                f = max(ready) if realtime else k
                data = box.worlds[f]
                for old in [x for x in box.worlds if x <= f]:
                    del box.worlds[old]
                return f, data
            now = time.monotonic()
            gone = bus.driver_gone()
            # A verified done is the driver's; without comm.auth anyone could have sent it, so it is
            # believed once the driver is gone too, or when no world came for DONE_GRACE_S since.
            if box.done and (bus.authenticated or gone or now - max(box.done_at, box.last_world) > DONE_GRACE_S):
                return "done"
            if gone:
                gone_at = gone_at or now
                bye = bus.farewell(DRIVER)
                if bye is not None and bye.get("code") == 128 + signal.SIGINT:
                    return "interrupted"
                if bye is not None:
                    return f"exit {bye.get('code')}: {bye.get('why', '')}"
                if now - gone_at > DRIVER_GRACE_S:
                    return "died"
            box.cond.wait(0.2 if gone or box.done else 0.5)


def _died(bus: Bus, cav: str) -> bool:
    """Its token dropped without a clean bye (a CAV whose vehicle left says bye with code 0)."""
    if not bus.was_alive(f"cav.{cav}") or bus.is_alive(f"cav.{cav}"):
        return False
    bye = bus.farewell(f"cav.{cav}")
    return bye is None or bye.get("code") != 0


def _wait_messages(box: Mailbox, bus: Bus, k: int, present: list[str], kinds: list[str],
                   lost: dict[str, int]) -> None:
    """Lockstep: wait until every live CAV's frame-k messages of `kinds` are in (or it is lost)."""
    deadline = time.monotonic() + HANG_TIMEOUT_S
    with box.cond:
        while True:
            missing = [c for c in present if c not in lost and not all(
                any(s == c for s, _ in box.raw.get((kind, k), ())) for kind in kinds)]
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
             ego_poses: dict[int, Pose], decoder: EgoDecoder,
             args: AgentArgs) -> tuple[FusionInputs, set[str], dict[str, Scan]]:
    """Decode frame k's messages, pass them through the channel, and gather what is fusable now;
    also the ids the CAVs saw (visible-vehicle ground truth) and their scans (for the recording)."""
    realtime = args.scenario.transport.clock == "realtime"
    now = world.time
    with box.cond:
        raw = {kind: box.raw.pop((kind, k), []) for kind in [*kinds, *SIDE_KINDS]}
        # messages of earlier frames that came late (realtime, or a rogue sender): judged now
        for (kind, f), table in list(box.raw.items()):
            if f < k:
                if kind in kinds:
                    raw[kind] += table
                del box.raw[(kind, f)]
        unframed, box.unframed = box.unframed, []
        early, box.rejected = box.rejected, []
    for kind, reason in early:
        _count_rejected(inboxes, kind, reason)
    for kind, sender, data in unframed:
        if kind in kinds:
            decoder.receive(kind, data, sender, _stats_for(inboxes, kind))  # too short to be anything: counted
    visible: set[str] = set()
    for _sender, data in raw["vis"]:
        try:
            visible.update(str(i) for i in json.loads(data)["ids"])
        except (ValueError, KeyError, TypeError):
            pass  # ground-truth side channel between our own processes, not a V2V message
    scans: dict[str, Scan] = {}
    for sender, data in raw["scan"]:
        try:
            scans[sender] = decode_scan(data, sender, args.scenario)
        except ValueError as e:
            print(f"v2vsim-ego: frame {k}: {e}; not recorded", file=sys.stderr)
    for kind in kinds:
        for sender, data in raw[kind]:
            msg = decoder.receive(kind, data, sender, _stats_for(inboxes, kind))
            if msg is None:
                inboxes[kind].mark_rejected(sender)
                continue
            ego_then = ego_poses.get(msg.frame, ego_poses[k])
            send_time = now if realtime else msg.capture_time
            inboxes[kind].offer(msg, len(data), send_time, distance(msg.sender_pose, ego_then.as_tuple()),
                                receiver_pose=ego_then.as_tuple(), world=world)  # geometry for comm.channel tr37885
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
                # float16 [C/r, F, F] (a sparse message scattered back); decompress() makes it float32 [C, F, F]
                inp.features[s] = dense_payload(msg, decoder.spec["features"].payload)
            elif kind == "points":
                inp.points[s] = msg.payload.astype(np.float32)
            else:
                inp.outputs[s] = (msg.payload.astype(np.float32), msg.extras["boxes"].astype(np.float32))
    return inp, visible, scans


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("ego", argv)
    return run_agent(args, "ego", args.cav, lambda bus: ego_loop(args, bus))


if __name__ == "__main__":
    sys.exit(main())
