"""One receiver's side of the channel: every received message passes its link's channel model,
and at fusion time the newest delivered, non-stale message per sender is handed out.

One `LinkModel` per (sender, receiver, message kind), all seeded from (seed, sender, receiver):
the kinds share one random stream, so the same frames are lost for every method and only the
serialisation delay differs with the message size. The receiver's own message skips the channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from v2vsim.comm.channel import LinkModel, is_stale
from v2vsim.comm.codec import Message
from v2vsim.comm.stats import CommStats
from v2vsim.comm.tr37885 import LinkGeometry
from v2vsim.config import CommConfig
from v2vsim.world import WorldState


@dataclass(frozen=True)
class Arrival:
    message: Message
    size: int
    arrival_time: float
    latency_s: float = 0.0  # on the channel (0 for the receiver's own message)


Outcome = Literal["delivered", "in_flight", "dropped", "out_of_range", "stale", "rejected"]


@dataclass(frozen=True)
class LinkEvent:
    """What one sender's link did at one fusion instant (the recording draws it as a V2V link).

    delivered: a message from this sender is fused for the first time now (latency_ms: its
    channel latency); otherwise the fate of its newest message: still in flight (latency_ms: when
    it will arrive), dropped, out of range or rejected by the decoder; stale: what it had sent
    became too old and nothing newer came."""

    sender: str
    outcome: Outcome
    latency_ms: float | None = None


class Inbox:
    """Messages of one kind for one receiver. Not thread-safe: feed it from the fusing thread."""

    def __init__(self, cfg: CommConfig, seed: int, receiver: str, kind: str, stats: CommStats | None = None) -> None:
        self.cfg = cfg
        self.seed = seed
        self.receiver = receiver
        self.kind = kind
        self.stats = stats if stats is not None else CommStats()
        if cfg.channel.model == "tr37885":
            self.stats.track_link_states()  # metrics.json gains los/nlos/nlosv even if nothing comes in range
        self._links: dict[str, LinkModel] = {}
        self._pending: dict[str, list[Arrival]] = {}
        self._latest: dict[str, Arrival] = {}  # the newest fused-or-fusable message per sender
        self._fused: set[tuple[str, int]] = set()  # (sender, frame) whose send-to-fuse latency is recorded
        self._events: dict[str, LinkEvent] = {}  # per sender, since the last take_events()
        self.bytes_this_frame = 0

    def link(self, sender: str) -> LinkModel:
        if sender not in self._links:
            self._links[sender] = LinkModel(self.cfg, self.seed, sender, self.receiver)
        return self._links[sender]

    def offer(self, msg: Message, size: int, send_time: float, distance_m: float, *,
              receiver_pose: tuple[float, ...] | None = None, world: WorldState | None = None) -> None:
        """A message came off the transport: decide its fate on the link and queue it if it arrives.

        Under comm.channel.model tr37885 the link also needs the receiver's pose when the message was sent (the
        sender's is msg.sender_pose) and the world whose buildings and vehicles may block it; disk ignores both."""
        if msg.sender_id == self.receiver:
            self._pending.setdefault(msg.sender_id, []).append(Arrival(msg, size, send_time))
            return
        self.bytes_this_frame += size  # what crossed the air; the receiver's own message did not
        self.stats.record_sent(size)
        geometry = None
        if self.cfg.channel.model == "tr37885":
            if receiver_pose is None:
                raise ValueError("comm.channel.model tr37885: Inbox.offer needs receiver_pose")
            geometry = LinkGeometry(tuple(msg.sender_pose), tuple(receiver_pose), world)
        d = self.link(msg.sender_id).transmit(size, send_time, distance_m, geometry)
        self.stats.record_channel(d, distance_m)
        if d.delivered:
            self._pending.setdefault(msg.sender_id, []).append(Arrival(msg, size, d.arrival_time, d.latency))
            self._events[msg.sender_id] = LinkEvent(msg.sender_id, "in_flight", d.latency * 1e3)
        else:
            self._events[msg.sender_id] = LinkEvent(msg.sender_id, d.reason)

    def mark_rejected(self, sender: str) -> None:
        """A message from `sender` failed decoding (already counted in stats by the decoder)."""
        if sender != self.receiver:
            self._events[sender] = LinkEvent(sender, "rejected")

    def sender_pose(self, msg: Message) -> tuple[float, float, float, float]:
        """The sender's capture pose as this receiver knows it (pose noise per link)."""
        if msg.sender_id == self.receiver:
            return msg.sender_pose
        return self.link(msg.sender_id).noisy_pose(msg.sender_pose)

    def ready(self, now: float) -> dict[str, Message]:
        """The newest message per sender that has arrived by `now` and is not older than max_age_ms."""
        out: dict[str, Message] = {}
        for sender, queue in self._pending.items():
            arrived = [a for a in queue if a.arrival_time <= now]
            self._pending[sender] = [a for a in queue if a.arrival_time > now]
            for a in arrived:
                prev = self._latest.get(sender)
                if prev is None or a.message.frame > prev.message.frame:
                    self._latest[sender] = a
        for sender, a in list(self._latest.items()):
            if is_stale(a.message.capture_time, now, self.cfg.max_age_ms):
                if sender != self.receiver:
                    self.stats.record_stale()
                    self._events.setdefault(sender, LinkEvent(sender, "stale"))
                del self._latest[sender]  # counted once; an older message never comes back
                continue
            out[sender] = a.message
            if sender != self.receiver and (sender, a.message.frame) not in self._fused:
                self._fused.add((sender, a.message.frame))  # a message reused in later frames counts once
                self.stats.record_fused(now - a.message.capture_time)
                self._events[sender] = LinkEvent(sender, "delivered", a.latency_s * 1e3)
        return out

    def take_events(self) -> list[LinkEvent]:
        """Each sender's link event since the last call, by sender."""
        events, self._events = self._events, {}
        return [events[s] for s in sorted(events)]

    def take_bytes(self) -> int:
        """Bytes received for this kind since the last call (the method's bytes_per_frame)."""
        n, self.bytes_this_frame = self.bytes_this_frame, 0
        return n


def distance(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])
