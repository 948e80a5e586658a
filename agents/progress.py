"""Progress of a run: one display for the whole run instead of one interleaved line per process.

Under `v2vsim run` (the runner sets V2VSIM_PROGRESS=records) every agent writes its progress as a
machine-readable line, `@progress {json}`, to stderr; the runner reads every child's stderr, feeds
those records to one `ProgressDisplay` and forwards every other line (warnings, errors, tracebacks)
unchanged on its own line. An agent started by hand (`v2vsim agent`) prints a human line instead.
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, TextIO

ENV = "V2VSIM_PROGRESS"  # "records": the runner parses this process's stderr
PREFIX = "@progress "
COUNTS = ("delivered", "dropped", "out_of_range")  # the ego's V2V counters shown on the run's line

_t0: dict[str, float] = {}  # standalone mode: when each reporter's first frame was done


def report_progress(who: str, frame: int, total: int, **counts: int) -> None:
    """`frame` of `total` frames done by `who` (e.g. "ego.cav0", "driver"); `counts`: the ego's V2V
    counters (delivered, dropped, out_of_range of its CommStats)."""
    if os.environ.get(ENV) == "records":
        doc = {"who": who, "frame": int(frame), "total": int(total), **{k: int(v) for k, v in counts.items()}}
        sys.stderr.write(PREFIX + json.dumps(doc, separators=(",", ":")) + "\n")
        sys.stderr.flush()
        return
    now = time.monotonic()
    t0 = _t0.setdefault(who, now)
    if frame < 1 or (frame % 20 and frame != total):
        return
    fps = (frame - 1) / (now - t0) if now > t0 and frame > 1 else 0.0
    extra = "".join(f"  {v} {k.replace('_', ' ')}" for k, v in counts.items())
    print(f"[{who}] frame {frame}/{total}  {fps:.1f} frames/s  ETA {_eta(total - frame, fps)}{extra}",
          file=sys.stderr, flush=True)


def parse_record(line: str) -> dict[str, Any] | None:
    """The record on a `@progress {json}` line, or None for any other line (forwarded as text)."""
    if not line.startswith(PREFIX):
        return None
    try:
        doc = json.loads(line[len(PREFIX):])
        int(doc["frame"]), int(doc["total"])
    except (ValueError, KeyError, TypeError):
        return None
    return doc if isinstance(doc, dict) else None


def _eta(frames_left: int, fps: float) -> str:
    if frames_left <= 0:
        return "0 s"
    if fps <= 0:
        return "--"
    s = round(frames_left / fps)
    return f"{s} s" if s < 120 else f"{s // 60} min {s % 60:02d} s"


class ProgressDisplay:
    """One line for the run: frames done by the slowest ego, frames/s, real-time factor, the egos'
    V2V counters and ETA. On a terminal it is redrawn in place; otherwise a plain line is written
    every `every` frames. Child output passed to `message` appears on its own lines. Thread-safe:
    one reader thread per child feeds it."""

    def __init__(self, total: int, rate_hz: float, egos: Sequence[str], stream: TextIO | None = None, *,
                 tty: bool | None = None, every: int | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total = total
        self.rate_hz = rate_hz
        self.egos = list(egos)
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(tty if tty is not None else getattr(self.stream, "isatty", lambda: False)())
        self.every = every or max(1, min(20, math.ceil(total / 10)))
        self.clock = clock
        self._lock = threading.Lock()
        self._frames: dict[str, int] = {}
        self._counts: dict[str, dict[str, int]] = {}
        self._t0: float | None = None
        self._done0 = 0
        self._live = ""  # the live line on screen (terminal), "" when none
        self._last_plain = 0
        self._last_draw = -math.inf
        self._drawn_done = -1

    def reset(self) -> None:
        """Forget every record (the runner restarted its processes)."""
        with self._lock:
            self._frames.clear()
            self._counts.clear()
            self._t0 = None
            self._last_plain = 0
            self._drawn_done = -1

    @property
    def done(self) -> int:
        """Frames every ego has finished (the run is as far as its slowest ego)."""
        return min((self._frames.get(e, 0) for e in self.egos), default=0)

    @property
    def started(self) -> bool:
        """Whether any ego has finished a frame (the run is under way)."""
        with self._lock:
            return any(v > 0 for v in self._frames.values())

    def record(self, who: str, doc: dict[str, Any]) -> None:
        """A progress record from process `who` ("driver", "ego.cav0", ...)."""
        with self._lock:
            now = self.clock()
            if self._t0 is None:
                self._t0, self._done0 = now, self.done
            if who in self.egos:
                self._frames[who] = max(self._frames.get(who, 0), int(doc["frame"]))
                self._counts[who] = {k: int(doc.get(k, 0)) for k in COUNTS}
            done = self.done
            if self.tty:
                if now - self._last_draw >= 0.1 or (done == self.total and self._drawn_done != done):
                    self._draw(self.text(now))
                    self._last_draw, self._drawn_done = now, done
            elif done > self._last_plain and (done >= self._last_plain + self.every or done == self.total):
                self._last_plain = done - done % self.every if done != self.total else done
                self.stream.write(self.text(now) + "\n")
                self.stream.flush()

    def text(self, now: float | None = None) -> str:
        """The progress line as it stands."""
        now = self.clock() if now is None else now
        done = self.done
        elapsed = now - self._t0 if self._t0 is not None else 0.0
        fps = (done - self._done0) / elapsed if elapsed > 0 else 0.0
        sums = {k: sum(c.get(k, 0) for c in self._counts.values()) for k in COUNTS}
        pct = 100 * done // max(self.total, 1)
        return (f"v2vsim: frame {done}/{self.total} ({pct}%)  {fps:.1f} frames/s  {fps / self.rate_hz:.2f}x real time"
                f"  V2V {sums['delivered']} delivered, {sums['dropped']} dropped, "
                f"{sums['out_of_range']} out of range  ETA {_eta(self.total - done, fps)}")

    def message(self, line: str) -> None:
        """Write a line (a child's warning, the runner's own news) without mangling the live line."""
        with self._lock:
            live = self._live
            if live:
                self._draw("")
            self.stream.write(line.rstrip("\n") + "\n")
            if live:
                self._draw(live)
            self.stream.flush()

    def close(self) -> None:
        """End the live line so that what follows starts on a line of its own."""
        with self._lock:
            if self._live:
                self.stream.write("\n")
                self.stream.flush()
                self._live = ""

    def _draw(self, text: str) -> None:
        self.stream.write("\r\x1b[K" + text)
        self.stream.flush()
        self._live = text
