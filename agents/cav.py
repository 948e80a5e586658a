"""CAV perception agent: one process per connected vehicle.

Every frame it senses from its own pose in the WorldState, encodes its BEV features and publishes
them once, whatever fusion methods are under test (each method fuses the same messages). When
early or late fusion is under test it also ships its raw points or its own decoded outputs. It
ends cleanly when its vehicle leaves the simulation or the driver says `done`, and on its own
within seconds when the driver dies (its token drops without a bye). The channel model is
applied by receivers.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from collections import Counter

import torch

from agents.args import AgentArgs, parse_agent_args, run_signer
from agents.bus import DRIVER_GRACE_S, START_TIMEOUT_S, Bus
from agents.lifecycle import receive_bound, run_agent
from agents.timing import StageTimer, write_timing
from agents.worlds import WorldQueue, world_window
from v2vsim.comm.codec import EVIDENCE, Message, encode
from v2vsim.comm.control import DRIVER
from v2vsim.comm.misbehaviour import Sent, active, tell
from v2vsim.comm.share import feature_message
from v2vsim.config import Scenario, neighbours_silent
from v2vsim.config.schema_misbehaviour import Lie
from v2vsim.evaluation.gt import gt_boxes, visible_actor_ids
from v2vsim.perception.aligned import build_cav_encoder, space_label
from v2vsim.perception.build import build_compressor, build_method_models, compress
from v2vsim.perception.device import prepare as prepare_device
from v2vsim.perception.device import resolve_device
from v2vsim.perception.encode import body_frame_points, late_outputs, pooled_confidence
from v2vsim.perception.encode import encode as encode_features
from v2vsim.perception.evidence import evidence_cells, evidence_grid, pack_array
from v2vsim.perception.plan import plan_models
from v2vsim.perception.precision import resolve as resolve_precision
from v2vsim.recording.scan import encode_scan, world_points
from v2vsim.sensors.camera import render_cameras
from v2vsim.sensors.scene import Scene, build_map_assets, build_scene
from v2vsim.sensors.sensing import SensorFrame, sense
from v2vsim.world.geometry import Pose
from v2vsim.world.serialize import MAX_STATIC_BYTES, MAX_WORLD_BYTES, static_from_bytes, world_from_bytes
from v2vsim.world.state import WorldState


def cav_loop(args: AgentArgs, bus: Bus) -> int:
    torch.set_num_threads(1)  # several agent processes share the cores
    sc = args.scenario
    me = args.cav
    methods = sc.perception.methods
    key = run_signer(args)
    # the runner checked the device before starting this process; a remote agent's host may differ (checked again)
    device = resolve_device(sc.perception.device)
    prepare_device(device)
    plan = plan_models(sc)  # the scenario's models, resolved once: every build below takes it
    encoder = build_cav_encoder(plan, me).to(device)  # the models move once; each inference moves its inputs
    modality = plan.agent_type(me).modality  # a mixed fleet's CAV: its own sensor (cavs.fleet)
    space = space_label(plan, me)  # what its feature messages name as their origin ("" outside a mixed fleet)
    precision = resolve_precision(sc.perception.precision)
    compressor, ratio = build_compressor(plan, encoder.out_channels), plan.wire_ratio
    compressor = None if compressor is None else compressor.to(device)
    late = "late" in methods
    # a closed-loop point that computes only `none` reads no neighbour's map: this CAV senses (the visible set) only
    silent = me not in args.egos and neighbours_silent(sc)
    # comm.share topk: the CAV ranks its cells by its own single-agent confidence; an ego keeps its whole map
    share = sc.comm.share.fraction if sc.comm.share.policy == "topk" and me not in args.egos else 1.0
    # its own single-agent model (late fusion's checkpoint is none's): decoded once a frame for both uses
    single = None
    if late or share < 1.0:
        name = "late" if late else "none"
        single = build_method_models(plan, encoder, (name,))[name].to(device)
    args.startup.mark("models")
    static = static_from_bytes(bus.fetch("static", "main", START_TIMEOUT_S))
    assets = build_map_assets(static)
    args.startup.mark("map")
    realtime = sc.transport.clock == "realtime"
    worlds = WorldQueue(world_window(sc), realtime)  # bounded: a forged far-future world is refused, not sensed
    done = threading.Event()
    bus.subscribe("world", lambda sender, data: worlds.put(data))
    bus.subscribe("done", lambda sender, data: done.set())
    bus.ready()
    seen = False
    gone_at: float | None = None  # when the driver's token was seen gone without a done
    frame = -1
    timer = StageTimer()
    told: Counter[str] = Counter()  # misbehaviour: the frames each lie was told
    try:
        while True:
            now = time.monotonic()
            if done.is_set() and done_believed(bus, frame, args.frames):
                return 0
            with timer.stage("wait"):
                data = worlds.take(timeout=0.2 if done.is_set() or gone_at else 0.5)
            if data is None:
                if bus.driver_gone() and not done.is_set():
                    gone_at = gone_at or now
                    bye = bus.farewell(DRIVER)
                    if bye is not None:
                        print(f"v2vsim-cav {me}: the driver ended (exit {bye.get('code')}) after frame {frame}; "
                              "agent stops", file=sys.stderr, flush=True)
                        return 0
                    if now - gone_at > DRIVER_GRACE_S:
                        print(f"v2vsim-cav {me}: the driver died after frame {frame}; agent stops",
                              file=sys.stderr, flush=True)
                        return 1
                continue
            try:
                world = world_from_bytes(data, static)
            except ValueError as e:
                print(f"v2vsim-cav {me}: ignoring {e}", file=sys.stderr)
                continue
            if world.frame <= frame:  # sent again for an ego that missed it (agents/driver.py): had it
                continue
            frame = world.frame
            actor = world.actor(me)
            if actor is None:
                if seen:
                    print(f"v2vsim-cav {me}: vehicle left the simulation at frame {world.frame}; agent stops",
                          file=sys.stderr, flush=True)
                    return 0
                continue
            seen = True
            lidar = modality == "lidar"
            with timer.stage("sensing"):
                scene = build_scene(world, assets)
                sf = sense(world, me, sc, scene, lidar=lidar, cameras=not lidar)
                seen_ids = _seen_actor_ids(world, sf)
            with timer.stage("comm"):
                bus.put("vis", json.dumps({"frame": world.frame, "ids": sorted(seen_ids)}).encode())
            if silent:
                if sc.output.rerun:
                    with timer.stage("recording"):
                        bus.put("scan", _scan(world, actor.pose, sf, scene, args))
                timer.frame_done()
                args.startup.mark("first_frame")
                continue
            with timer.stage("encoding"):
                feats = encode_features(encoder, sf, sc, precision, modality)
            confidence = maps = boxes = None
            if single is not None:
                with timer.stage("decoding"):  # its own outputs: decoder + heads
                    maps, boxes = late_outputs(single, feats, boxes=late, precision=precision)
                    if share < 1.0:
                        confidence = pooled_confidence(maps[0], feats.shape[-1])
            pose = actor.pose.as_tuple()
            grid = None
            if sc.defence.evidence and lidar:  # what its rays establish, sent with what it claims (signed with it)
                with timer.stage("evidence"):
                    grid = evidence_grid(sf.lidar.points, sc.sensors.lidar.height_m, encoder.bev_size_m,
                                         evidence_cells(encoder.out_cells))
            lies = active(sc.misbehaviour, me, world.frame)
            if lies:  # an attacked run (misbehaviour): what it sends is false, its own perception stays honest
                sent = lie(Sent(feats, pose, maps, boxes, grid), lies, world, me, seen_ids, sc, told)
                feats, pose, maps, boxes, grid = sent.features, sent.pose, sent.maps, sent.boxes, sent.evidence
            stamp = {"run_id": args.run_id, "sender_id": me, "frame": world.frame, "capture_time": world.time,
                     "sender_pose": pose, "compression": sc.comm.compression}
            ev = {} if grid is None else {EVIDENCE: pack_array(grid)}
            with timer.stage("comm"):
                labelled = {**stamp, "space": space} if space else stamp
                bus.put("features", encode(feature_message(compress(compressor, feats), confidence, share, labelled,
                                                           ratio, ev), key))
                if compressor is not None and me in args.egos:  # its ego fuses its own map uncompressed
                    bus.put("own", encode(Message(kind="features", payload=feats, **labelled), key))
                if "early" in methods and lidar:
                    bus.put("points", encode(Message(kind="points", payload=body_frame_points(sf, sc), **stamp), key))
            if late:
                with timer.stage("comm"):
                    bus.put("outputs", encode(Message(kind="outputs", payload=maps, extras={"boxes": boxes, **ev},
                                                      **stamp), key))
            if sc.output.rerun:
                with timer.stage("recording"):
                    bus.put("scan", _scan(world, actor.pose, sf, scene, args))
            timer.frame_done()
            args.startup.mark("first_frame")
    finally:
        if told:
            print(f"v2vsim-cav {me}: lied on purpose (misbehaviour): "
                  + ", ".join(f"{k} in {n} frames" for k, n in sorted(told.items())), file=sys.stderr, flush=True)
        write_timing(args.out, f"cav.{me}", timer, bus.control_rejections(), args.startup)


def lie(sent: Sent, lies: list[Lie], world: WorldState, me: str, seen_ids: set[str], sc: Scenario,
        told: Counter[str]) -> Sent:
    """`sent` after this frame's lies (v2vsim/comm/misbehaviour.py); `told` counts the frames each kind was told."""
    boxes, ids = gt_boxes(world, me, sc.bev)  # every actor on its grid, in its frame (the liar knows the truth)
    targets = {i: b for b, i in zip(boxes, ids, strict=True)}
    seen = boxes[[i in seen_ids for i in ids]] if len(ids) else boxes
    out, kinds = tell(sent, lies, sc.bev.size_m, targets, seen)
    told.update(kinds)
    return out


def done_believed(bus: Bus, frame: int, frames: int) -> bool:
    """Whether a `done` ends this CAV. A verified one does. Without comm.auth anyone could have sent it: it is
    believed once the driver is gone, or once this CAV sensed the run's last frame; an honest driver says done
    only after every frame was fused, so a done any earlier is from the future (the old rule, believed after
    DONE_GRACE_S without a world, let one forged done end every CAV while the driver waited for a slow ego)."""
    return bus.authenticated or frame >= frames - 1 or bus.driver_gone()


def _scan(world: WorldState, pose: Pose, sf: SensorFrame, scene: Scene, args: AgentArgs) -> bytes:
    """The recording's view of this frame: a subset of the sweep in world coordinates, and from
    an ego's own CAV its four camera images (rendered for the recording if the encoder used LiDAR)."""
    sc, me = args.scenario, args.cav
    points = None if sf.lidar is None else world_points(sf.lidar.points, pose, sc.sensors.lidar.height_m, sc.seed,
                                                        world.frame, me)
    images = None
    if me in args.egos:
        cams = sf.cameras if sf.cameras is not None else render_cameras(world, me, sc.sensors.cameras, scene=scene)
        images = cams.images
    return encode_scan(world.frame, points, images)


def _seen_actor_ids(world: WorldState, sf: SensorFrame) -> set[str]:
    """Ids of the vehicles this CAV's sensors hit (ground truth for the visible-vehicle mask)."""
    lidar = [sf.lidar] if sf.lidar is not None else []
    cams = [sf.cameras] if sf.cameras is not None else []
    return set(visible_actor_ids(lidar, cams, world))


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("cav", argv)
    return run_agent(args, "cav", args.cav, lambda bus: cav_loop(args, bus),  # it takes worlds and the static map
                     max_message_bytes=receive_bound(max(MAX_WORLD_BYTES, MAX_STATIC_BYTES)))


if __name__ == "__main__":
    sys.exit(main())
