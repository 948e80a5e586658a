"""Communication counters for metrics.json `comm` (DESIGN.md "metrics.json").

Semantics, so that senders and receivers in different processes can be merged:
  sent        messages handed to the transport (one per publication and receiving link, as the
              caller counts them), with their encoded size in bytes;
  delivered   messages the channel model let through to a receiver;
  dropped     messages the channel model lost (Bernoulli / Gilbert-Elliott);
  out_of_range messages not delivered because the link was longer than comm.range_m;
  stale       delivered messages older than max_age_ms when the receiver would fuse them;
  rejected    received bytes that failed codec validation (by reason);
  latency     channel time of fused messages (serialisation + the configured latency, arrival minus
              capture), counted once per message, in the run's clock;
  age         at every fusion, each fused neighbour message's age at the instant the fused frame describes
              (its capture time t_k): 0 when the message of frame k came by the fusion deadline, 100 ms when
              the ego fused the previous frame's, ...; AGE_BUCKET_MS-wide buckets plus p50/p95.
Under comm.channel.model tr37885 (only then; disk output is unchanged) also:
  los, nlos, nlosv       messages within range by link state (delivered or not);
  delivery_by_distance   per link state and DISTANCE_BIN_M-wide bin of the sender-receiver distance
                         ("0-25", "25-50", ...): {"sent", "delivered", "ratio"} of those messages.
Under comm.medium shared (only then) also:
  cbr      the channel busy ratio of each 100 ms window: {"mean", "p95", "windows"};
  medium   {"rate_mbps", "transmissions", "airtime_s", "superseded", "aged_out"}: what the shared
           channel carried (every CAV's broadcasts of this kind) and what senders dropped before
           sending (a newer message replaced it; it would have started older than max_age_ms).
           Messages dropped at their sender also count in `dropped`.
Not thread-safe: update it from the one thread that consumes messages.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from typing import Any

import numpy as np

from v2vsim.comm.channel import Delivery
from v2vsim.comm.medium import SharedMedium
from v2vsim.comm.tr37885 import LINK_STATES

DISTANCE_BIN_M = 25.0  # width of the delivery_by_distance bins (m)
AGE_BUCKET_MS = 100.0  # width of the age-at-fusion buckets: one frame at 10 Hz


class CommStats:
    """Running counters plus the raw samples percentiles are computed from."""

    def __init__(self) -> None:
        self.sent = 0
        self.delivered = 0
        self.dropped = 0
        self.out_of_range = 0
        self.stale = 0
        self.rejected_reasons: Counter[str] = Counter()
        self.bytes_sent = 0
        self.latency_s: list[float] = []
        self.age_s: list[float] = []  # one per (fusion, neighbour message)
        self.lost_agents: set[str] = set()
        self.link_states: Counter[str] | None = None  # None: no link states (disk); see track_link_states
        self.by_distance: Counter[tuple[str, int, bool]] = Counter()  # (state, bin, delivered) -> messages
        self.medium: dict[str, float] | None = None  # None: per-link channel; see track_medium
        self.cbr: list[float] = []  # per 100 ms window

    @property
    def rejected(self) -> int:
        return sum(self.rejected_reasons.values())

    def record_sent(self, nbytes: int, copies: int = 1) -> None:
        """A message of nbytes (len of the encoded bytes) sent `copies` times (e.g. one per link)."""
        self.sent += copies
        self.bytes_sent += nbytes * copies

    def track_link_states(self) -> Counter[str]:
        """Report link states (los/nlos/nlosv and delivery_by_distance) even while none has been counted."""
        if self.link_states is None:
            self.link_states = Counter()
        return self.link_states

    def track_medium(self) -> dict[str, float]:
        """Report the shared medium (cbr, medium) even before anything went on the air."""
        if self.medium is None:
            self.medium = {"rate_mbps": 0.0, "transmissions": 0, "airtime_s": 0.0, "superseded": 0, "aged_out": 0}
        return self.medium

    def record_medium(self, medium: SharedMedium, cbr: list[float]) -> None:
        """The medium's running totals (they replace the previous ones) and newly completed CBR windows."""
        self.medium = {"rate_mbps": medium.rate_mbps, "transmissions": medium.transmissions,
                       "airtime_s": medium.airtime_s, "superseded": medium.superseded, "aged_out": medium.aged_out}
        self.cbr.extend(cbr)

    def record_channel(self, d: Delivery, distance_m: float | None = None) -> None:
        """Count the channel model's verdict on one message (sent over distance_m, for the distance bins)."""
        if d.delivered:
            self.delivered += 1
        elif d.reason == "dropped":
            self.dropped += 1
        else:
            self.out_of_range += 1
        if d.state is not None:
            self.track_link_states()[d.state] += 1
            if distance_m is not None and math.isfinite(distance_m):
                self.by_distance[(d.state, int(max(distance_m, 0.0) // DISTANCE_BIN_M), d.delivered)] += 1

    def record_stale(self) -> None:
        self.stale += 1

    def record_rejected(self, reason: str, n: int = 1) -> None:
        self.rejected_reasons[reason] += n

    def record_fused(self, latency_s: float) -> None:
        """A message is fused for the first time; it spent latency_s on the channel (seconds, the run's clock)."""
        self.latency_s.append(float(latency_s))

    def record_age(self, age_s: float) -> None:
        """A neighbour message was fused age_s after its capture, measured at the fused frame's instant."""
        self.age_s.append(float(age_s))

    def record_lost_agent(self, agent_id: str) -> None:
        self.lost_agents.add(agent_id)

    def merge(self, other: CommStats) -> CommStats:
        """Add another process's counters into this one (returns self)."""
        self.sent += other.sent
        self.delivered += other.delivered
        self.dropped += other.dropped
        self.out_of_range += other.out_of_range
        self.stale += other.stale
        self.rejected_reasons.update(other.rejected_reasons)
        self.bytes_sent += other.bytes_sent
        self.latency_s.extend(other.latency_s)
        self.age_s.extend(other.age_s)
        self.lost_agents |= other.lost_agents
        if other.link_states is not None:
            self.track_link_states().update(other.link_states)
        self.by_distance.update(other.by_distance)
        if other.medium is not None:
            mine = self.track_medium()
            for key, v in other.medium.items():
                mine[key] = max(mine[key], v) if key == "rate_mbps" else mine[key] + v
        self.cbr.extend(other.cbr)
        return self

    def latency_percentile_ms(self, q: float) -> float | None:
        if not self.latency_s:
            return None
        return round(float(np.percentile(np.asarray(self.latency_s) * 1000.0, q)), 3)

    def age_json(self) -> dict[str, Any]:
        """{"fused": n, "buckets": {"0": n, "100": n, ...}, "p50", "p95"} of the ages at fusion (ms)."""
        ms = np.asarray(self.age_s, dtype=float) * 1000.0
        # a frame-k message fused at frame k is 0 ms old; k-1's is 100 ms (+- float error): bucket by lower bound
        buckets = Counter(int(math.floor(v / AGE_BUCKET_MS + 1e-6) * AGE_BUCKET_MS) for v in ms)
        return {"fused": int(ms.size),
                "buckets": {str(b): buckets[b] for b in sorted(buckets)},
                "p50": round(float(np.percentile(ms, 50)), 3) if ms.size else None,
                "p95": round(float(np.percentile(ms, 95)), 3) if ms.size else None}

    @property
    def bytes_per_message(self) -> int:
        return round(self.bytes_sent / self.sent) if self.sent else 0

    def delivery_by_distance(self) -> dict[str, dict[str, dict[str, Any]]]:
        """{state: {"lo-hi": {"sent", "delivered", "ratio"}}} over the distance bins that saw a message."""
        out: dict[str, dict[str, dict[str, Any]]] = {s: {} for s in LINK_STATES}
        bins = sorted({(s, b) for s, b, _ in self.by_distance}, key=lambda k: (LINK_STATES.index(k[0]), k[1]))
        for state, b in bins:
            ok, lost = self.by_distance[(state, b, True)], self.by_distance[(state, b, False)]
            lo, hi = b * DISTANCE_BIN_M, (b + 1) * DISTANCE_BIN_M
            out[state][f"{lo:g}-{hi:g}"] = {"sent": ok + lost, "delivered": ok, "ratio": round(ok / (ok + lost), 4)}
        return out

    def to_json(self) -> dict[str, Any]:
        """The metrics.json `comm` object (contract keys first, then extras; link states only under tr37885)."""
        doc: dict[str, Any] = {
            "sent": self.sent,
            "delivered": self.delivered,
            "dropped": self.dropped,
            "stale": self.stale,
            "rejected": self.rejected,
            "bytes_per_message": self.bytes_per_message,
            "latency_ms": {"p50": self.latency_percentile_ms(50), "p95": self.latency_percentile_ms(95)},
            "out_of_range": self.out_of_range,
            "bytes_total": self.bytes_sent,
            "rejected_reasons": dict(sorted(self.rejected_reasons.items())),
            "lost_agents": sorted(self.lost_agents),
            "age_ms": self.age_json(),
        }
        if self.link_states is not None:
            doc.update({s: self.link_states[s] for s in LINK_STATES})
            doc["delivery_by_distance"] = self.delivery_by_distance()
        if self.medium is not None:
            cbr = np.asarray(self.cbr, dtype=float)
            doc["cbr"] = {"mean": round(float(cbr.mean()), 4) if cbr.size else None,
                          "p95": round(float(np.percentile(cbr, 95)), 4) if cbr.size else None,
                          "windows": int(cbr.size)}
            doc["medium"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.medium.items()}
        return doc

    def to_state(self) -> dict[str, Any]:
        """Everything, raw samples included, as plain JSON types (to ship to another process)."""
        return {"sent": self.sent, "delivered": self.delivered, "dropped": self.dropped,
                "out_of_range": self.out_of_range, "stale": self.stale,
                "rejected_reasons": dict(self.rejected_reasons), "bytes_sent": self.bytes_sent,
                "latency_s": list(self.latency_s), "age_s": list(self.age_s), "lost_agents": sorted(self.lost_agents),
                "link_states": None if self.link_states is None else dict(self.link_states),
                "by_distance": [[s, b, ok, n] for (s, b, ok), n in sorted(self.by_distance.items())],
                "medium": self.medium, "cbr": list(self.cbr)}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> CommStats:
        s = cls()
        s.sent, s.delivered, s.dropped = int(state["sent"]), int(state["delivered"]), int(state["dropped"])
        s.out_of_range, s.stale = int(state["out_of_range"]), int(state["stale"])
        s.rejected_reasons = Counter({str(k): int(v) for k, v in state["rejected_reasons"].items()})
        s.bytes_sent = int(state["bytes_sent"])
        s.latency_s = [float(v) for v in state["latency_s"]]
        s.age_s = [float(v) for v in state.get("age_s", [])]
        s.lost_agents = set(state["lost_agents"])
        if state.get("link_states") is not None:  # absent in states written before tr37885
            s.link_states = Counter({str(k): int(v) for k, v in state["link_states"].items()})
        s.by_distance = Counter({(str(st), int(b), bool(ok)): int(n) for st, b, ok, n in state.get("by_distance", [])})
        if state.get("medium") is not None:
            s.medium = dict(state["medium"])
        s.cbr = [float(v) for v in state.get("cbr", [])]
        return s

    def __repr__(self) -> str:
        return f"CommStats({json.dumps(self.to_json())})"
