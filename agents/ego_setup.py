"""The ego's set-up (agents.ego.ego_loop): its models on their device, the decode path of every V2V kind, the
mailbox and its subscriptions, and where the run's results accumulate, built once before the first frame into
one `Ego` that the frame loop (agents.ego) and the finish (agents.ego_finish) read. `EgoRun` is the little the
loop changes as it goes.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from agents.args import AgentArgs, run_signer
from agents.bus import START_TIMEOUT_S, Bus
from agents.ego_defence import SenderCheck
from agents.ego_mailbox import Mailbox, Window, notify, put_world, set_done
from agents.ego_replay import ReplayBus
from agents.ego_scoring import AfterFusion
from agents.timing import StageTimer
from v2vsim.comm.inbox import Inbox
from v2vsim.comm.signing import Signer
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import EgoDecoder, ego_wire_spec
from v2vsim.config import Scenario, neighbours_silent
from v2vsim.control.pilot import Pilot
from v2vsim.evaluation.fuse_and_score import PredictionMemo
from v2vsim.evaluation.metrics import ApAccumulator, MethodScore
from v2vsim.evaluation.report import RunSummary
from v2vsim.perception.aligned import feature_space
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_extrapolation,
    build_method_models,
    method_checkpoints,
)
from v2vsim.perception.device import device_record, resolve_device
from v2vsim.perception.device import prepare as prepare_device
from v2vsim.perception.fleet import agent_type, is_mixed
from v2vsim.perception.plan import ModelPlan, plan_models
from v2vsim.perception.precision import Precision
from v2vsim.perception.precision import resolve as resolve_precision
from v2vsim.perception.threads import fusion_pool, fusion_threads
from v2vsim.recording.messages import MessageTape
from v2vsim.recording.scan import max_scan_bytes
from v2vsim.sensors.scene import MapAssets, build_map_assets
from v2vsim.world.geometry import Pose
from v2vsim.world.serialize import static_from_bytes
from v2vsim.world.state import StaticMap

if TYPE_CHECKING:  # rerun and matplotlib load only in an ego that records (open_recorder)
    from models.compression import ChannelCompressor
    from models.extrapolation import FeatureExtrapolation
    from v2vsim.recording.recorder import Recorder

MAX_VIS_BYTES = 1 << 20  # the visible-ids side channel: a few hundred ids


@dataclass(frozen=True)
class EgoModels:
    """What the ego runs, every model on `device` already."""

    plan: ModelPlan  # the scenario's models, resolved once (v2vsim.perception.plan)
    device: torch.device
    encoder: torch.nn.Module  # the CAVs' encoder: its out_channels and out_cells size every feature message
    precision: Precision
    models: dict[str, torch.nn.Module]  # method -> its model, for the runnable methods of perception.methods
    extrapolations: dict[str, FeatureExtrapolation]  # comm.compensation: method -> its trained extrapolation
    sender_check: SenderCheck | None  # defence.on: each sender's map checked against the others'


@dataclass(frozen=True)
class EgoWire:
    """How the ego reads what arrives: the kinds it takes and the decode path of each."""

    kinds: list[str]  # the V2V kinds its methods fuse: features, points (early, LiDAR), outputs (late)
    side: list[str]  # the side channels: every CAV's visible ids, and its scan where the run records
    channels: int  # C of a feature map [C, F, F]
    cells: int  # F of a feature map
    ratio: int  # the wire's channel compression ratio (1: uncompressed)
    compressor: ChannelCompressor | None  # None: features travel uncompressed
    decoder: EgoDecoder  # every V2V kind, from every CAV of the run
    own_decoder: EgoDecoder | None  # a compressed wire: its own CAV's map, handed over uncompressed ("own")
    lidar_cavs: list[str]  # the CAVs that send points (a mixed fleet's camera CAVs send none)
    silent: bool  # the other CAVs send no map (config.neighbours_silent)

    @property
    def side_and_own(self) -> list[str]:
        """The side channels, and "own" where its own CAV hands its map over uncompressed."""
        return [*self.side, *(["own"] if self.own_decoder is not None else [])]


@dataclass(frozen=True)
class Ego:
    """Everything the ego's frame loop and its finish need, built once by build_ego."""

    args: AgentArgs
    bus: Bus
    replay: ReplayBus | None  # v2vsim evaluate: `bus` is this ReplayBus too
    nets: EgoModels
    wire: EgoWire
    static: StaticMap
    assets: MapAssets  # the map rasters of the ground truth
    window: Window  # which frames a message is still kept for
    box: Mailbox
    done_doc: dict  # what the driver said with its done, once it said it (closed loop: SSM conflicts per vehicle)
    stats: CommStats  # the feature link's counts, the run's V2V totals
    inboxes: dict[str, Inbox]  # V2V kind -> its channel model and counts
    scores: dict[str, MethodScore]  # method -> its running scores (filled on the scoring thread)
    out_dir: Path
    recorder: Recorder | None  # output.rerun
    pilot: Pilot | None  # closed loop: this ego's vehicle plans on control.method's output
    summary: RunSummary
    tape: MessageTape | None  # output.record_messages
    timer: StageTimer
    after: AfterFusion  # scores (and records) each fused frame beside the next frame's fusion
    memo: PredictionMemo | None  # a replay's predictions shared with the other replays of its recording
    threads: int  # fusion threads
    pool: ThreadPoolExecutor | None  # None: the methods run in the main thread
    progress_name: str

    @property
    def sc(self) -> Scenario:
        """The run's scenario."""
        return self.args.scenario

    @property
    def me(self) -> str:
        """This ego's CAV id."""
        return self.args.cav

    @property
    def realtime(self) -> bool:
        """transport.clock realtime: a frame is fused with whatever has arrived when its world comes."""
        return self.sc.transport.clock == "realtime"


@dataclass
class EgoRun:
    """What the frame loop changes as the run goes; the finish reads it."""

    t_start: float  # time.monotonic() once the ego said it is ready
    k: int = -1  # the last frame whose world came (-1: none yet)
    working: int = 0  # the frame being waited for or worked on (for a crash's status)
    frames_done: int = 0
    status: str = "complete"  # how the run ended, before final_status
    code: int = 0  # the exit code
    lost: dict[str, int] = field(default_factory=dict)  # CAV -> the frame it was lost at
    ego_poses: dict[int, Pose] = field(default_factory=dict)  # frame -> this ego's pose, the window's frames only


def build_ego(args: AgentArgs, bus: Bus, replay: ReplayBus | None, encoder: torch.nn.Module | None,
              plan: ModelPlan | None = None) -> Ego:
    """The ego's whole set-up, in the order a live run needs it (the start-up marks "models" and "map" fall in
    between); `encoder`: the CAVs' encoder where main built it already, from `plan` (None: resolved here)."""
    torch.set_num_threads(1)
    sc, me = args.scenario, args.cav
    key = run_signer(args)
    nets = load_models(args, encoder, plan)
    args.startup.mark("models")
    static_bytes, static, assets = load_map(bus, replay)
    args.startup.mark("map")
    wire = build_wire(args, nets, key, replay)
    window = Window.for_scenario(sc)
    box = open_mailbox(sc, wire, window, replay)
    done_doc = subscribe(bus, box, wire)
    stats = CommStats()
    inboxes = {k: Inbox(sc.comm, sc.seed, me, k, stats if k == "features" else CommStats()) for k in wire.kinds}
    lidar = sc.perception.modality == "lidar"
    scores = {m: MethodScore(boxes=ApAccumulator(sort=sc.evaluation.ap_sort) if lidar else None, size_m=sc.bev.size_m)
              for m in nets.models}
    out_dir = Path(args.out) / ("" if me == args.egos[0] else f"ego_{me}")
    recorder = open_recorder(args, out_dir, list(nets.models), static)
    pilot = make_pilot(sc, me, nets.models)
    summary = run_summary(args, nets, wire)
    tape = open_tape(args, out_dir, wire, static_bytes)
    if tape is not None:
        box.on_collect = tape.collected
    timer = StageTimer()
    after = AfterFusion(scores, recorder, timer)
    memo = None if replay is None else replay.prediction_memo(nets.precision, sc.bev.cells)
    # replays keep one method at a time: several replays share a process and its cores (agents.ego_replay)
    threads = fusion_threads(sc.perception.fusion_threads, len(nets.models)) if replay is None else 1
    pool = fusion_pool(threads)
    progress_name = f"ego.{me}" if replay is None or replay.label is None else replay.label
    return Ego(args, bus, replay, nets, wire, static, assets, window, box, done_doc, stats, inboxes, scores, out_dir,
               recorder, pilot, summary, tape, timer, after, memo, threads, pool, progress_name)


def v2v_kinds(sc: Scenario) -> list[str]:
    """The V2V kinds the ego takes: every method fuses features; early fusion LiDAR points, late fusion outputs."""
    methods = sc.perception.methods
    lidar = sc.perception.modality == "lidar"
    return ["features"] + (["points"] if "early" in methods and lidar else []) + (
        ["outputs"] if "late" in methods else [])


def load_models(args: AgentArgs, encoder: torch.nn.Module | None, plan: ModelPlan | None = None) -> EgoModels:
    """The ego's models, each moved to the scenario's device; `encoder` where main built it already, from `plan`
    (the scenario's, resolved once: None resolves it here)."""
    sc = args.scenario
    plan = plan_models(sc) if plan is None else plan
    # checked before any process started (runner, evaluate); again here, where the models will run
    device = resolve_device(sc.perception.device)
    prepare_device(device)
    encoder = (encoder if encoder is not None else build_agent_encoder(plan)).to(device)
    precision = resolve_precision(sc.perception.precision)
    # every model moves to the device once; each inference moves its inputs and brings its outputs to the host
    models = {m: model.to(device) for m, model in build_method_models(plan, encoder, plan.methods).items()}
    # comm.compensation: each intermediate method whose zoo ships a trained extrapolation (never a random one)
    extrapolations = {m: e.to(device) for m in models
                      if sc.comm.compensation and (e := build_extrapolation(plan, m)) is not None}
    # defence: each sender's features decoded alone by the single-agent model, compared with the others' each frame
    sender_check = None if not sc.defence.on else SenderCheck(
        sc, models["none"] if "none" in models else build_method_models(plan, encoder, ("none",))["none"].to(device),
        precision)
    return EgoModels(plan, device, encoder, precision, models, extrapolations, sender_check)


def load_map(bus: Bus, replay: ReplayBus | None) -> tuple[bytes, StaticMap, MapAssets]:
    """The driver's static map (as sent, and decoded) and the ground truth's map rasters."""
    static_bytes = bus.fetch("static", "main", START_TIMEOUT_S)
    static = static_from_bytes(static_bytes)
    # the map rasters for the ground truth: one set for every replay of a recording in this process
    assets = (build_map_assets(static) if replay is None
              else replay.once_per_recording("map_assets", partial(build_map_assets, static)))
    return static_bytes, static, assets


def build_wire(args: AgentArgs, nets: EgoModels, key: Signer | None, replay: ReplayBus | None) -> EgoWire:
    """The decode path of every kind the ego takes, with the scenario's exact shapes and bounds."""
    sc, me, encoder, device = args.scenario, args.cav, nets.encoder, nets.device
    c, f = encoder.out_channels, encoder.out_cells
    compressor, ratio = build_compressor(nets.plan, c), nets.plan.wire_ratio
    compressor = None if compressor is None else compressor.to(device)
    # a mixed fleet: every feature message names its space, and one this ego's models were not trained on is refused
    spaces = frozenset({feature_space(nets.plan)}) if is_mixed(sc) else None
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
    return EgoWire(kinds=v2v_kinds(sc), side=side, channels=c, cells=f, ratio=ratio, compressor=compressor,
                   decoder=decoder, own_decoder=own_decoder, lidar_cavs=lidar_cavs, silent=neighbours_silent(sc))


def open_mailbox(sc: Scenario, wire: EgoWire, window: Window, replay: ReplayBus | None) -> Mailbox:
    """The mailbox of every kind the ego takes, each bounded by its longest message and checked on arrival."""
    decoder, own_decoder = wire.decoder, wire.own_decoder

    def check(kind: str, sender: str, data: bytes) -> int:
        if kind == "own":
            return own_decoder.check_arrival("features", data, sender)  # type: ignore[union-attr]
        return decoder.check_arrival(kind, data, sender)

    box = Mailbox({kind: decoder.max_bytes(kind) for kind in wire.kinds} | {"vis": MAX_VIS_BYTES,
                                                                            "scan": max_scan_bytes(sc)}
                  | ({"own": own_decoder.max_bytes("features")} if own_decoder is not None else {}),
                  check=check, window=window)
    if replay is not None:
        replay.attach(box)
    return box


def subscribe(bus: Bus, box: Mailbox, wire: EgoWire) -> dict:
    """Every kind the ego takes, the worlds and the driver's done into `box`; returns the dict the done fills."""
    for kind in [*wire.kinds, *wire.side_and_own]:
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
    bus.on_lost(lambda who: notify(box))
    return done_doc


def open_recorder(args: AgentArgs, out_dir: Path, methods: list[str], static: StaticMap) -> Recorder | None:
    """The Rerun recording of the run (output.rerun), else None."""
    sc = args.scenario
    if not sc.output.rerun:
        return None
    # imported here: rerun and matplotlib cost an ego that does not record ~0.45 s at start
    from v2vsim.recording.recorder import Recorder

    return Recorder(out_dir / "recording.rrd", sc, methods, list(args.cavs), args.cav, static,
                    types={cav: agent_type(sc, cav).label for cav in args.cavs} if is_mixed(sc) else None)


def make_pilot(sc: Scenario, me: str, models: dict[str, torch.nn.Module]) -> Pilot | None:
    """Closed loop: the planner of this ego's vehicle, on control.method's output; None in open loop."""
    if sc.control is None:
        return None
    if sc.control.method != "oracle" and sc.control.method not in models:
        raise ValueError(f"control.method {sc.control.method!r} cannot run in this run (runnable: "
                         f"{', '.join(models)})")
    return Pilot(sc, me)


def compensation_schemes(sc: Scenario, methods: list[str], extrapolations: dict[str, object]) -> dict[str, str]:
    """What compensates each method's late messages under comm.compensation (the report and metrics.json say it)."""
    if not sc.comm.compensation:
        return {}
    out = {m: "learned feature extrapolation (FFNet, the zoo's extrapolate stage)" for m in extrapolations}
    if "late" in methods:
        out["late"] = "model-free: boxes and vehicle map moved by object velocity"
    return out


def run_summary(args: AgentArgs, nets: EgoModels, wire: EgoWire) -> RunSummary:
    """The run's summary as far as the set-up knows it; the finish adds how the run went."""
    sc, models = args.scenario, nets.models
    checkpoints = method_checkpoints(nets.plan, tuple(models))
    return RunSummary(scenario=sc, ego=args.cav, methods=list(models),
                      untrained=all(v is None for v in checkpoints.values()), checkpoints=checkpoints,
                      skipped=[m for m in sc.perception.methods if m not in models],
                      compensation=compensation_schemes(sc, list(models), nets.extrapolations),
                      grid_cells=wire.cells, channels=wire.channels, wire_ratio=wire.ratio,
                      fleet={cav: agent_type(sc, cav).label for cav in args.cavs} if is_mixed(sc) else {},
                      device=device_record(sc.perception.device, nets.device))


def open_tape(args: AgentArgs, out_dir: Path, wire: EgoWire, static_bytes: bytes) -> MessageTape | None:
    """The tape of every message the ego takes (output.record_messages), else None."""
    sc = args.scenario
    if not sc.output.record_messages:
        return None
    return MessageTape(out_dir / "messages", sc, run_id=args.run_id, run_instance=args.run_instance, ego=args.cav,
                       cavs=list(args.cavs), frames=args.frames, kinds=wire.kinds, side=wire.side_and_own,
                       static=static_bytes)
