"""The ego's mailbox and its waits: raw messages kept by (kind, frame, sender) as zenoh delivers them,
the worlds and the driver's done, and the waits of ego_loop for the next world (or why none will come)
and, in lockstep, for every live CAV's messages of a frame.
"""

from __future__ import annotations

import json
import signal
import struct
import sys
import threading
import time
from collections import defaultdict

from agents.common import DONE_GRACE_S, DRIVER, DRIVER_GRACE_S, Bus
from v2vsim.recording.scan import scan_frame

HANG_TIMEOUT_S = 60.0  # a live CAV that sends nothing for this long is treated as lost
# Side channels between our own processes, not V2V messages: not channel-modelled, not counted.
SIDE_KINDS = ("vis", "scan", "own")  # "own": the ego's uncompressed map from its own CAV process


class Mailbox:
    """Raw messages by (kind, frame, sender), filled on zenoh's thread, read on the main thread.

    limits: kind -> the longest message that could be accepted; longer ones are not kept, only
    counted (`rejected`), so a flood of oversized messages cannot pile up unread."""

    def __init__(self, limits: dict[str, int] | None = None) -> None:
        self.cond = threading.Condition()
        self.raw: dict[tuple[str, int], list[tuple[str, bytes]]] = defaultdict(list)  # (sender key, bytes)
        self.unframed: list[tuple[str, str, bytes]] = []  # could not even read a frame number
        self.rejected: list[tuple[str, str]] = []  # (kind, reason) decided on arrival
        self.worlds: dict[int, bytes] = {}
        self.done = False
        self.done_at = 0.0  # time.monotonic() of the first done
        self.last_world = 0.0  # time.monotonic() of the latest world
        self.limits = dict(limits or {})

    def put(self, kind: str, sender: str, data: bytes) -> None:
        limit = self.limits.get(kind, 0)
        if limit and len(data) > limit:
            if kind not in SIDE_KINDS:
                with self.cond:
                    self.rejected.append((kind, "size_mismatch"))
            return
        frame = _peek_frame(kind, data)
        with self.cond:
            if frame is None:
                self.unframed.append((kind, sender, data))
            else:
                self.raw[(kind, frame)].append((sender, data))
            self.cond.notify_all()


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
    try:
        frame = int(json.loads(data)["frame"])
    except (ValueError, KeyError, TypeError):
        return
    with box.cond:
        box.worlds[frame] = data
        box.last_world = time.monotonic()
        box.cond.notify_all()


def set_done(box: Mailbox) -> None:
    with box.cond:
        if not box.done:
            box.done, box.done_at = True, time.monotonic()
        box.cond.notify_all()


def notify(box: Mailbox) -> None:
    with box.cond:
        box.cond.notify_all()


def wait_world(box: Mailbox, bus: Bus, k: int, realtime: bool) -> tuple[int, bytes] | str:
    """World k (lockstep), or the newest world from k on (realtime: frames we fell behind on are skipped),
    or why none will come: "done" (the driver finished), "died" (its token dropped without a bye or
    done), "interrupted" (it was stopped by SIGINT: the run's Ctrl-C), or the reason it gave in its bye."""
    gone_at = None
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
            # A verified done is the driver's; without comm.auth anyone could have sent it, so it is
            # believed once the driver is gone too, or when no world came for DONE_GRACE_S since.
            if box.done and (bus.authenticated or gone or now - max(box.done_at, box.last_world) > DONE_GRACE_S):
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
            box.cond.wait(0.2 if gone or box.done else 0.5)


def cav_died(bus: Bus, cav: str) -> bool:
    """Its token dropped without a clean bye (a CAV whose vehicle left says bye with code 0)."""
    if not bus.was_alive(f"cav.{cav}") or bus.is_alive(f"cav.{cav}"):
        return False
    bye = bus.farewell(f"cav.{cav}")
    return bye is None or bye.get("code") != 0


def wait_messages(box: Mailbox, bus: Bus, k: int, present: list[str], kinds: list[str],
                   lost: dict[str, int]) -> None:
    """Lockstep: wait until every live CAV's frame-k messages of `kinds` are in (or it is lost)."""
    deadline = time.monotonic() + HANG_TIMEOUT_S
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
                    print(f"v2vsim-ego: CAV {c} sent nothing for {HANG_TIMEOUT_S:g} s at frame {k}; "
                          "treating it as lost", file=sys.stderr)
                return
            box.cond.wait(0.2)
