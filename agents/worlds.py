"""The worlds an agent holds before it uses them, bounded whatever arrives.

A world message is for one frame, and an honest driver is never far ahead of the agents: in lockstep it
publishes frame k+1 only once every ego fused frame k - transport.pipeline, and an ego fuses a frame only
once every live CAV sent its messages for it; so a world more than `transport.pipeline + 2` frames past the
last frame an agent took cannot be the driver's (realtime, with no acks, the window is counted from the
newest world held). Such a world, a second different world for a frame held, or one that is not a world is
refused (RejectedMessage: the Bus counts it under its reason); a world for a frame taken already is the
driver sending it again for a late ego, and is dropped without a word. Without comm.auth a single world
for frame 10**6 made a CAV skip every real world after it, and a flood of worlds for future frames was kept
until the run ended (8 MiB each took the ego from 636 to 1,539 MiB).
"""

from __future__ import annotations

import json
import threading

from v2vsim.comm.codec import RejectedMessage
from v2vsim.config import Scenario
from v2vsim.world.serialize import MAX_WORLD_BYTES


def world_frame(data: bytes) -> int:
    """The frame a world message is for (its length checked before it is parsed), or RejectedMessage."""
    if len(data) > MAX_WORLD_BYTES:
        raise RejectedMessage("size_mismatch", f"a world of {len(data)} bytes, at most {MAX_WORLD_BYTES}")
    try:
        frame = json.loads(data)["frame"]
    except (ValueError, KeyError, TypeError):
        raise RejectedMessage("bad_header", "not a world message") from None
    if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0:
        raise RejectedMessage("bad_header", f"world frame {frame!r}")
    return frame


def admit_world(held: dict[int, bytes], frame: int, data: bytes, taken: int, newest: int, ahead: int | None,
                realtime: bool) -> bool:
    """The one rule for holding a world (the CAV's WorldQueue and the ego's mailbox, each under its own lock):
    store `data` for `frame` in `held` and return True, or return False for one taken already (frame <= `taken`)
    or held already with the same bytes, or raise RejectedMessage for a second, different world of a frame held
    or one more than `ahead` frames past `taken` (realtime: past max(taken, newest)); `ahead` None: no window.
    Realtime keeps only the `ahead` newest, the only ones ever taken."""
    if frame <= taken:
        return False  # sent again for an ego that missed it (agents/driver.py): had it
    same = held.get(frame)
    if same is not None:
        if same == data:
            return False
        raise RejectedMessage("duplicate", f"a second, different world for frame {frame}")
    if ahead is not None:
        ref = max(taken, newest) if realtime else taken
        if frame > ref + ahead:
            raise RejectedMessage("out_of_window", f"world for frame {frame}, {ref + ahead} at most")
    held[frame] = data
    if realtime and ahead is not None:
        for old in sorted(held)[:-ahead]:
            del held[old]
    return True


def world_window(sc: Scenario) -> int:
    """How many frames past the last one taken a world may be for (see the module docstring): the same
    window the ego keeps V2V messages in (agents.ego_mailbox.Window.ahead)."""
    return sc.transport.pipeline + 2


class WorldQueue:
    """A CAV's worlds by frame, filled on zenoh's thread (`put`), taken in frame order (lockstep) or newest
    first (realtime: frames it could not keep up with are skipped) by its main loop (`take`). Holds at most
    `ahead` worlds of at most MAX_WORLD_BYTES each."""

    def __init__(self, ahead: int, realtime: bool = False) -> None:
        self.ahead = ahead
        self.realtime = realtime
        self._cond = threading.Condition()
        self._held: dict[int, bytes] = {}
        self._taken = -1  # the latest frame handed out
        self._newest = -1  # the newest frame held or taken (realtime's window starts here)

    def put(self, data: bytes) -> None:
        frame = world_frame(data)
        with self._cond:
            if admit_world(self._held, frame, data, self._taken, self._newest, self.ahead, self.realtime):
                self._newest = max(self._newest, frame)
                self._cond.notify_all()

    def take(self, timeout: float) -> bytes | None:
        """The next world (lockstep: the lowest frame held; realtime: the newest, dropping the older ones), or
        None after `timeout` seconds without one."""
        with self._cond:
            if not self._held:
                self._cond.wait(timeout)
            if not self._held:
                return None
            frame = max(self._held) if self.realtime else min(self._held)
            data = self._held[frame]
            for f in [f for f in self._held if f <= frame]:
                del self._held[f]
            self._taken = frame
            return data

    def __len__(self) -> int:
        with self._cond:
            return len(self._held)
