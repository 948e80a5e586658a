"""One receiver's side of the channel: every received message passes its link's channel model,
and at fusion time the newest delivered, non-stale message per sender is handed out.

One `LinkModel` per (sender, receiver, message kind), all seeded from (seed, sender, receiver):
the kinds share one random stream, so the same frames are lost for every method and only the
serialisation delay differs with the message size. The receiver's own message skips the channel.

comm.medium shared: each kind also has one `SharedMedium` that every CAV's broadcast of that kind
(the receiver's own included) queues on; a message's link is judged when the medium starts it, so
its delivery waits for the channel, and one dropped at the sender (superseded or too old) is lost.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

from v2vsim.comm.channel import Delivery, LinkModel, data_rate_mbps, is_stale
from v2vsim.comm.codec import Message
from v2vsim.comm.medium import SharedMedium
from v2vsim.comm.stats import CommStats
from v2vsim.comm.tr37885 import LinkGeometry
from v2vsim.config import CommConfig
from v2vsim.world.state import WorldState


@dataclass(frozen=True)
class Arrival:
    message: Message
    size: int
    arrival_time: float
    latency_s: float = 0.0  # on the channel (0 for the receiver's own message)


Outcome = Literal["delivered", "reused", "in_flight", "dropped", "out_of_range", "stale", "rejected"]


@dataclass(frozen=True)
class LinkEvent:
    """What one sender's link did at one fusion instant (the recording draws it as a V2V link).

    delivered: a message from this sender is fused for the first time now (latency_ms: its
    channel latency); reused: nothing newer came by the deadline, so an earlier message is fused
    again; otherwise the fate of its newest message: still in flight (latency_ms: when it will
    arrive), dropped, out of range or rejected by the decoder; stale: what it had sent became too
    old and nothing newer came. age_ms: the fused message's age at the fused frame's instant."""

    sender: str
    outcome: Outcome
    latency_ms: float | None = None
    age_ms: float | None = None


@dataclass(frozen=True)
class _OnAir:
    """A message waiting for the shared medium, with what its link needs to judge it."""

    message: Message
    size: int
    distance_m: float
    geometry: LinkGeometry | None


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
        self._previous: dict[str, Message] = {}  # the one _latest replaced, per sender
        self._fused: set[tuple[str, int]] = set()  # (sender, frame) whose channel latency is recorded
        self._events: dict[str, LinkEvent] = {}  # per sender, since the last take_events()
        self.bytes_this_frame = 0
        self.bytes_by_sender: dict[str, int] = {}  # every message that crossed the air, by sender (a mixed fleet's
        # report splits them by agent type)
        self.medium: SharedMedium[_OnAir] | None = None
        if cfg.medium == "shared":
            rate = data_rate_mbps(cfg)
            if rate is None:
                raise ValueError("comm.medium shared needs comm.bandwidth_mbps or comm.channel.model tr37885")
            self.medium = SharedMedium(rate, cfg.max_age_ms / 1000.0, seed)
            self.stats.track_medium()

    def link(self, sender: str) -> LinkModel:
        if sender not in self._links:
            self._links[sender] = LinkModel(self.cfg, self.seed, sender, self.receiver)
        return self._links[sender]

    def offer(self, msg: Message, size: int, send_time: float, distance_m: float, *,
              receiver_pose: tuple[float, ...] | None = None, world: WorldState | None = None) -> None:
        """A message came off the transport: decide its fate on the link and queue it if it arrives.

        Under comm.channel.model tr37885 the link also needs the receiver's pose when the message was sent (the
        sender's is msg.sender_pose) and the world whose buildings and vehicles may block it; disk ignores both."""
        own = msg.sender_id == self.receiver
        if own:
            self._pending.setdefault(msg.sender_id, []).append(Arrival(msg, size, send_time))
        geometry = None
        if self.cfg.channel.model == "tr37885" and not own:
            if receiver_pose is None:
                raise ValueError("comm.channel.model tr37885: Inbox.offer needs receiver_pose")
            geometry = LinkGeometry(tuple(msg.sender_pose), tuple(receiver_pose), world)
        if self.medium is not None:  # the own broadcast takes airtime too
            self.medium.enqueue(msg.sender_id, msg.frame, size, send_time, msg.capture_time,
                                _OnAir(msg, size, distance_m, geometry))
            if not own:
                self.bytes_this_frame += size
                self.bytes_by_sender[msg.sender_id] = self.bytes_by_sender.get(msg.sender_id, 0) + size
                self.stats.record_sent(size)
                self._events[msg.sender_id] = LinkEvent(msg.sender_id, "in_flight")  # waiting for the channel
            return
        if own:
            return
        self.bytes_this_frame += size  # what crossed the air; the receiver's own message did not
        self.bytes_by_sender[msg.sender_id] = self.bytes_by_sender.get(msg.sender_id, 0) + size
        self.stats.record_sent(size)
        d = self.link(msg.sender_id).transmit(size, send_time, distance_m, geometry)
        self._judge(msg, size, d, distance_m)

    def _judge(self, msg: Message, size: int, d: Delivery, distance_m: float) -> None:
        self.stats.record_channel(d, distance_m)
        if d.delivered:
            self._pending.setdefault(msg.sender_id, []).append(Arrival(msg, size, d.arrival_time, d.latency))
            self._events[msg.sender_id] = LinkEvent(msg.sender_id, "in_flight", d.latency * 1e3)
        else:
            self._events[msg.sender_id] = LinkEvent(msg.sender_id, d.reason)

    def _dropped_at_sender(self, on_air: _OnAir) -> None:
        if on_air.message.sender_id != self.receiver:
            self.stats.record_channel(Delivery(False, "dropped", math.inf, on_air.message.capture_time))
            self._events[on_air.message.sender_id] = LinkEvent(on_air.message.sender_id, "dropped")

    def _advance_medium(self, now: float) -> None:
        """Judge, on its link, every message the shared medium starts by `now`."""
        assert self.medium is not None
        started, dropped = self.medium.advance(now)
        for on_air in dropped:
            self._dropped_at_sender(on_air)
        for tx in started:
            m = tx.item.message
            if m.sender_id == self.receiver:
                continue
            d = self.link(m.sender_id).transmit(tx.size, tx.ready, tx.item.distance_m, tx.item.geometry, start=tx.start)
            self._judge(m, tx.size, d, tx.item.distance_m)
        self.stats.record_medium(self.medium, self.medium.take_cbr(now))

    def mark_rejected(self, sender: str) -> None:
        """A message from `sender` failed decoding (already counted in stats by the decoder)."""
        if sender != self.receiver:
            self._events[sender] = LinkEvent(sender, "rejected")

    def sender_pose(self, msg: Message) -> tuple[float, float, float, float]:
        """The sender's capture pose as this receiver knows it (pose noise per link)."""
        if msg.sender_id == self.receiver:
            return msg.sender_pose
        return self.link(msg.sender_id).noisy_pose(msg.sender_pose)

    def ready(self, now: float, as_of: float | None = None) -> dict[str, Message]:
        """The newest message per sender that has arrived by `now` and is not older than max_age_ms at `as_of`.

        `now` is when the receiver fuses (the fused frame's capture time plus comm.fusion_deadline_ms) and
        `as_of` the instant the fused frame describes (its capture time; default `now`): a message captured at
        `as_of` that arrived by the deadline is fused aligned, age 0. Every neighbour message handed out is
        counted with its age at `as_of` (CommStats.record_age), and, the first time, its channel latency."""
        as_of = now if as_of is None else as_of
        if self.medium is not None:
            self._advance_medium(now)
        out: dict[str, Message] = {}
        for sender, queue in self._pending.items():
            arrived = [a for a in queue if a.arrival_time <= now]
            self._pending[sender] = [a for a in queue if a.arrival_time > now]
            for a in arrived:
                prev = self._latest.get(sender)
                if prev is None or a.message.frame > prev.message.frame:
                    if prev is not None:
                        self._previous[sender] = prev.message
                    self._latest[sender] = a
        for sender, a in list(self._latest.items()):
            if is_stale(a.message.capture_time, as_of, self.cfg.max_age_ms):
                if sender != self.receiver:
                    self.stats.record_stale()
                    self._events.setdefault(sender, LinkEvent(sender, "stale"))
                del self._latest[sender]  # counted once; an older message never comes back
                self._previous.pop(sender, None)  # nor its predecessor: compensation needs two recent messages
                continue
            out[sender] = a.message
            if sender == self.receiver:
                continue
            age_s = as_of - a.message.capture_time
            self.stats.record_age(age_s)
            if (sender, a.message.frame) not in self._fused:
                self._fused.add((sender, a.message.frame))  # a message reused in later frames counts once
                self.stats.record_fused(a.latency_s)
                self._events[sender] = LinkEvent(sender, "delivered", a.latency_s * 1e3, age_s * 1e3)
            else:  # fused again, older: the link's label carries the age of what is fused
                prior = self._events.get(sender)
                self._events[sender] = (LinkEvent(sender, "reused", None, age_s * 1e3) if prior is None
                                        else dataclasses.replace(prior, age_ms=age_s * 1e3))
        return out

    def previous(self, sender: str) -> Message | None:
        """The message `sender` had delivered before the one `ready` now hands out (an older frame), if any:
        what latency compensation estimates motion from."""
        return self._previous.get(sender)

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
