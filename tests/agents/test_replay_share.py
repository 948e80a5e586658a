"""ReplayShare (agents.ego_replay): several replays of one recording in one process read it once, compute what
they share once, and keep only the frames some live replay still needs."""

from __future__ import annotations

import threading
import time
from collections import Counter
from pathlib import Path

import pytest

from agents.ego_replay import ReplayShare
from agents.lifecycle import Stop
from v2vsim.recording.messages import RecordedFrame


class _Recording:
    """Stands in for v2vsim.recording.messages.Recording: counts how often its frames are read."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.reads = 0
        self.header: dict = {}
        self.folder = Path(".")

    def frames(self):  # noqa: ANN201
        for k in range(self.n):
            self.reads += 1
            yield k, RecordedFrame(f"world {k}".encode(), {}, Counter())


def test_frames_are_read_once_work_is_shared_and_old_frames_are_dropped() -> None:
    rec = _Recording(12)
    share = ReplayShare(rec, consumers=3)  # type: ignore[arg-type]
    calls: Counter = Counter()
    seen: list[list[int]] = [[], [], []]
    kept: list[int] = []

    def replay(i: int) -> None:
        index = 0
        while (got := share.take(i, index)) is not None:
            k, frame = got
            assert frame.world == f"world {k}".encode()

            def work(k: int = k) -> int:
                calls[k] += 1
                time.sleep(0.002)
                return k * k

            assert share.once(k, "square", work) == k * k
            seen[i].append(k)
            kept.append(len(share._read))
            index += 1
        share.leave(i)

    threads = [threading.Thread(target=replay, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert seen == [list(range(12))] * 3
    assert rec.reads == 12 and all(n == 1 for n in calls.values()) and len(calls) == 12
    assert share.lookups == {"square": 36} and share.hits == {"square": 24}
    assert max(kept) <= ReplayShare.AHEAD + 2  # a replay runs at most AHEAD frames past the slowest
    assert not share._memo and not share._read  # everything dropped once every replay has passed it


def test_an_error_reaches_every_replay_that_asks_and_stop_ends_them() -> None:
    share = ReplayShare(_Recording(3), consumers=2)  # type: ignore[arg-type]
    share.take(0, 0)

    def boom() -> int:
        raise ValueError("bad frame")

    for _ in range(2):
        with pytest.raises(ValueError, match="bad frame"):
            share.once(0, "x", boom)
    share.stop()
    with pytest.raises(Stop):
        share.take(1, 0)
