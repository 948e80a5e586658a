"""The ego's mailbox and its waits: raw messages kept by (kind, frame, sender) as zenoh delivers them,
the worlds and the driver's done, and the waits of ego_loop for the next world (or why none will come)
and, in lockstep, for every live CAV's messages of a frame.
"""

from __future__ import annotations

import json
import math
import signal
import struct
import sys
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass

from agents.bus import DRIVER_GRACE_S, START_TIMEOUT_S, Bus
from agents.worlds import admit_world, world_frame
from v2vsim.comm.codec import RejectedMessage
from v2vsim.comm.control import DRIVER
from v2vsim.config import Scenario
from v2vsim.recording.scan import scan_frame

HANG_TIMEOUT_S = 60.0  # a driver alive but silent this long is a hang; a live CAV's default (transport.lost_after_s)
# Side channels between our own processes, not V2V messages: not channel-modelled, not counted.
SIDE_KINDS = ("vis", "scan", "own")  # "own": the ego's uncompressed map from its own CAV process


@dataclass(frozen=True)
class Window:
    """Which frames the ego can still use a message for, as frames relative to the pipeline.

    A CAV sends frame f only after the driver published world f, and in lockstep the driver publishes
    world k+1 only once this ego fused frame k - transport.pipeline; so an honest message is for a frame
    at most `ahead` past the last frame the ego collected (realtime: past the newest world it has; no
    acks hold the driver back). A message older than `behind` frames before the last collected one can
    only be fused stale (comm.max_age_ms), so it is not kept either."""

    ahead: int  # transport.pipeline + 1, and 1 for a message that overtakes its world
    behind: int  # frames within comm.max_age_ms
    realtime: bool = False

    @classmethod
    def for_scenario(cls, sc: Scenario) -> Window:
        return cls(ahead=sc.transport.pipeline + 2, behind=math.ceil(sc.comm.max_age_ms / 1000 * sc.rate_hz) + 1,
                   realtime=sc.transport.clock == "realtime")


ArrivalCheck = Callable[[str, str, bytes], int]
"""check(kind, key sender, bytes) -> the frame the message is for, or RejectedMessage(reason): the
cheap checks on arrival (header, signature, run, sender: v2vsim.comm.wire_spec.EgoDecoder.check_arrival)."""


class Mailbox:
    """Raw messages by (kind, frame), one per sender, filled on zenoh's thread, read on the main thread.

    What it holds is bounded whatever arrives (issue 34): a message longer than its kind's `limits`,
    failing `check` (a forged signature never takes a slot), for a frame outside the `window`, or for a
    (kind, frame, sender) slot it already holds or held is not kept, only counted in `rejected` by reason
    (out_of_window, duplicate, replayed, or the check's). So memory is at most (window frames x senders x
    kinds) messages of bounded size, and only what a method could fuse reaches the channel model and its
    byte counts. Side kinds (vis, scan, own) are bounded the same way but never counted as V2V rejections."""

    def __init__(self, limits: dict[str, int] | None = None, *, check: ArrivalCheck | None = None,
                 window: Window | None = None) -> None:
        self.cond = threading.Condition()
        self.raw: dict[tuple[str, int], list[tuple[str, bytes]]] = defaultdict(list)  # (sender key, bytes)
        self.rejected: Counter[tuple[str, str]] = Counter()  # (kind, reason) decided on arrival
        self.worlds: dict[int, bytes] = {}  # within the window too (put_world)
        self.done = False
        self.newest_world = -1
        self.collected = -1  # the latest frame taken out for fusion (ego_collect.collect)
        self.limits = dict(limits or {})
        self.check = check
        self.window = window
        self._held: dict[int, set[tuple[str, str]]] = defaultdict(set)  # frame -> {(kind, sender)} ever kept
        # output.record_messages: told what collect() took for each frame (v2vsim.recording.messages.MessageTape)
        self.on_collect: Callable[[int, dict[str, list[tuple[str, bytes]]], Counter], None] | None = None

    def put(self, kind: str, sender: str, data: bytes) -> None:
        limit = self.limits.get(kind, 0)
        if limit and len(data) > limit:
            self._reject(kind, "size_mismatch")
            return
        if self.check is not None and kind not in SIDE_KINDS[:2]:
            try:
                frame: int | None = self.check(kind, sender, data)
            except RejectedMessage as e:
                self._reject(kind, e.reason)
                return
        else:
            frame = _peek_frame(kind, data)
        if frame is None:
            self._reject(kind, "truncated")
            return
        with self.cond:
            reason = self._refuse(kind, sender, frame, data)
            if reason is None:
                self._held[frame].add((kind, sender))
                self.raw[(kind, frame)].append((sender, data))
                self.cond.notify_all()
        if reason is not None:
            self._reject(kind, reason)

    def _refuse(self, kind: str, sender: str, frame: int, data: bytes) -> str | None:
        """Why frame `frame` of `kind` from `sender` is not kept (None: keep it). Under self.cond."""
        w = self.window
        if w is not None:
            ref = max(self.collected, self.newest_world) if w.realtime else self.collected
            if frame > ref + w.ahead or frame < self.collected - w.behind:
                return "out_of_window"
        if (kind, sender) in self._held.get(frame, ()):
            held = [d for s, d in self.raw.get((kind, frame), ()) if s == sender]
            return "duplicate" if held and held[0] != data else "replayed"
        return None

    def _reject(self, kind: str, reason: str) -> None:
        if kind in SIDE_KINDS:  # our own processes' side channels: not V2V traffic, not counted
            return
        with self.cond:
            self.rejected[(kind, reason)] += 1

    def mark_collected(self, k: int) -> None:
        """Frame k was taken out for fusion: the window moves on. Under self.cond."""
        self.collected = max(self.collected, k)
        if self.window is not None:  # slots too old to be kept again need no memory of being held
            for f in [f for f in self._held if f < self.collected - self.window.behind]:
                del self._held[f]

    def refused(self, kind: str, reason: str) -> None:
        """Count a message of `kind` refused before `put` (too long to copy off the transport: agents/bus.py)."""
        self._reject(kind, reason)

    def pending(self) -> int:
        """Messages held, for every kind and frame (a bound the flood test checks)."""
        with self.cond:
            return sum(len(v) for v in self.raw.values())


def _peek_frame(kind: str, data: bytes) -> int | None:
    """The frame a message claims, without validating it (validation happens at decode)."""
    if kind == "vis":
        try:
            return int(json.loads(data)["frame"])
        except (ValueError, KeyError, TypeError):
            return None
    if kind == "scan":
        return scan_frame(data)
    try:
        return int(struct.unpack_from("<I", data, 12)[0])  # codec fixed header: frame after 12 bytes
    except struct.error:
        return None


def put_world(box: Mailbox, data: bytes) -> None:
    """Keep a world the ego will fuse, within the mailbox's window like V2V messages (agents/worlds.py says why):
    RejectedMessage (the Bus counts it) for one that is not a world, too long, out of the window, or a second,
    different world for a frame held. A world for a frame fused already (sent again) is dropped silently."""
    frame = world_frame(data)
    w = box.window
    with box.cond:
        if admit_world(box.worlds, frame, data, box.collected, box.newest_world, None if w is None else w.ahead,
                       w is not None and w.realtime):
            box.newest_world = max(box.newest_world, frame)
            box.cond.notify_all()


def set_done(box: Mailbox) -> None:
    with box.cond:
        box.done = True
        box.cond.notify_all()


def notify(box: Mailbox) -> None:
    with box.cond:
        box.cond.notify_all()


def wait_world(box: Mailbox, bus: Bus, k: int, realtime: bool) -> tuple[int, bytes] | str:
    """World k (lockstep), or the newest world from k on (realtime: frames we fell behind on are skipped),
    or why none will come: "done" (the driver finished), "died" (its token dropped without a bye or
    done), "interrupted" (it was stopped by SIGINT: the run's Ctrl-C), the reason it gave in its bye, or
    "no world for N s" when the driver, alive as far as anyone can tell, sent none for that long (frame 0:
    START_TIMEOUT_S, the driver waits for every agent to start; later: HANG_TIMEOUT_S)."""
    gone_at = None
    bound = START_TIMEOUT_S if k == 0 else HANG_TIMEOUT_S
    deadline = time.monotonic() + bound
    with box.cond:
        while True:
            ready = [f for f in box.worlds if f >= k]
            if ready and (realtime or k in box.worlds):
                f = max(ready) if realtime else k
                data = box.worlds[f]
                for old in [x for x in box.worlds if x <= f]:
                    del box.worlds[old]
                return f, data
            now = time.monotonic()
            gone = bus.driver_gone()
            # A verified done is the driver's; without comm.auth anyone could have sent it, so it is believed
            # once the driver is gone too. An honest driver says done only after every live ego acked the last
            # frame, so a done that comes while this ego still waits for a world is from the future (the old
            # rule, believed after DONE_GRACE_S without a world, let a forged one end a run waiting on a slow ego).
            if box.done and (bus.authenticated or gone):
                return "done"
            if gone:
                gone_at = gone_at or now
                bye = bus.farewell(DRIVER)
                if bye is not None and bye.get("code") == 128 + signal.SIGINT:
                    return "interrupted"
                if bye is not None:
                    return f"exit {bye.get('code')}: {bye.get('why', '')}"
                if now - gone_at > DRIVER_GRACE_S:
                    return "died"
            elif now > deadline:
                return f"no world for {bound:g} s"
            box.cond.wait(0.2 if gone or box.done else 0.5)


def cav_died(bus: Bus, cav: str) -> bool:
    """Its token dropped without a clean bye (a CAV whose vehicle left says bye with code 0)."""
    if not bus.was_alive(f"cav.{cav}") or bus.is_alive(f"cav.{cav}"):
        return False
    bye = bus.farewell(f"cav.{cav}")
    return bye is None or bye.get("code") != 0


def wait_messages(box: Mailbox, bus: Bus, k: int, present: list[str], kinds: list[str],
                  lost: dict[str, int], lost_after_s: float = HANG_TIMEOUT_S) -> None:
    """Lockstep: wait until every live CAV's frame-k messages of `kinds` are in (or it is lost: gone, or silent for
    `lost_after_s`, transport.lost_after_s)."""
    deadline = time.monotonic() + lost_after_s
    with box.cond:
        while True:
            missing = [c for c in present if c not in lost and not all(
                any(s == c for s, _ in box.raw.get((kind, k), ())) for kind in kinds)]
            dead = [c for c in missing if bus.was_alive(f"cav.{c}") and not bus.is_alive(f"cav.{c}")]
            for c in dead:
                lost[c] = k
                print(f"v2vsim-ego: CAV {c} is gone at frame {k}; fusing the others", file=sys.stderr)
            if not [c for c in missing if c not in dead]:
                return
            if time.monotonic() > deadline:
                for c in missing:
                    lost[c] = k
                    print(f"v2vsim-ego: CAV {c} sent nothing for {lost_after_s:g} s at frame {k}; "
                          "treating it as lost", file=sys.stderr)
                return
            box.cond.wait(0.2)
