"""A PettingZoo ParallelEnv for learning what to share: CAVs are agents, messages are actions, measured
bytes are the cost (Where2comm's question, on bytes that were actually encoded).

One process, the run's code: the traffic backend steps the world; every CAV senses
(v2vsim.sensors.sensing), encodes (v2vsim.perception) and ranks its feature cells by its own single-agent
vehicle confidence; its action picks the share of cells it sends, which becomes a real message
(v2vsim.comm.share + codec; its byte count is the encoded length). Each receiver decodes it with the
ego's wire spec, passes it through its own channel model (v2vsim.comm.inbox: latency, loss,
bandwidth, range, as in a run), scatters sparse messages back into a map and fuses with the env's
methods. A receiver with no neighbour message fuses nothing: it predicts with its single-agent model
(`none`), which is what sending nothing means.

Step t: the actions apply to the frame the observations showed (frame t); the receivers fuse at
frame t; then the world moves to frame t + 1 and the new observations are sensed.

Reward of agent i: sum over the other receivers j of IoU_j(all messages) - IoU_j(all but i's), the
per-frame visible-vehicle IoU (v2vsim.evaluation.metrics) with `methods[0]`, minus `byte_cost` per byte i
encoded. Frames where j's ground truth and prediction are both empty count 0.
"""

from __future__ import annotations

import functools
import json
import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from models.registration import PluginError
from models.registry import METHODS, check_methods, is_intermediate
from v2vsim.comm.codec import Message, encode
from v2vsim.comm.inbox import Inbox, distance
from v2vsim.comm.share import cells_sent, dense_payload, feature_message
from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import EgoDecoder, ego_wire_spec
from v2vsim.config import ConfigError, Scenario, load_scenario
from v2vsim.evaluation.gt import bev_ground_truth, visible_actor_ids
from v2vsim.evaluation.metrics import MethodScore, vehicle_iou
from v2vsim.perception.build import (
    build_agent_encoder,
    build_compressor,
    build_method_models,
    compress,
    decompress,
)
from v2vsim.perception.encode import encode as encode_features
from v2vsim.perception.encode import vehicle_confidence
from v2vsim.perception.fuse import FusionInputs, Prediction, predict
from v2vsim.perception.plan import plan_models
from v2vsim.sensors.scene import build_map_assets, build_scene
from v2vsim.sensors.sensing import ego_ids, sense
from v2vsim.traffic import TrafficBackend, cav_id, make_backend
from v2vsim.world.geometry import Pose, relative_pose
from v2vsim.world.state import WorldState

NO_LINK = -1.0  # distance / latency of a link that does not exist (itself, a CAV gone)


@dataclass(frozen=True)
class EnvOptions:
    """The env's own knobs (everything else is the scenario).

    features: the observation's own BEV features, the full map [C, F, F] or its per-channel mean [C].
    methods: the fusion methods every receiver runs (intermediate ones or none); methods[0] scores the reward.
    receivers: who fuses and is scored: every CAV, or the scenario's egos (cavs.ego) only (faster).
    byte_cost: reward per byte an agent encodes (1e-6: a whole 128 KiB map costs 0.13 IoU).
    link_window: messages the recent delivery ratio of a link is counted over.
    reward: "leave_one_out" (the module docstring) or "bytes" (only the byte cost: no extra fusion passes, for
        evaluating fixed policies).
    """

    features: Literal["map", "pooled"] = "map"
    methods: tuple[str, ...] = ("cobevt",)
    receivers: Literal["all", "egos"] = "all"
    byte_cost: float = 1e-6
    link_window: int = 10
    reward: Literal["leave_one_out", "bytes"] = "leave_one_out"

    def check(self) -> None:
        if self.features not in ("map", "pooled"):
            raise ConfigError(f"env features={self.features!r}; allowed: 'map', 'pooled'")
        if self.receivers not in ("all", "egos"):
            raise ConfigError(f"env receivers={self.receivers!r}; allowed: 'all', 'egos'")
        if not self.methods or any(m not in METHODS or not (m == "none" or is_intermediate(m)) for m in self.methods):
            allowed = [m for m in METHODS if m == "none" or is_intermediate(m)]
            raise ConfigError(f"env methods={list(self.methods)}; allowed: a non-empty list of {', '.join(allowed)} "
                              "(early and late fusion share points / outputs, not feature cells)")
        try:  # a fusion plugin among them: imported and checked against the fusion contract
            check_methods(self.methods)
        except PluginError as e:
            raise ConfigError(f"env methods: {e}") from None
        if not (self.byte_cost >= 0 and math.isfinite(self.byte_cost)):
            raise ConfigError(f"env byte_cost={self.byte_cost}; allowed: a finite number >= 0")
        if self.reward not in ("leave_one_out", "bytes"):
            raise ConfigError(f"env reward={self.reward!r}; allowed: 'leave_one_out', 'bytes'")
        if self.link_window < 1:
            raise ConfigError(f"env link_window={self.link_window}; allowed: >= 1")


@dataclass(frozen=True)
class Sensed:
    """One agent's view of one frame: what it observes and what it could send."""

    features: np.ndarray  # [C, F, F] float32, the encoder's map
    payload: np.ndarray  # [C/r, F, F] float32, what goes on the wire (channel-compressed)
    confidence: np.ndarray  # [F, F] single-agent vehicle probability, max-pooled to the grid
    seen: frozenset[str]  # vehicles its sensors hit (the visible-vehicle ground truth)


def scenario_overrides(overrides: dict[str, Any]) -> tuple[str, ...]:
    """Keyword overrides as `--set` strings: `seed=5`, `{"comm.drop.p": 0.3}` or `comm__drop__p=0.3`."""
    return tuple(f"{k.replace('__', '.')}={json.dumps(v)}" for k, v in overrides.items())


class CooperativePerceptionEnv(ParallelEnv):
    """See the module docstring. Build it with `v2vsim.env.parallel_env`."""

    metadata = {"name": "v2vsim_share_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, scenario_path: str | Path, *, render_mode: str | None = None,
                 options: EnvOptions = EnvOptions(), overrides: tuple[str, ...] = ()) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode={render_mode!r}; allowed: None, 'rgb_array'")
        options.check()
        self.scenario_path = str(scenario_path)
        self.overrides = overrides
        self.options = options
        self.render_mode = render_mode
        self.sc: Scenario = load_scenario(self.scenario_path, overrides)
        sc = self.sc
        if sc.cavs.fleet:
            raise ConfigError(f"{sc.source}: cavs.fleet: the PettingZoo env runs one agent type for every CAV; a mixed "
                              "fleet runs with `v2vsim run`; allowed here: no cavs.fleet")
        self.possible_agents: list[str] = [cav_id(i) for i in range(sc.cavs.count)]
        self.agents: list[str] = []
        methods = tuple(dict.fromkeys(("none", *options.methods)))
        plan = plan_models(sc, extra=methods)  # the scenario's models, resolved once; the env's methods among them
        self.encoder = build_agent_encoder(plan)
        self.compressor = build_compressor(plan, self.encoder.out_channels)
        self.models = build_method_models(plan, self.encoder, methods)
        self.channels, self.cells = self.encoder.out_channels, self.encoder.out_cells
        self.ratio = plan.wire_ratio  # the zoo's, where comm.channel_compression is null
        self.wire_shape = (self.channels // self.ratio, self.cells, self.cells)
        self.max_cycles: int | None = None  # PettingZoo's episode cap (parallel_api_test sets it); None: duration_s
        self._backend: TrafficBackend | None = None
        self._assets: Any = None
        self._episode_sc = sc
        self._world: WorldState | None = None
        self._sensed: dict[str, Sensed] = {}
        self._inboxes: dict[str, Inbox] = {}
        self._links: dict[tuple[str, str], deque[bool]] = {}
        self._latency: dict[tuple[str, str], float] = {}
        self._last: dict[str, Any] = {}  # what render() draws: the latest fused frame
        self.scores: dict[str, dict[str, MethodScore]] = {}  # receiver -> method -> episode scores
        self.bytes_sent: dict[str, list[int]] = {}  # agent -> bytes encoded per step
        self.stats = CommStats()
        self._t = 0

    # -- spaces -----------------------------------------------------------------------------------------------

    @functools.cache  # noqa: B019 - PettingZoo wants the same object every call
    def observation_space(self, agent: str) -> spaces.Dict:
        c, f, n = self.channels, self.cells, len(self.possible_agents)
        feat = (c, f, f) if self.options.features == "map" else (c,)
        return spaces.Dict({
            "features": spaces.Box(-np.inf, np.inf, feat, np.float32),
            "confidence": spaces.Box(0.0, 1.0, (f, f), np.float32),
            "pose": spaces.Box(-np.inf, np.inf, (4,), np.float32),  # x, y, z, yaw in the world frame
            # per CAV of possible_agents: distance (m), recent delivery ratio, latency (ms) of the link from this
            # agent to it; -1 / 0 / -1 for itself and CAVs not present
            "links": spaces.Box(np.array([[NO_LINK, 0.0, NO_LINK]] * n, np.float32),
                                np.array([[np.inf, 1.0, np.inf]] * n, np.float32), dtype=np.float32),
        })

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        """The share of its feature cells to send this frame, ranked by its confidence (0 nothing, 1 all)."""
        return spaces.Box(0.0, 1.0, (1,), np.float32)

    # -- episode ----------------------------------------------------------------------------------------------

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self._episode_sc = load_scenario(self.scenario_path, (*self.overrides, f"seed={int(seed)}"))
        sc = self._episode_sc
        if self._backend is not None:
            self._backend.close()
        self._backend = make_backend(sc)
        world = self._backend.reset()
        if self._assets is None:  # the map is the scenario's; only the seed changes between resets
            self._assets = build_map_assets(self._backend.static)
        self._world = world
        self.agents = [a for a in self.possible_agents if world.actor(a) is not None]
        self._inboxes = {a: Inbox(sc.comm, sc.seed, a, "features", CommStats()) for a in self.possible_agents}
        self._decoder = EgoDecoder(ego_wire_spec(sc, self.channels, self.cells, self.ratio), f"env-{sc.seed}",
                                    frozenset(self.possible_agents))
        self._links = {}
        self._latency = {}
        self.scores = {a: {m: MethodScore() for m in self.options.methods} for a in self.possible_agents}
        self.bytes_sent = {a: [] for a in self.possible_agents}
        self.stats = CommStats()
        self._t = 0
        self._last = {}
        self._sensed = self._sense(world)
        obs = {a: self._observe(a) for a in self.agents}
        return obs, {a: {"frame": world.frame} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if self._world is None:
            raise RuntimeError("call reset() before step()")
        if not self.agents:
            return {}, {}, {}, {}, {}
        world, sc = self._world, self._episode_sc
        sent: dict[str, tuple[bytes, Message]] = {}
        nbytes = dict.fromkeys(self.agents, 0)
        fractions: dict[str, float] = {}
        for a in self.agents:
            frac = fractions[a] = _fraction(actions.get(a, 0.0), a)
            s = self._sensed[a]
            if round(frac * self.cells * self.cells) == 0:
                continue  # nothing to send: no message, no bytes
            stamp = {"run_id": self._decoder.run_id, "sender_id": a, "frame": world.frame,
                     "capture_time": world.time, "sender_pose": world.actor(a).pose.as_tuple(),
                     "compression": sc.comm.compression}
            msg = feature_message(s.payload, s.confidence, frac, stamp, self.ratio)
            data = encode(msg)
            sent[a] = (data, msg)
            nbytes[a] = len(data)
        for a in self.agents:
            self.bytes_sent[a].append(nbytes[a])
        visible = frozenset().union(*(s.seen for s in self._sensed.values()))
        receivers = self._receivers()
        gain = dict.fromkeys(self.agents, 0.0)
        infos: dict[str, dict] = {a: {"frame": world.frame, "fraction": fractions[a], "bytes": nbytes[a],
                                      "cells": 0 if a not in sent else cells_sent(sent[a][1], self.cells ** 2)}
                                  for a in self.agents}
        # every receiver gets the same bytes: validated once (a rejection counted once, in self.stats)
        decoded = {i: self._decoder.receive("features", data, i, [self.stats]) for i, (data, _) in sent.items()}
        for j in receivers:
            inp = self._receive(j, sent, decoded, world)
            gt = bev_ground_truth(world, j, sc.bev, visible, assets=self._assets)
            preds = {m: self._predict(m, inp) for m in self.options.methods}
            for m, p in preds.items():
                self.scores[j][m].add_segmentation(p.probs, gt)
            base = vehicle_iou(preds[self.options.methods[0]].probs["vehicle"], gt)
            infos[j]["iou"] = base
            infos[j]["neighbours"] = [s for s in inp.senders if s != j]
            credited = inp.senders[1:] if self.options.reward == "leave_one_out" else []
            for i in credited:  # leave-one-out: what i's message added to j's prediction
                if i in gain:
                    without = self._predict(self.options.methods[0], _without(inp, i))
                    gain[i] += (base or 0.0) - (vehicle_iou(without.probs["vehicle"], gt) or 0.0)
            if j == receivers[0]:
                self._last = {"receiver": j, "gt": gt, "pred": preds[self.options.methods[0]], "sent": sent,
                              "world": world}
        rewards = {a: gain[a] - self.options.byte_cost * nbytes[a] for a in self.agents}
        for a in self.agents:
            infos[a]["iou_gain"] = gain[a]

        # the next frame
        self._t += 1
        limit = sc.frames if self.max_cycles is None else min(sc.frames, self.max_cycles)
        truncate = self._t >= limit
        terminations = dict.fromkeys(self.agents, False)
        truncations = dict.fromkeys(self.agents, truncate)
        if not truncate:
            world = self._backend.step()
            self._world = world
            for a in self.agents:
                terminations[a] = world.actor(a) is None  # its vehicle left the simulation
            alive = [a for a in self.agents if not terminations[a]]
            self._sensed = self._sense(world, alive)
        finished = [a for a in self.agents if terminations[a] or truncations[a]]
        obs = {a: self._observe(a) if a in self._sensed and not terminations[a] else self._blank()
               for a in self.agents}
        self.agents = [a for a in self.agents if a not in finished]
        return obs, rewards, terminations, truncations, infos

    def render(self) -> np.ndarray | None:
        """rgb_array: the first receiver's ground truth | fused prediction (errors) | the cells each CAV sent."""
        if self.render_mode is None:
            return None
        from v2vsim.env.render import render_frame

        return render_frame(self._last, self._episode_sc.bev, self.cells)

    def close(self) -> None:
        if self._backend is not None:
            self._backend.close()
            self._backend = None
        self._world = None
        self.agents = []

    # -- pieces -----------------------------------------------------------------------------------------------

    def _receivers(self) -> list[str]:
        if self.options.receivers == "egos":
            return ego_ids(self._episode_sc, self.agents)
        return list(self.agents)

    def _sense(self, world: WorldState, who: list[str] | None = None) -> dict[str, Sensed]:
        sc = self._episode_sc
        lidar = sc.perception.modality == "lidar"
        scene = build_scene(world, self._assets)
        out = {}
        for a in self.agents if who is None else who:
            sf = sense(world, a, sc, scene, lidar=lidar, cameras=not lidar)
            feats = encode_features(self.encoder, sf, sc)
            seen = visible_actor_ids([sf.lidar] if lidar else [], [] if lidar else [sf.cameras], world)
            out[a] = Sensed(feats, compress(self.compressor, feats), vehicle_confidence(self.models["none"], feats),
                            frozenset(seen))
        return out

    def _receive(self, j: str, sent: dict[str, tuple[bytes, Message]], decoded: dict[str, Message | None],
                 world: WorldState) -> FusionInputs:
        """What receiver j fuses at this frame: its own full map, and what its channel delivered (`decoded`: each
        sent message as the wire spec decoded it, None if it was rejected)."""
        inbox = self._inboxes[j]
        me = world.actor(j).pose
        own = self._sensed[j].payload.astype(np.float16)  # its whole map, as the wire would carry it
        airtime = len(sent[j][0]) if j in sent else 0  # its broadcast's size (comm.medium shared counts it)
        inbox.offer(Message(kind="features", run_id=self._decoder.run_id, sender_id=j, frame=world.frame,
                            capture_time=world.time, sender_pose=me.as_tuple(), payload=own,
                            channel_compression=self.ratio),
                    airtime, world.time, 0.0)
        for i, (data, _) in sent.items():
            if i == j:
                continue
            msg = decoded[i]
            if msg is None:
                inbox.mark_rejected(i)
                continue
            inbox.offer(msg, len(data), msg.capture_time, distance(msg.sender_pose, me.as_tuple()),
                        receiver_pose=me.as_tuple(), world=world)
        deadline = world.time + self._episode_sc.fusion_deadline_s  # as the ego does (docs/run.md)
        fusable = inbox.ready(deadline, as_of=world.time)
        for ev in inbox.take_events():
            self._note_link(ev.sender, j, ev.outcome, ev.latency_ms)
        inbox.take_bytes()
        senders = [j] + sorted(s for s in fusable if s != j)
        rel = np.zeros((len(senders), 3), np.float32)
        inp = FusionInputs(senders=senders, rel_poses=rel)
        for n, s in enumerate(senders):
            msg = fusable[s]
            rel[n] = relative_pose(me, Pose(*inbox.sender_pose(msg)))
            # its own map never went on the air: it fuses it as its encoder made it (float16, like any payload)
            inp.features[s] = (decompress(None, self._sensed[j].features.astype(np.float16)) if s == j
                               else decompress(self.compressor, dense_payload(msg, self.wire_shape)))
        return inp

    def _predict(self, method: str, inp: FusionInputs) -> Prediction:
        """A method's prediction; with no neighbour message, the single-agent one (there is nothing to fuse)."""
        if len(inp.senders) == 1:
            method = "none"
        pred = predict(method, self.models[method], inp, self._episode_sc.bev.cells)
        assert pred is not None  # the receiver's own map is always there
        return pred

    def _note_link(self, sender: str, receiver: str, outcome: str, latency_ms: float | None) -> None:
        if outcome in ("in_flight", "reused"):  # reused: an earlier message fused again, not a delivery
            return
        window = self._links.setdefault((sender, receiver), deque(maxlen=self.options.link_window))
        window.append(outcome == "delivered")
        if outcome == "delivered" and latency_ms is not None:
            self._latency[(sender, receiver)] = latency_ms

    def _observe(self, a: str) -> dict[str, np.ndarray]:
        s = self._sensed[a]
        world = self._world
        pose = world.actor(a).pose
        links = np.array([[NO_LINK, 0.0, NO_LINK]] * len(self.possible_agents), np.float32)
        for n, other in enumerate(self.possible_agents):
            actor = world.actor(other)
            if other == a or actor is None:
                continue
            window = self._links.get((a, other), ())
            links[n] = (math.hypot(actor.pose.x - pose.x, actor.pose.y - pose.y),
                        sum(window) / len(window) if window else 0.0, self._latency.get((a, other), NO_LINK))
        feats = s.features if self.options.features == "map" else s.features.mean(axis=(1, 2))
        return {"features": feats.astype(np.float32), "confidence": s.confidence.astype(np.float32),
                "pose": np.array(pose.as_tuple(), np.float32), "links": links}

    def _blank(self) -> dict[str, np.ndarray]:
        """The last observation of an agent whose vehicle left: zeros, and no links."""
        space = self.observation_space(self.possible_agents[0])
        out = {k: np.zeros(b.shape, np.float32) for k, b in space.spaces.items()}
        out["links"][:] = (NO_LINK, 0.0, NO_LINK)
        return out


def _fraction(action: Any, agent: str) -> float:
    """An action (a 1-element array or a number) as a share in [0, 1]; ValueError naming the agent if not a number."""
    a = np.asarray(action, dtype=np.float64).reshape(-1)
    if a.size != 1 or not math.isfinite(a[0]):
        raise ValueError(f"action of {agent}: expected one finite number (the share of cells to send), got {action!r}")
    return float(np.clip(a[0], 0.0, 1.0))


def _without(inp: FusionInputs, sender: str) -> FusionInputs:
    keep = [n for n, s in enumerate(inp.senders) if s != sender]
    return FusionInputs(senders=[inp.senders[n] for n in keep], rel_poses=inp.rel_poses[keep],
                        features={s: v for s, v in inp.features.items() if s != sender})
