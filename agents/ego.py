"""Ego fusion process: receives every CAV's messages, puts them through the channel model, warps
them into its own frame with the sender's pose at capture time, fuses with every method under
test, and scores each against ground truth. Writes metrics.json, report.md, plots and the Rerun
recording when the run ends, is interrupted, or loses agents.

lockstep: frame k is fused once every live CAV's frame-k messages are in (a CAV that dies is
noticed through zenoh liveliness within milliseconds, or after HANG_TIMEOUT_S if it hangs).
realtime: frame k is fused when its world arrives, with whatever has arrived by then.

Every received V2V message goes through one decode path (v2vsim.comm.wire_spec.EgoDecoder, with
the scenario's exact shapes and bounds); a rejected one is counted, never fatal. metrics.json
`status` says how the run ended: complete, degraded (every frame, but CAVs lost or a method with no score:
v2vsim.evaluation.status, exit 0), ended early (the driver finished or stopped), driver died (its liveliness
token dropped without a bye: the ego stops within seconds), interrupted, or crashed at frame k (the exception
is re-raised, exit 1).

The run in three parts: its set-up (agents.ego_setup.build_ego, one `Ego`), the frame loop here (`step`, one
frame at a time, on the per-run `EgoRun`), and its finish (agents.ego_finish.finish, the result files).
"""

from __future__ import annotations

import json
import sys
import time
from functools import partial

import numpy as np
import torch

from agents.args import AgentArgs, parse_agent_args
from agents.bus import Bus
from agents.ego_collect import bytes_for, collect
from agents.ego_finish import crashed_status, finish
from agents.ego_mailbox import cav_died, wait_messages, wait_world
from agents.ego_replay import ReplayBus
from agents.ego_scoring import FusedFrame
from agents.ego_setup import MAX_VIS_BYTES, Ego, EgoRun, build_ego
from agents.lifecycle import Stop, receive_bound, run_agent
from agents.progress import report_progress
from v2vsim.comm.control import DRIVER
from v2vsim.comm.inbox import LinkEvent
from v2vsim.comm.wire_spec import ego_wire_spec
from v2vsim.config import Scenario
from v2vsim.control.pilot import PilotStep
from v2vsim.evaluation.fuse_and_score import predict_all
from v2vsim.evaluation.gt import bev_ground_truth, gt_boxes, map_layer
from v2vsim.evaluation.metrics import cavs_in_range
from v2vsim.perception.build import build_agent_encoder, decompress
from v2vsim.perception.consistency import MAX_CELLS
from v2vsim.perception.extrapolate import extrapolate_features
from v2vsim.perception.fuse import FusionInputs, Prediction
from v2vsim.perception.plan import ModelPlan, plan_models
from v2vsim.recording.scan import Scan, max_scan_bytes
from v2vsim.sensors.scene import GROUND_BUILDING, MapAssets
from v2vsim.world.serialize import MAX_STATIC_BYTES, MAX_WORLD_BYTES, world_from_bytes
from v2vsim.world.state import WorldState


def largest_message(sc: Scenario, encoder: torch.nn.Module, ratio: int) -> int | None:
    """The longest message the ego of `sc` accepts, whatever its kind (None: some kind has no bound): every
    V2V kind's (the uncompressed map from its own CAV included), the side channels, a world, the static map.
    Its zenoh session drops a longer message before reassembling it (agents.lifecycle.receive_bound); `ratio`: the
    wire's channel compression (ModelPlan.wire_ratio)."""
    c, f = encoder.out_channels, encoder.out_cells
    specs = [*ego_wire_spec(sc, c, f, ratio).items(), ("features", ego_wire_spec(sc, c, f, 1)["features"])]
    sizes = [ks.max_message_bytes(kind) for kind, ks in specs]
    if any(n is None for n in sizes):
        return None
    return max([*sizes, MAX_VIS_BYTES, max_scan_bytes(sc), MAX_WORLD_BYTES, MAX_STATIC_BYTES])  # type: ignore[list-item]


def ego_loop(args: AgentArgs, bus: Bus, replay: ReplayBus | None = None, encoder: torch.nn.Module | None = None,
             plan: ModelPlan | None = None) -> int:
    """The ego's whole run. `replay` (v2vsim evaluate): `bus` is a ReplayBus that feeds a recording's frames
    straight into the mailbox, after the arrival checks they passed when recorded; everything else is the same.
    `encoder`: the CAVs' encoder, built already (main sizes its zenoh session by it) from `plan`, the scenario's
    models resolved once (None: resolved in build_ego)."""
    ego = build_ego(args, bus, replay, encoder, plan)
    bus.ready()
    run = EgoRun(t_start=time.monotonic())
    try:
        while run.k + 1 < args.frames:
            if not step(ego, run):
                break
    except Stop:
        # The runner stops everyone when the driver dies: say so rather than "interrupted".
        died = bus.driver_gone() and bus.farewell(DRIVER) is None
        run.status = f"driver died {_after(run.k)}" if died else f"interrupted after {run.frames_done} frames"
        raise
    except Exception as e:
        run.status = crashed_status(f"at frame {run.working}", e)
        raise
    finally:
        finish(ego, run)
    return run.code


def step(ego: Ego, run: EgoRun) -> bool:
    """The next frame, from its world to its ack; False when the run ends here (run.status says why)."""
    run.working = run.k + 1
    got = next_world(ego, run)
    if got is None:
        return False
    run.k, data = got
    k = run.working = run.k
    world = read_world(ego, k, data)
    ego_actor = world.actor(ego.me)
    if ego_actor is None:
        run.status = f"ego {ego.me} left the simulation at frame {k}"
        return False
    run.ego_poses[k] = ego_actor.pose
    for f in [f for f in run.ego_poses if f < k - ego.window.behind - 1]:  # older messages are refused
        del run.ego_poses[f]
    near = cavs_in_range(world, ego.me, ego.sc.comm.range_m)
    present = [a.id for a in world.cavs if a.id in ego.args.cavs]
    await_messages(ego, run, k, present)
    for cav in run.lost:
        ego.stats.record_lost_agent(cav)
    fused, ack = fuse(ego, run, k, world)
    return hand_on(ego, run, fused, ack, near)


def next_world(ego: Ego, run: EgoRun) -> tuple[int, bytes] | None:
    """The next frame's world as (frame, bytes), or None when none will come: run.status (and run.code) say why."""
    k, me = run.k, ego.me
    with ego.timer.stage("wait"):
        got = wait_world(ego.box, ego.bus, k + 1, ego.realtime)
    if got == "done":
        run.status = f"ended early: the driver finished {_after(k)}" if not ego.realtime else run.status
    elif got == "died":
        run.status, run.code = f"driver died {_after(k)}", 1
        print(f"v2vsim-ego {me}: the driver died {_after(k)}; writing results and stopping",
              file=sys.stderr, flush=True)
    elif got == "interrupted":  # Ctrl-C reached the driver before it reached us
        run.status = f"interrupted after {run.frames_done} frames"
    elif isinstance(got, str) and got.startswith("no world"):  # the driver is there but silent: a hang
        run.status, run.code = f"stalled {_after(k)}: {got} from the driver", 1
        print(f"v2vsim-ego {me}: {got} from the driver {_after(k)}; writing results and stopping",
              file=sys.stderr, flush=True)
    elif isinstance(got, str):
        run.status = f"ended early: the driver stopped {_after(k)} ({got})"
    else:
        return got
    return None


def read_world(ego: Ego, k: int, data: bytes) -> WorldState:
    """Frame k's world, decoded (once for every replay of a recording in this process), and taped."""
    if ego.tape is not None:
        ego.tape.world(k, data)
    with ego.timer.stage("comm"):
        return (world_from_bytes(data, ego.static) if ego.replay is None
                else ego.replay.once(("world",), partial(world_from_bytes, data, ego.static)))


def await_messages(ego: Ego, run: EgoRun, k: int, present: list[str]) -> None:
    """Lockstep: wait until every present CAV's frame-k messages are in, or it is lost (run.lost); realtime:
    wait for nothing, only mark lost the CAVs that are gone."""
    box, bus, me, wire, lost = ego.box, ego.bus, ego.me, ego.wire, run.lost
    lost_after = ego.sc.transport.lost_after_s
    if not ego.realtime:
        with ego.timer.stage("wait"):
            if wire.silent:  # only `none`: its own map, and what every CAV saw
                wait_messages(box, bus, k, [me] if me in present else [], wire.kinds, lost, lost_after)
                wait_messages(box, bus, k, present, wire.side, lost, lost_after)
            else:
                wait_messages(box, bus, k, present, [kd for kd in [*wire.kinds, *wire.side] if kd != "points"], lost,
                              lost_after)
            if "points" in wire.kinds:
                wait_messages(box, bus, k, [c for c in present if c in wire.lidar_cavs], ["points"], lost,
                              lost_after)
            if wire.own_decoder is not None and me in present:
                wait_messages(box, bus, k, [me], ["own"], lost, lost_after)
    else:  # lockstep marks a CAV lost at the first frame whose messages it never sent (above);
        # the driver and CAVs may be frames ahead, so a CAV gone by now may have sent frame k
        for cav in present:
            if cav not in lost and cav_died(bus, cav):
                lost[cav] = k


def fusion_inputs(ego: Ego, run: EgoRun, k: int, world: WorldState
                  ) -> tuple[FusionInputs, set[str], dict[str, Scan], list[LinkEvent]]:
    """Frame k's fusion inputs (feature maps decompressed, late ones extrapolated under comm.compensation), the
    vehicles some CAV saw, the CAVs' scans and what each feature link did."""
    wire, nets, me = ego.wire, ego.nets, ego.me
    with ego.timer.stage("comm"):
        inp, visible, scans = collect(ego.box, k, world, me, wire.kinds, ego.inboxes, run.ego_poses, wire.decoder,
                                      ego.args, wire.own_decoder)
        events = {kind: ib.take_events() for kind, ib in ego.inboxes.items()}
        links = events["features"]  # the message every method fuses: what the links show
        # float32 [C, F, F] each; its own map never went on the air: the uncompressed one where it came
        inp.features = {s: decompress(None, inp.own) if s == me and inp.own is not None
                        else decompress(wire.compressor, v) for s, v in inp.features.items()}
    if nets.extrapolations:
        with ego.timer.stage("compensation"):
            inp.previous_features = {s: (decompress(wire.compressor, old), rel, gap)
                                     for s, (old, rel, gap) in inp.previous_features.items()}
            inp.extrapolated = {m: extrapolate_features(e, inp, ego.sc.bev.size_m)
                                for m, e in nets.extrapolations.items()}
    return inp, visible, scans, links


def fuse(ego: Ego, run: EgoRun, k: int, world: WorldState) -> tuple[FusedFrame, dict]:
    """Frame k fused by every method (and planned on, closed loop): the frame for the scoring thread and the ack."""
    sc, me, nets, timer, replay = ego.sc, ego.me, ego.nets, ego.timer, ego.replay
    inp, visible, scans, links = fusion_inputs(ego, run, k, world)
    with timer.stage("ground_truth"):
        gt, boxes_gt = (ground_truth(world, me, sc, visible, ego.assets) if replay is None else
                        replay.once(("ground_truth", me, frozenset(visible)),
                                    partial(ground_truth, world, me, sc, visible, ego.assets)))
    flagged: set[str] = set()
    # with the defence, `none` (the ego's own features decoded) runs first and the check reuses its map for the ego:
    # the ego is never excluded, so what `none` fuses does not depend on the check, and it is decoded once
    first = {"none": nets.models["none"]} if nets.sender_check is not None and "none" in nets.models else {}
    own = predict_all(first, inp, sc.bev.cells, nets.precision, ego.memo) if first else {}
    if nets.sender_check is not None:  # the map's drivable area is map knowledge, not the frame's ground truth
        with timer.stage("consistency"):
            pose = world.actor(me).pose  # type: ignore[union-attr]
            buildings = None
            if sc.defence.evidence:  # the map's buildings, for the senders' walls (v2vsim/perception/evidence_check)
                buildings = map_layer(ego.assets.ground, pose, sc.bev.size_m, MAX_CELLS, GROUND_BUILDING)
            inp, flagged = nets.sender_check.check(k, inp, gt["road"], buildings, (pose.x, pose.y, pose.yaw),
                                                   own.get("none"))
    rest = {m: model for m, model in nets.models.items() if m not in own}
    later = predict_all(rest, inp, sc.bev.cells, nets.precision, ego.memo, ego.pool,
                        cost=None if ego.pool is None else timer.method_ms())
    preds = {m: p for m in nets.models if (p := own.get(m) or later.get(m)) is not None}  # the models' order
    for m, pred in preds.items():
        timer.add(f"fusion.{m}", pred.ms - pred.decode_ms)
        timer.add(f"decoding.{m}", pred.decode_ms)
    sent = {m: bytes_for(m, ego.inboxes) for m in preds}
    for ib in ego.inboxes.values():
        ib.take_bytes()
    drive, ack = plan(ego, k, world, preds)
    return FusedFrame(k, world, gt, boxes_gt, preds, inp, sent, links, scans, drive, frozenset(flagged),
                      sc.defence.exclude), ack


def plan(ego: Ego, k: int, world: WorldState, preds: dict[str, Prediction]) -> tuple[PilotStep | None, dict]:
    """Closed loop: what this ego's vehicle does on control.method's output (None in open loop), and frame k's
    ack, which carries its command to the driver."""
    ack: dict = {"ego": ego.me, "frame": k}
    drive = None
    if ego.pilot is not None:
        with ego.timer.stage("planning"):
            drive = ego.pilot.step(world, preds.get(ego.sc.control.method))  # type: ignore[union-attr]
        if drive is not None:
            ack["command"] = {"accel": round(drive.plan.accel, 4)}
    return drive, ack


def hand_on(ego: Ego, run: EgoRun, fused: FusedFrame, ack: dict, near: int | None) -> bool:
    """A fused frame to the scoring thread and its ack to the driver; False when the driven vehicle's route is
    done (it arrives: its run is complete)."""
    k, me, drive = fused.k, ego.me, fused.drive
    # Scoring and recording run beside the next frame's fusion; frames stay in order.
    ego.after.submit(fused)
    run.frames_done += 1
    ego.summary.neighbours.append(near)
    ego.timer.frame_done()
    ego.args.startup.mark("first_frame")
    if not ego.realtime or ego.pilot is not None:  # realtime: no ack awaited, but a plan must reach the driver
        with ego.timer.stage("comm"):
            ego.bus.put("ack", json.dumps(ack).encode())
    stats = ego.stats
    report_progress(ego.progress_name, k + 1, ego.args.frames, delivered=stats.delivered, dropped=stats.dropped,
                    out_of_range=stats.out_of_range)
    if drive is not None and drive.logged.finished:  # its route is done: it arrives, its run is complete
        print(f"v2vsim-ego {me}: route completed at frame {k} ({drive.logged.time:.1f} s)", file=sys.stderr,
              flush=True)
        return False
    return True


def ground_truth(world: WorldState, me: str, sc: Scenario, visible: set[str],
                 assets: MapAssets) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The ego's BEV ground truth masks and its scored boxes [K, 5] (the vehicles some CAV saw)."""
    gt = bev_ground_truth(world, me, sc.bev, visible, assets=assets)
    boxes_gt, ids = gt_boxes(world, me, sc.bev)
    return gt, boxes_gt[[i in visible for i in ids]] if len(ids) else boxes_gt


def _after(k: int) -> str:
    """Where in the run frame k is, for a status: after it, or before the first."""
    return f"after frame {k}" if k >= 0 else "before frame 0"


def main(argv: list[str] | None = None) -> int:
    """The ego process: its zenoh session sized by the longest message it accepts, then its run."""
    args = parse_agent_args("ego", argv)
    torch.set_num_threads(1)
    plan = plan_models(args.scenario)  # the scenario's models, resolved once for the whole process
    encoder = build_agent_encoder(plan)
    return run_agent(args, "ego", args.cav, lambda bus: ego_loop(args, bus, encoder=encoder, plan=plan),
                     max_message_bytes=receive_bound(largest_message(args.scenario, encoder, plan.wire_ratio)))


if __name__ == "__main__":
    sys.exit(main())
