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
"""

from __future__ import annotations

import json
import sys
import time
from collections import Counter
from functools import partial
from pathlib import Path

import numpy as np
import torch

from agents.args import AgentArgs, parse_agent_args, run_signer
from agents.bus import DRIVER_GRACE_S, START_TIMEOUT_S, Bus
from agents.ego_collect import bytes_for, collect, control_rejections, reject_leftovers
from agents.ego_defence import SenderCheck
from agents.ego_mailbox import Mailbox, Window, cav_died, notify, put_world, set_done, wait_messages, wait_world
from agents.ego_replay import ReplayBus
from agents.ego_scoring import AfterFusion, FusedFrame, signals_deferred
from agents.lifecycle import Stop, receive_bound, run_agent
from agents.progress import report_progress
from agents.timing import StageTimer
from v2vsim.comm.control import DRIVER
from v2vsim.comm.inbox import Inbox
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import EgoDecoder, ego_wire_spec
from v2vsim.config import Scenario, neighbours_silent
from v2vsim.control.critical import critical_measures, critical_total
from v2vsim.control.measures import driving_block, vehicle_measures
from v2vsim.control.pilot import Pilot
from v2vsim.control.score import PENALTY, score_block, total_score
from v2vsim.evaluation.fuse_and_score import box_iou, predict_all
from v2vsim.evaluation.gt import bev_ground_truth, gt_boxes
from v2vsim.evaluation.metrics import ApAccumulator, MethodScore, cavs_in_range
from v2vsim.evaluation.report import RunSummary, write_outputs
from v2vsim.evaluation.status import final_status, unscored
from v2vsim.perception.aligned import feature_space
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_extrapolation,
    build_method_models,
    decompress,
    method_checkpoints,
    runnable_methods,
    wire_ratio,
)
from v2vsim.perception.device import device_record, resolve_device
from v2vsim.perception.device import prepare as prepare_device
from v2vsim.perception.extrapolate import extrapolate_features
from v2vsim.perception.fleet import agent_type, is_mixed
from v2vsim.perception.precision import resolve as resolve_precision
from v2vsim.perception.threads import fusion_pool, fusion_threads
from v2vsim.recording.messages import MessageTape
from v2vsim.recording.scan import max_scan_bytes
from v2vsim.sensors.scene import MapAssets, build_map_assets
from v2vsim.world.geometry import Pose
from v2vsim.world.serialize import MAX_STATIC_BYTES, MAX_WORLD_BYTES, static_from_bytes, world_from_bytes
from v2vsim.world.state import WorldState

MAX_VIS_BYTES = 1 << 20  # the visible-ids side channel: a few hundred ids


def compensation_schemes(sc: Scenario, methods: list[str], extrapolations: dict[str, object]) -> dict[str, str]:
    """What compensates each method's late messages under comm.compensation (the report and metrics.json say it)."""
    if not sc.comm.compensation:
        return {}
    out = {m: "learned feature extrapolation (FFNet, the zoo's extrapolate stage)" for m in extrapolations}
    if "late" in methods:
        out["late"] = "model-free: boxes and vehicle map moved by object velocity"
    return out


def largest_message(sc: Scenario, encoder: torch.nn.Module) -> int | None:
    """The longest message the ego of `sc` accepts, whatever its kind (None: some kind has no bound): every
    V2V kind's (the uncompressed map from its own CAV included), the side channels, a world, the static map.
    Its zenoh session drops a longer message before reassembling it (agents.lifecycle.receive_bound)."""
    c, f = encoder.out_channels, encoder.out_cells
    specs = [*ego_wire_spec(sc, c, f, wire_ratio(sc)).items(), ("features", ego_wire_spec(sc, c, f, 1)["features"])]
    sizes = [ks.max_message_bytes(kind) for kind, ks in specs]
    if any(n is None for n in sizes):
        return None
    return max([*sizes, MAX_VIS_BYTES, max_scan_bytes(sc), MAX_WORLD_BYTES, MAX_STATIC_BYTES])  # type: ignore[list-item]


DONE_WAIT_S = 10.0  # how long an ego at the end of its run waits for the driver's done (SUMO closing, its SSM log)
STOPPING_WAIT_S = 1.5  # the same for an ego that is stopping (Ctrl-C, the driver gone): the runner's grace is 5 s


def driver_word(box: Mailbox, bus: Bus, done_doc: dict, wait_s: float) -> dict:
    """What the driver said as it ended: its done ({frames, control_rejections, ssm_conflicts}), or, when it stopped
    or failed first, the same fields in its bye; {} when it died without a word. Waits at most `wait_s`, and not
    once the driver's token has been gone for DRIVER_GRACE_S: a killed driver says nothing more."""
    deadline = time.monotonic() + wait_s
    gone_at = None
    with box.cond:
        while not box.done:
            if bus.farewell(DRIVER) is not None:
                break
            now = time.monotonic()
            if bus.driver_gone():
                gone_at = gone_at or now
                if now - gone_at > DRIVER_GRACE_S:
                    break
            if now >= deadline:
                break
            box.cond.wait(0.1)
    if box.done:
        return done_doc
    return bus.farewell(DRIVER) or {}


def driver_refusals(word: dict) -> dict[tuple[str, str], int]:
    """The control messages the driver refused, from its final word, keyed as the ego's own (kind@driver, reason)
    so that metrics.json comm.rejected_reasons and the report count them too."""
    out: dict[tuple[str, str], int] = {}
    refused = word.get("control_rejections")
    for kind, reasons in (refused.items() if isinstance(refused, dict) else ()):
        for reason, n in (reasons.items() if isinstance(reasons, dict) else ()):
            if isinstance(n, int) and n > 0:
                out[(f"{kind}@driver", str(reason))] = n
    return out


def driving_summary(sc: Scenario, me: str, pilot: Pilot, word: dict, time_limit_reached: bool) -> dict:
    """metrics.json `driving` of this ego's vehicle. SUMO writes its SSM log when the simulation closes, after the
    last frame: the driver counts its conflicts and says them as it ends (`word`, from driver_word); None when it
    never said them (it died). `time_limit_reached`: the run went on until its last frame or the route's end (status
    complete: a route not completed by then is a timeout; a run stopped early is not)."""
    assert sc.control is not None
    conflicts = word.get("ssm_conflicts")
    count = conflicts.get(me, 0) if isinstance(conflicts, dict) else None
    c = sc.control
    header = {"method": c.method, "planner": c.planner, "driven": [me],
              "actuation_delay_frames": sc.actuation_delay_frames,
              "actuation_delay_ms": round(1000.0 * sc.actuation_delay_frames * sc.dt, 3),
              "background_ignore_junction_foes": c.background_ignore_junction_foes,
              "ssm_thresholds": {"ttc_s": c.ssm.ttc_s, "drac_mps2": c.ssm.drac_mps2, "pet_s": c.ssm.pet_s,
                                 "range_m": c.ssm.range_m},
              "hard_brake_mps2": c.hard_brake_mps2, "near_miss_gap_m": c.near_miss_gap_m}
    per = vehicle_measures(pilot.frames, sc.dt, c.hard_brake_mps2, c.near_miss_gap_m, count)
    if per.get("frames"):
        per |= score_block(pilot.frames, per["collisions"], time_limit_reached)
        per |= critical_measures(pilot.frames, pilot.critical)
    block = driving_block({me: per}, {**header, "route_m": c.route_m, "penalties": dict(PENALTY)})
    block["total"] |= total_score([v for v in block["vehicles"].values() if v.get("frames")])
    block["total"] |= critical_total(block["vehicles"], me)
    return block


def ego_loop(args: AgentArgs, bus: Bus, replay: ReplayBus | None = None, encoder: torch.nn.Module | None = None
             ) -> int:
    """The ego's whole run. `replay` (v2vsim evaluate): `bus` is a ReplayBus that feeds a recording's frames
    straight into the mailbox, after the arrival checks they passed when recorded; everything else is the same.
    `encoder`: the CAVs' encoder, built already (main sizes its zenoh session by it)."""
    torch.set_num_threads(1)
    sc = args.scenario
    me = args.cav
    methods = sc.perception.methods
    lidar = sc.perception.modality == "lidar"
    key = run_signer(args)
    kinds = ["features"] + (["points"] if "early" in methods and lidar else []) + (
        ["outputs"] if "late" in methods else [])
    # checked before any process started (runner, evaluate); again here, where the models will run
    device = resolve_device(sc.perception.device)
    prepare_device(device)
    encoder = (encoder if encoder is not None else build_agent_encoder(sc)).to(device)
    precision = resolve_precision(sc.perception.precision)
    # every model moves to the device once; each inference moves its inputs and brings its outputs to the host
    models = {m: model.to(device) for m, model in build_method_models(sc, encoder, runnable_methods(sc)).items()}
    # comm.compensation: each intermediate method whose zoo ships a trained extrapolation (never a random one)
    extrapolations = {m: e.to(device) for m in models
                      if sc.comm.compensation and (e := build_extrapolation(sc, m)) is not None}
    # defence: each sender's features decoded alone by the single-agent model, compared with the others' each frame
    sender_check = None if not sc.defence.on else SenderCheck(
        sc, models["none"] if "none" in models else build_method_models(sc, encoder, ("none",))["none"].to(device),
        precision)
    args.startup.mark("models")
    static_bytes = bus.fetch("static", "main", START_TIMEOUT_S)
    static = static_from_bytes(static_bytes)
    # the map rasters for the ground truth: one set for every replay of a recording in this process
    assets = (build_map_assets(static) if replay is None
              else replay.once_per_recording("map_assets", partial(build_map_assets, static)))
    args.startup.mark("map")
    c, f = encoder.out_channels, encoder.out_cells
    compressor, ratio = build_compressor(sc, c), wire_ratio(sc)
    compressor = None if compressor is None else compressor.to(device)
    # a mixed fleet: every feature message names its space, and one this ego's models were not trained on is refused
    spaces = frozenset({feature_space(sc)}) if is_mixed(sc) else None
    decoder = EgoDecoder(ego_wire_spec(sc, c, f, ratio, spaces), args.run_id, frozenset(args.cavs), key)
    # a compressed wire: the ego's own CAV also hands it its map uncompressed ("own"), which it fuses as its own
    own_decoder = None if compressor is None else EgoDecoder(
        {"features": ego_wire_spec(sc, c, f, 1, spaces)["features"]}, args.run_id, frozenset({me}), key)
    # LiDAR points come from the LiDAR CAVs only (a mixed fleet's camera CAVs send none)
    lidar_cavs = [cav for cav in args.cavs if agent_type(sc, cav).modality == "lidar"]
    if replay is not None:  # replays of one recording in one process decode each message once
        decoder = replay.decoder(decoder, "v2v")
        own_decoder = None if own_decoder is None else replay.decoder(own_decoder, "own")

    side = ["vis", "scan"] if sc.output.rerun else ["vis"]
    silent = neighbours_silent(sc)  # the other CAVs send no map (config.neighbours_silent)
    def check(kind: str, sender: str, data: bytes) -> int:
        if kind == "own":
            return own_decoder.check_arrival("features", data, sender)  # type: ignore[union-attr]
        return decoder.check_arrival(kind, data, sender)

    window = Window.for_scenario(sc)
    box = Mailbox({kind: decoder.max_bytes(kind) for kind in kinds} | {"vis": MAX_VIS_BYTES,
                                                                       "scan": max_scan_bytes(sc)}
                  | ({"own": own_decoder.max_bytes("features")} if own_decoder is not None else {}),
                  check=check, window=window)
    if replay is not None:
        replay.attach(box)
    for kind in [*kinds, *side, *(["own"] if own_decoder is not None else [])]:
        # too long for its kind: refused from its length on zenoh's buffer, before a copy (case 5 of issue 45)
        bus.subscribe(kind, lambda sender, data, kind=kind: box.put(kind, sender, data),
                      max_bytes=box.limits.get(kind) or None,
                      oversize=lambda sender, kind=kind: box.refused(kind, "size_mismatch"))
    bus.subscribe("world", lambda sender, data: put_world(box, data))  # bounded like the messages (worlds.py)
    done_doc: dict = {}  # what the driver said with its done (closed loop: SUMO's SSM conflicts per vehicle)

    def on_done(sender: str, data: bytes) -> None:
        try:
            doc = json.loads(data)
            done_doc.update(doc if isinstance(doc, dict) else {})
        except ValueError:
            pass
        set_done(box)

    bus.subscribe("done", on_done)
    lost: dict[str, int] = {}
    bus.on_lost(lambda who: notify(box))

    stats = CommStats()
    inboxes = {k: Inbox(sc.comm, sc.seed, me, k, stats if k == "features" else CommStats()) for k in kinds}
    scores = {m: MethodScore(boxes=ApAccumulator(sort=sc.evaluation.ap_sort) if lidar else None, size_m=sc.bev.size_m)
              for m in models}
    ego_poses: dict[int, Pose] = {}
    out_dir = Path(args.out) / ("" if me == args.egos[0] else f"ego_{me}")
    recorder = None
    if sc.output.rerun:  # imported here: rerun and matplotlib cost an ego that does not record ~0.45 s at start
        from v2vsim.recording.recorder import Recorder

        recorder = Recorder(out_dir / "recording.rrd", sc, list(models), list(args.cavs), me, static,
                            types={cav: agent_type(sc, cav).label for cav in args.cavs} if is_mixed(sc) else None)
    pilot = None
    if sc.control is not None:  # closed loop: this ego's vehicle plans on control.method's output
        if sc.control.method != "oracle" and sc.control.method not in models:
            raise ValueError(f"control.method {sc.control.method!r} cannot run in this run (runnable: "
                             f"{', '.join(models)})")
        pilot = Pilot(sc, me)
    checkpoints = method_checkpoints(sc, tuple(models))
    summary = RunSummary(scenario=sc, ego=me, methods=list(models),
                         untrained=all(v is None for v in checkpoints.values()), checkpoints=checkpoints,
                         skipped=[m for m in methods if m not in models],
                         compensation=compensation_schemes(sc, list(models), extrapolations),
                         grid_cells=f, channels=c, wire_ratio=ratio,
                         fleet={cav: agent_type(sc, cav).label for cav in args.cavs} if is_mixed(sc) else {},
                         device=device_record(sc.perception.device, device))
    tape = MessageTape(out_dir / "messages", sc, run_id=args.run_id, run_instance=args.run_instance, ego=me,
                       cavs=list(args.cavs), frames=args.frames, kinds=kinds,
                       side=[*side, *(["own"] if own_decoder is not None else [])],
                       static=static_bytes) if sc.output.record_messages else None
    if tape is not None:
        box.on_collect = tape.collected
    timer = StageTimer()
    after = AfterFusion(scores, recorder, timer)
    memo = None if replay is None else replay.prediction_memo(precision, sc.bev.cells)
    # replays keep one method at a time: several replays share a process and its cores (agents.ego_replay)
    threads = fusion_threads(sc.perception.fusion_threads, len(models)) if replay is None else 1
    pool = fusion_pool(threads)
    progress_name = f"ego.{me}" if replay is None or replay.label is None else replay.label
    bus.ready()
    t_start = time.monotonic()
    frames_done = 0
    status = "complete"
    realtime = sc.transport.clock == "realtime"
    lost_after = sc.transport.lost_after_s
    k = -1
    working = 0  # the frame being waited for or worked on (for a crash's status)
    code = 0
    try:
        while k + 1 < args.frames:
            working = k + 1
            with timer.stage("wait"):
                got = wait_world(box, bus, k + 1, realtime)
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
            if isinstance(got, str) and got.startswith("no world"):  # the driver is there but silent: a hang
                status, code = f"stalled {_after(k)}: {got} from the driver", 1
                print(f"v2vsim-ego {me}: {got} from the driver {_after(k)}; writing results and stopping",
                      file=sys.stderr, flush=True)
                break
            if isinstance(got, str):
                status = f"ended early: the driver stopped {_after(k)} ({got})"
                break
            k, data = got
            working = k
            if tape is not None:
                tape.world(k, data)
            with timer.stage("comm"):
                world = (world_from_bytes(data, static) if replay is None
                         else replay.once(("world",), partial(world_from_bytes, data, static)))
            ego_actor = world.actor(me)
            if ego_actor is None:
                status = f"ego {me} left the simulation at frame {k}"
                break
            ego_poses[k] = ego_actor.pose
            for f in [f for f in ego_poses if f < k - window.behind - 1]:  # older messages are refused
                del ego_poses[f]
            near = cavs_in_range(world, me, sc.comm.range_m)
            present = [a.id for a in world.cavs if a.id in args.cavs]
            if not realtime:
                with timer.stage("wait"):
                    if silent:  # only `none`: its own map, and what every CAV saw
                        wait_messages(box, bus, k, [me] if me in present else [], kinds, lost, lost_after)
                        wait_messages(box, bus, k, present, side, lost, lost_after)
                    else:
                        wait_messages(box, bus, k, present, [kd for kd in [*kinds, *side] if kd != "points"], lost,
                                      lost_after)
                    if "points" in kinds:
                        wait_messages(box, bus, k, [c for c in present if c in lidar_cavs], ["points"], lost,
                                      lost_after)
                    if own_decoder is not None and me in present:
                        wait_messages(box, bus, k, [me], ["own"], lost, lost_after)
            else:  # lockstep marks a CAV lost at the first frame whose messages it never sent (above);
                # the driver and CAVs may be frames ahead, so a CAV gone by now may have sent frame k
                for cav in present:
                    if cav not in lost and cav_died(bus, cav):
                        lost[cav] = k
            for cav in lost:
                stats.record_lost_agent(cav)
            with timer.stage("comm"):
                inp, visible, scans = collect(box, k, world, me, kinds, inboxes, ego_poses, decoder, args, own_decoder)
                events = {kind: ib.take_events() for kind, ib in inboxes.items()}
                links = events["features"]  # the message every method fuses: what the links show
                # float32 [C, F, F] each; its own map never went on the air: the uncompressed one where it came
                inp.features = {s: decompress(None, inp.own) if s == me and inp.own is not None
                                else decompress(compressor, v) for s, v in inp.features.items()}
            if extrapolations:
                with timer.stage("compensation"):
                    inp.previous_features = {s: (decompress(compressor, old), rel, gap)
                                             for s, (old, rel, gap) in inp.previous_features.items()}
                    inp.extrapolated = {m: extrapolate_features(e, inp, sc.bev.size_m)
                                        for m, e in extrapolations.items()}
            with timer.stage("ground_truth"):
                gt, boxes_gt = (ground_truth(world, me, sc, visible, assets) if replay is None else
                                replay.once(("ground_truth", me, frozenset(visible)),
                                            partial(ground_truth, world, me, sc, visible, assets)))
            flagged: set[str] = set()
            if sender_check is not None:  # the map's drivable area is map knowledge, not the frame's ground truth
                with timer.stage("consistency"):
                    inp, flagged = sender_check.check(k, inp, gt["road"])
            preds = predict_all(models, inp, sc.bev.cells, precision, memo, pool,
                                cost=None if pool is None else timer.method_ms())
            for m, pred in preds.items():
                timer.add(f"fusion.{m}", pred.ms - pred.decode_ms)
                timer.add(f"decoding.{m}", pred.decode_ms)
            sent = {m: bytes_for(m, inboxes) for m in preds}
            for ib in inboxes.values():
                ib.take_bytes()
            ack: dict = {"ego": me, "frame": k}
            drive = None
            if pilot is not None:
                with timer.stage("planning"):
                    drive = pilot.step(world, preds.get(sc.control.method))  # type: ignore[union-attr]
                if drive is not None:
                    ack["command"] = {"accel": round(drive.plan.accel, 4)}
            # Scoring and recording run beside the next frame's fusion; frames stay in order.
            after.submit(FusedFrame(k, world, gt, boxes_gt, preds, inp, sent, links, scans, drive, frozenset(flagged),
                                    sc.defence.exclude))
            frames_done += 1
            summary.neighbours.append(near)
            timer.frame_done()
            args.startup.mark("first_frame")
            if not realtime or pilot is not None:  # realtime: no ack awaited, but a plan must reach the driver
                with timer.stage("comm"):
                    bus.put("ack", json.dumps(ack).encode())
            report_progress(progress_name, k + 1, args.frames, delivered=stats.delivered, dropped=stats.dropped,
                            out_of_range=stats.out_of_range)
            if drive is not None and drive.logged.finished:  # its route is done: it arrives, its run is complete
                print(f"v2vsim-ego {me}: route completed at frame {k} ({drive.logged.time:.1f} s)", file=sys.stderr,
                      flush=True)
                break
    except Stop:
        # The runner stops everyone when the driver dies: say so rather than "interrupted".
        died = bus.driver_gone() and bus.farewell(DRIVER) is None
        status = f"driver died {_after(k)}" if died else f"interrupted after {frames_done} frames"
        raise
    except Exception as e:
        status = _crashed(f"at frame {working}", e)
        raise
    finally:
        with signals_deferred():  # a second Ctrl-C or the runner's SIGINT must not cut the files short
            late_error: BaseException | None = None
            try:
                after.close()  # every fused frame scored (and recorded) before the files are written
            except Exception as e:
                status = _crashed(f"after frame {k}", e)
                late_error, code = e, 1
            if pool is not None:  # a Stop may leave a method running on it: let it end
                pool.shutdown(wait=True)
            reject_leftovers(box, kinds, inboxes, decoder)
            # a run through every frame that lost agents or scored nothing for a method says so (a replay too:
            # its lost agents are the recording's, from the same frames)
            ious = {m: (s.vehicle.iou, s.vehicle_all.iou, s.road.iou, s.lane.iou) for m, s in scores.items()}
            went_to_end = status == "complete"
            status = final_status(status, lost, unscored(ious),
                                  None if sender_check is None else sender_check.flagged_counts())
            summary.timing = timer.to_json() | {"fusion_threads": threads, "startup": args.startup.to_json()}
            summary.defence = None if sender_check is None else sender_check.to_json()
            summary.frames = frames_done
            summary.sim_s = (k + 1) / sc.rate_hz
            summary.status = status
            summary.wall_s = time.monotonic() - t_start
            summary.lost_agents = dict(lost)
            summary.feature_bytes = dict(inboxes["features"].bytes_by_sender)
            # the driver's last word (its SSM conflicts and refusals): waited for only live; long only where the
            # driving block needs SUMO's SSM log and the run went to its end (the other egos may still be fusing)
            wait_s = (0.0 if replay is not None else DONE_WAIT_S if pilot is not None and went_to_end
                      else STOPPING_WAIT_S)
            word = driver_word(box, bus, done_doc, wait_s)
            if pilot is not None:
                summary.driving = driving_summary(sc, me, pilot, word, went_to_end)
            control = Counter(bus.control_rejections()) + Counter(driver_refusals(word))
            by_kind = {kind: ib.stats for kind, ib in inboxes.items()}
            by_kind["control"] = control_rejections(control, stats)
            write_outputs(out_dir, summary, scores, stats, by_kind, box_iou)
            if recorder is not None:
                recorder.close()
            if tape is not None:
                tape.close(status=status, lost=lost, control=dict(control))
            if replay is not None:
                replay.close()
        if late_error is not None:
            raise late_error
    return code


def ground_truth(world: WorldState, me: str, sc: Scenario, visible: set[str],
                 assets: MapAssets) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The ego's BEV ground truth masks and its scored boxes [K, 5] (the vehicles some CAV saw)."""
    gt = bev_ground_truth(world, me, sc.bev, visible, assets=assets)
    boxes_gt, ids = gt_boxes(world, me, sc.bev)
    return gt, boxes_gt[[i in visible for i in ids]] if len(ids) else boxes_gt


def _crashed(where: str, e: BaseException) -> str:
    """metrics.json status of a crash: where, the exception type and its message on one line."""
    return f"crashed {where}: {type(e).__name__}: {' '.join(str(e).split())[:300]}"


def _after(k: int) -> str:
    return f"after frame {k}" if k >= 0 else "before frame 0"


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("ego", argv)
    torch.set_num_threads(1)
    encoder = build_agent_encoder(args.scenario)
    return run_agent(args, "ego", args.cav, lambda bus: ego_loop(args, bus, encoder=encoder),
                     max_message_bytes=receive_bound(largest_message(args.scenario, encoder)))


if __name__ == "__main__":
    sys.exit(main())
