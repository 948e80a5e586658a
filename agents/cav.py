"""CAV perception agent: one process per connected vehicle.

Every frame it senses from its own pose in the WorldState, encodes its BEV features and publishes
them once, whatever fusion methods are under test (each method fuses the same messages). When
early or late fusion is under test it also ships its raw points or its own decoded outputs. It
ends cleanly when its vehicle leaves the simulation. The channel model is applied by receivers.
"""

from __future__ import annotations

import json
import queue
import sys
import threading

import torch

from agents.common import START_TIMEOUT_S, AgentArgs, Bus, parse_agent_args, run_agent
from v2vsim.comm.codec import Message, encode
from v2vsim.gt import visible_actor_ids
from v2vsim.perception import (
    body_frame_points,
    build_agent_encoder,
    build_compressor,
    build_method_models,
    compress,
    late_outputs,
)
from v2vsim.perception import encode as encode_features
from v2vsim.sensing import SensorFrame, sense
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.world import WorldState
from v2vsim.world_io import static_from_bytes, world_from_bytes


def read_key(path: str | None) -> bytes | None:
    return None if path is None else open(path, "rb").read().strip()


def cav_loop(args: AgentArgs, bus: Bus) -> int:
    torch.set_num_threads(1)  # several agent processes share the cores
    sc = args.scenario
    me = args.cav
    methods = sc.perception.methods
    key = read_key(sc.comm.auth.key_file)
    encoder = build_agent_encoder(sc)
    compressor = build_compressor(sc, encoder.out_channels)
    late_model = build_method_models(sc, encoder, ("late",))["late"] if "late" in methods else None
    static = static_from_bytes(bus.fetch("static", "main", START_TIMEOUT_S))
    assets = build_map_assets(static)
    worlds: queue.Queue[bytes] = queue.Queue()
    done = threading.Event()
    bus.subscribe("world", lambda sender, data: worlds.put(data))
    bus.subscribe("done", lambda sender, data: done.set())
    bus.ready()
    realtime = sc.transport.clock == "realtime"
    seen = False
    while not done.is_set():
        try:
            data = worlds.get(timeout=0.5)
        except queue.Empty:
            continue
        if realtime:  # sense the newest world; frames we could not keep up with are skipped
            while not worlds.empty():
                data = worlds.get_nowait()
        try:
            world = world_from_bytes(data, static)
        except ValueError as e:
            print(f"v2vsim-cav {me}: ignoring {e}", file=sys.stderr)
            continue
        actor = world.actor(me)
        if actor is None:
            if seen:
                print(f"v2vsim-cav {me}: vehicle left the simulation at frame {world.frame}; agent stops",
                      file=sys.stderr, flush=True)
                return 0
            continue
        seen = True
        scene = build_scene(world, assets)
        lidar = sc.perception.modality == "lidar"
        sf = sense(world, me, sc, scene, lidar=lidar, cameras=not lidar)
        seen_ids = _seen_actor_ids(world, sf)
        bus.put("vis", json.dumps({"frame": world.frame, "ids": sorted(seen_ids)}).encode())
        feats = encode_features(encoder, sf, sc)
        stamp = {"run_id": args.run_id, "sender_id": me, "frame": world.frame, "capture_time": world.time,
                 "sender_pose": actor.pose.as_tuple(), "compression": sc.comm.compression}
        bus.put("features", encode(Message(kind="features", payload=compress(compressor, feats),
                                           channel_compression=sc.comm.channel_compression, **stamp), key))
        if "early" in methods and lidar:
            bus.put("points", encode(Message(kind="points", payload=body_frame_points(sf, sc), **stamp), key))
        if late_model is not None:
            maps, boxes = late_outputs(late_model, feats)
            bus.put("outputs", encode(Message(kind="outputs", payload=maps, extras={"boxes": boxes}, **stamp), key))
    return 0


def _seen_actor_ids(world: WorldState, sf: SensorFrame) -> set[str]:
    """Ids of the vehicles this CAV's sensors hit (ground truth for the visible-vehicle mask)."""
    lidar = [sf.lidar] if sf.lidar is not None else []
    cams = [sf.cameras] if sf.cameras is not None else []
    return set(visible_actor_ids(lidar, cams, world))


def main(argv: list[str] | None = None) -> int:
    args = parse_agent_args("cav", argv)
    return run_agent(args, "cav", args.cav, lambda bus: cav_loop(args, bus))


if __name__ == "__main__":
    sys.exit(main())
