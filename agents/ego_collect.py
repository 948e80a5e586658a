"""Message collection for one ego frame: decode the frame's messages, put them through the channel
model and gather what is fusable; count every rejection, including those of messages never fused.
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from collections.abc import Mapping

import numpy as np

from agents.args import AgentArgs
from agents.ego_mailbox import SIDE_KINDS, Mailbox
from v2vsim.comm.codec import EVIDENCE, Message
from v2vsim.comm.inbox import Inbox, distance
from v2vsim.comm.share import dense_payload
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import EgoDecoder, message_kind
from v2vsim.perception.evidence import evidence_cells, unpack
from v2vsim.perception.fuse import FusionInputs
from v2vsim.perception.motion import OutputMessage, compensate_outputs
from v2vsim.recording.scan import Scan, decode_scan
from v2vsim.world.geometry import Pose, relative_pose
from v2vsim.world.state import WorldState


def collect(box: Mailbox, k: int, world: WorldState, me: str, kinds: list[str], inboxes: dict[str, Inbox],
             ego_poses: dict[int, Pose], decoder: EgoDecoder, args: AgentArgs,
             own_decoder: EgoDecoder | None = None) -> tuple[FusionInputs, set[str], dict[str, Scan]]:
    """Decode frame k's messages, pass them through the channel, and gather what is fusable now;
    also the ids the CAVs saw (visible-vehicle ground truth) and their scans (for the recording). With
    `own_decoder` (a compressed wire) the ego's uncompressed map from its own CAV goes into FusionInputs.own."""
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
        box.mark_collected(k)
        early, box.rejected = box.rejected, Counter()
    if box.on_collect is not None:  # a recorded run: exactly what this frame works on
        box.on_collect(k, raw, early)
    for (kind, reason), n in early.items():
        if kind in inboxes:
            _count_rejected(inboxes, kind, reason, n)
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
    # a message captured after the frames the window admits would wait in the channel model until the run ends
    latest = None if box.window is None else now + (box.window.ahead + 1) / args.scenario.rate_hz
    for kind in kinds:
        for sender, data in raw[kind]:
            msg = decoder.receive(kind, data, sender, _stats_for(inboxes, kind), verified=box.check is not None)
            if msg is not None and latest is not None and msg.capture_time > latest:
                _count_rejected(inboxes, kind, "out_of_window")
                msg = None
            if msg is None:
                inboxes[kind].mark_rejected(sender)
                continue
            ego_then = ego_poses.get(msg.frame, ego_poses[k])
            send_time = now if realtime else msg.capture_time
            inboxes[kind].offer(msg, len(data), send_time, distance(msg.sender_pose, ego_then.as_tuple()),
                                receiver_pose=ego_then.as_tuple(), world=world)  # geometry for comm.channel tr37885
    ego_pose = ego_poses[k]
    compensate = args.scenario.comm.compensation
    # fuse at the deadline, as of the frame's capture instant: a message of frame k that arrived by then is aligned
    deadline = now + args.scenario.fusion_deadline_s
    fusable = {kind: inboxes[kind].ready(deadline, as_of=now) for kind in kinds}
    senders = [me] + sorted({s for table in fusable.values() for s in table} - {me})
    rel = np.zeros((len(senders), 3), np.float32)
    # each kind's own capture poses: a sender's outputs may be a frame older than its features, and a method
    # must warp what it fuses with the pose that message was captured at
    by_kind = {kind: np.zeros((len(senders), 3), np.float32) for kind in fusable}
    inp = FusionInputs(senders=senders, rel_poses=rel, poses_by_kind=by_kind)
    posed: set[int] = set()
    for kind, table in fusable.items():
        for s, msg in table.items():
            i = senders.index(s)
            x, y, z, yaw = inboxes[kind].sender_pose(msg)
            by_kind[kind][i] = relative_pose(ego_pose, Pose(x, y, z, yaw))
            if i not in posed:  # rel_poses: the first kind's (features come first)
                rel[i] = by_kind[kind][i]
                posed.add(i)
            if EVIDENCE in msg.extras and s not in inp.evidence:
                grid = _evidence_of(msg, evidence_cells(decoder.spec["features"].payload[-1]))
                if grid is not None:
                    inp.evidence[s] = grid
            if kind == "features":
                # float16 [C/r, F, F] (a sparse message scattered back); decompress() makes it float32 [C, F, F]
                inp.features[s] = dense_payload(msg, decoder.spec["features"].payload)
                prev = inboxes[kind].previous(s) if compensate and s != me else None
                if prev is not None and msg.capture_time > now - 1e-9:
                    prev = None  # fused aligned: nothing to compensate
                if prev is not None:
                    inp.feature_ages[s] = now - msg.capture_time
                    inp.previous_features[s] = (dense_payload(prev, decoder.spec["features"].payload),
                                                np.asarray(relative_pose(Pose(x, y, z, yaw),
                                                                         _pose_as_known(prev, msg, (x, y, z, yaw))),
                                                           np.float32),
                                                msg.capture_time - prev.capture_time)
            elif kind == "points":
                inp.points[s] = msg.payload.astype(np.float32)
            else:
                inp.outputs[s] = (msg.payload.astype(np.float32), msg.extras["boxes"].astype(np.float32))
                if compensate and s != me:
                    inp.outputs[s] = _moved_outputs(inp.outputs[s], msg, (x, y, z, yaw), inboxes[kind].previous(s),
                                                    now - msg.capture_time, args.scenario.bev.size_m)
    if own_decoder is not None:
        for sender, data in raw["own"]:
            msg = own_decoder.receive("features", data, sender, (),  # its own process: a failure is not V2V's
                                      verified=box.check is not None)
            if msg is not None and msg.sender_id == me and msg.frame == k:
                inp.own = msg.payload
    return inp, visible, scans


def _evidence_of(msg: Message, cells: int) -> np.ndarray | None:
    """A message's free-space evidence as a grid; None for a cell both free and occupied (no sender's honest rays
    make one: such evidence is worth nothing, and the claims it came with are judged without it)."""
    try:
        return unpack(msg.extras[EVIDENCE].tobytes(), cells)
    except ValueError:
        return None


def _moved_outputs(outputs: tuple[np.ndarray, np.ndarray], msg: Message, pose: tuple[float, ...],
                   prev: Message | None, age_s: float, bev_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """comm.compensation on, late fusion: a neighbour's maps and boxes moved by each object's velocity from its
    two latest output messages (v2vsim.perception.motion)."""
    if prev is None:
        return outputs
    old = OutputMessage(prev.payload.astype(np.float32), prev.extras["boxes"].astype(np.float32),
                        _pose_as_known(prev, msg, pose), prev.capture_time)
    return compensate_outputs(OutputMessage(*outputs, pose, msg.capture_time), old, age_s, bev_size_m=bev_size_m)


def control_rejections(refused: Mapping[tuple[str, str], int], total: CommStats) -> CommStats:
    """The control messages (done, world, vis, ...) this ego's bus dropped, and those the driver did (acks, commands:
    kinds `<kind>@driver`), also counted in comm.rejected."""
    control = CommStats()
    for (_kind, reason), n in refused.items():
        control.rejected_reasons[reason] += n
        total.rejected_reasons[reason] += n
    return control


def reject_leftovers(box: Mailbox, kinds: list[str], inboxes: dict[str, Inbox], decoder: EgoDecoder) -> None:
    """Messages never fused (e.g. claiming a frame the run never reached) still get validated and counted."""
    with box.cond:
        leftovers = [(kind, s, data) for (kind, _f), table in box.raw.items() if kind in kinds for s, data in table]
        early, box.rejected = box.rejected, Counter()
        box.raw.clear()
    for (kind, reason), n in early.items():
        if kind in inboxes:
            _count_rejected(inboxes, kind, reason, n)
    for kind, sender, data in leftovers:
        decoder.receive(kind, data, sender, _stats_for(inboxes, kind), verified=box.check is not None)


def _stats_for(inboxes: dict[str, Inbox], kind: str) -> list[CommStats]:
    """Where a rejection of `kind` is counted: per kind, and every kind also in comm.rejected (the
    features inbox's stats)."""
    return [inboxes[kind].stats] + ([inboxes["features"].stats] if kind != "features" else [])


def _count_rejected(inboxes: dict[str, Inbox], kind: str, reason: str, n: int = 1) -> None:
    for s in _stats_for(inboxes, kind):
        s.record_rejected(reason, n)


def bytes_for(method: str, inboxes: dict[str, Inbox]) -> int:
    kind = message_kind(method)
    return 0 if kind is None else inboxes[kind].bytes_this_frame


def _pose_as_known(prev: Message, msg: Message, known: tuple[float, ...]) -> Pose:
    """The sender's pose at `prev`'s capture as the receiver knows it: with the same error as `known`, its pose of
    the newer `msg` (comm.pose_noise; a receiver's error in a sender's pose changes little within a few frames,
    and drawing new noise here would change the noise stream of every run with compensation on)."""
    return Pose(*(float(p + k - m) for p, k, m in zip(prev.sender_pose, known, msg.sender_pose, strict=True)))
