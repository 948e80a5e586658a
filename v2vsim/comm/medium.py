"""One broadcast channel shared by every CAV (comm.medium: shared).

Per-link mode gives every (sender, receiver) link its own comm.bandwidth_mbps, as OpenCOOD's
"1.06 Mb / 27 Mbps" does. A V2V broadcast is one transmission on one channel that every CAV
shares: at 10 Hz, four CAVs sending 131 KB feature maps offer about 42 Mbps of airtime to a
10 MHz ITS-G5 channel whose fastest MCS carries 27 Mbps. Here:

- A message occupies the channel for size * 8 / rate (the link's data rate, `data_rate_mbps`).
- Transmissions go one at a time (CSMA with every CAV in carrier-sense range of every other:
  one junction), in order of readiness; messages ready at the same instant go in a random
  order drawn per (seed, frame, sender), like a backoff, and the same in every process.
- Each sender holds one message waiting (ETSI DCC's gatekeeper holds one packet per queue):
  a newer one replaces it (`superseded`), so the queue never serves last second's map.
- A message that would start more than comm.max_age_ms after its capture is dropped at the
  sender (`aged_out`): fusion would throw it away anyway, and it would only cost airtime.
- The channel busy ratio (CBR, ETSI TS 102 687) is the busy share of each 100 ms window.

Not modelled: hidden terminals (with everyone in carrier-sense range no two transmissions
overlap, so the SINR is the SNR), MAC overheads (preamble, AIFS, backoff slots; sizes are
payload bytes), and DCC's rate control.

Every receiver keeps its own copy: it sees every CAV's broadcast of this kind (its own
included), so copies in different processes make the same schedule from the same messages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np

from v2vsim.comm.channel import id_entropy

T = TypeVar("T")

CBR_WINDOW_S = 0.1  # ETSI TS 102 687: CBR measured over 100 ms


def backoff_rank(seed: int, frame: int, sender: str) -> float:
    """A uniform draw per (seed, frame, sender) that orders messages ready at the same instant."""
    ss = np.random.SeedSequence([int(seed), 0x6D656469, int(frame), *id_entropy(sender)])
    return float(np.random.Generator(np.random.PCG64(ss)).random())


@dataclass(frozen=True)
class Transmission(Generic[T]):
    """A message on the air from `start` to `end` (seconds of the run's clock)."""

    sender: str
    frame: int
    size: int
    ready: float  # when the sender handed it to the radio
    start: float
    end: float
    item: T  # what the caller queued with it


@dataclass(order=True)
class _Waiting(Generic[T]):
    ready: float
    rank: float
    sender: str
    frame: int = field(compare=False)
    size: int = field(compare=False)
    capture_time: float = field(compare=False)
    item: T = field(compare=False)


class SharedMedium(Generic[T]):
    """The channel's schedule as one receiver sees it. Feed it in time order from one thread:
    `enqueue` what was sent, in order of readiness (lockstep: frame by frame), then `advance(now)`
    returns what started by `now`."""

    def __init__(self, rate_mbps: float, max_age_s: float, seed: int, window_s: float = CBR_WINDOW_S) -> None:
        if not (rate_mbps > 0 and math.isfinite(rate_mbps)):
            raise ValueError(f"a shared medium needs a finite data rate, got {rate_mbps!r} Mbps")
        self.rate_mbps = rate_mbps
        self.max_age_s = max_age_s
        self.seed = seed
        self.window_s = window_s
        self.busy_until = -math.inf
        self.clock = -math.inf  # the latest `now` advanced to: nothing starts before it
        self.airtime_s = 0.0
        self.transmissions = 0
        self.superseded = 0
        self.aged_out = 0
        self._waiting: dict[str, _Waiting[T]] = {}
        self._started: list[Transmission[T]] = []  # since the last advance()
        self._dropped: list[T] = []  # superseded or aged out, since the last advance()
        self._busy: list[tuple[float, float]] = []  # (start, end) of transmissions not yet fully counted in a window
        self._next_window: int | None = None  # index of the first window not yet reported

    def airtime(self, size_bytes: int) -> float:
        return size_bytes * 8.0 / (self.rate_mbps * 1e6)

    def enqueue(self, sender: str, frame: int, size: int, ready: float, capture_time: float, item: T) -> None:
        """Queue a message handed to the radio at `ready`. What was due to start before `ready` starts
        first; a message its sender still has waiting is dropped for the newer one (`superseded`)."""
        self._run(ready, inclusive=False)
        new = _Waiting(ready, backoff_rank(self.seed, frame, sender), sender, frame, size, capture_time, item)
        if self._next_window is None:
            self._next_window = math.floor(ready / self.window_s)
        old = self._waiting.get(sender)
        if old is not None and old.frame > frame:  # a stale duplicate: the newer one keeps its place
            old, new = new, old
        self._waiting[sender] = new
        if old is not None:
            self.superseded += 1
            self._dropped.append(old.item)

    def advance(self, now: float) -> tuple[list[Transmission[T]], list[T]]:
        """Start every message whose turn comes by `now`; returns what started and what senders dropped
        (superseded or too old) since the last call."""
        self._run(now, inclusive=True)
        self.clock = max(self.clock, now)
        started, dropped = self._started, self._dropped
        self._started, self._dropped = [], []
        return started, dropped

    def _run(self, until: float, inclusive: bool) -> None:
        while self._waiting:
            w = min(self._waiting.values())  # when the channel frees, the earliest-ready goes (ties: backoff rank)
            t0 = max(self.busy_until, w.ready, self.clock)
            if t0 > until or (t0 == until and not inclusive):
                return
            del self._waiting[w.sender]
            if t0 - w.capture_time > self.max_age_s + 1e-9:
                self.aged_out += 1
                self._dropped.append(w.item)
                continue
            end = t0 + self.airtime(w.size)
            self.busy_until = end
            self.airtime_s += end - t0
            self.transmissions += 1
            self._busy.append((t0, end))
            self._started.append(Transmission(w.sender, w.frame, w.size, w.ready, t0, end, w.item))

    def take_cbr(self, now: float) -> list[float]:
        """The CBR of every 100 ms window that ended by `now` and was not returned before (later
        transmissions cannot start before `now`, so those windows are final)."""
        if self._next_window is None:
            return []
        out: list[float] = []
        w = self._next_window
        while (w + 1) * self.window_s <= now + 1e-12:
            lo, hi = w * self.window_s, (w + 1) * self.window_s
            busy = sum(max(0.0, min(e, hi) - max(s, lo)) for s, e in self._busy)
            out.append(min(1.0, busy / self.window_s))
            w += 1
        self._next_window = w
        self._busy = [(s, e) for s, e in self._busy if e > w * self.window_s]
        return out
