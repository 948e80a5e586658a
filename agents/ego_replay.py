"""The bus of a replay (`v2vsim evaluate`): a recording (v2vsim.recording.messages) played into the ego's
mailbox, one frame per ack, so that agents.ego.ego_loop runs unchanged with no driver, CAVs or zenoh.

Frame k's world and every message collect() took for frame k when recorded go into the mailbox when the ego
acks frame k-1 (frame 0: when it says ready), straight into its per-frame tables: they passed the arrival
checks (signature, run, sender, window) when they were recorded, and the decode that follows skips the
signature as it did then. Rejections decided on arrival are put back as counted. A CAV lost in the recorded
run is lost again from the same frame; the run ends as the recorded one did (its frames, then done).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from agents.ego_mailbox import Mailbox
from v2vsim.recording.messages import RecordedFrame, Recording


class ReplayBus:
    authenticated = True  # a done is the recording's: believed at once

    def __init__(self, recording: Recording, frames: int) -> None:
        self.recording = recording
        self.frames = frames
        self._it: Iterator[tuple[int, RecordedFrame]] = recording.frames()
        self._subs: dict[str, Callable[[str, bytes], None]] = {}
        self._box: Mailbox | None = None
        self._lost = {str(c): int(f) for c, f in recording.header.get("lost_agents", {}).items()}
        self._current = -1

    def attach(self, box: Mailbox) -> None:
        self._box = box

    # the Bus methods ego_loop uses
    def fetch(self, kind: str, sender: str, timeout_s: float) -> bytes:
        assert kind == "static"
        return self.recording.static

    def subscribe(self, kind: str, callback: Callable[[str, bytes], None]) -> None:
        self._subs[kind] = callback

    def on_lost(self, callback: Callable[[str], None]) -> None:
        pass

    def ready(self) -> None:
        self._feed()

    def put(self, kind: str, data: bytes) -> int:
        if kind == "ack":
            self._feed()
        return len(data)

    def driver_gone(self) -> bool:
        return False

    def farewell(self, who: str) -> dict[str, Any] | None:
        return None

    def was_alive(self, who: str) -> bool:
        return True

    def is_alive(self, who: str) -> bool:
        cav = who.split(".", 1)[1] if who.startswith("cav.") else who
        return not (cav in self._lost and self._current >= self._lost[cav])

    def control_rejections(self) -> dict[tuple[str, str], int]:
        return {(k, r): int(n) for k, r, n in self.recording.header.get("control_rejections", [])}

    def _feed(self) -> None:
        box = self._box
        assert box is not None, "ReplayBus.attach(mailbox) before the ego starts"
        got = next(self._it, None)
        if got is None or got[0] >= self.frames:
            self._subs["done"]("main", b"")
            return
        k, frame = got
        self._current = k
        with box.cond:
            for kind, table in frame.raw.items():
                if kind not in self._subs:  # a kind this ego does not take (fewer methods): never sent to it
                    continue
                box.raw[(kind, k)].extend(table)
            box.rejected.update(frame.rejected)
        self._subs["world"]("main", frame.world)
