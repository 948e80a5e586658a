"""Where a process's frame time goes: wall milliseconds per named stage, averaged over frames; and where its
start-up went (`Startup`: the instants from its launch to its first frame, `v2vsim bench startup`).

Each agent keeps one `StageTimer`; the ego puts its split in metrics.json ("timing"), the driver
and CAVs write theirs to <out>/timing/<process>.json, and `v2vsim bench run` prints them side by
side. Stages named "wait*" are time spent waiting for others, not the process's own compute.
"""

from __future__ import annotations

import json
import os
import resource
import threading
import time
from collections import defaultdict
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

LAUNCHED_ENV = "V2VSIM_LAUNCHED_AT"  # time.time() when the runner started the process (v2vsim.runner)


@dataclass
class Startup:
    """A process's start-up: wall-clock instants (time.time(), comparable across the run's processes) of each
    stage reached, from `launched` (the runner's clock when it started the process) to `first_frame`. The stages
    a process marks, in order: imports (its main() began: interpreter and imports done), zenoh (its session and
    bus up), then its own (the driver: sumo, agents_alive; a CAV: models, map; an ego: models), then
    first_frame."""

    launched: float | None = field(default_factory=lambda: _env_float(LAUNCHED_ENV))
    marks: dict[str, float] = field(default_factory=dict)

    def mark(self, stage: str) -> None:
        """The first time `stage` is reached (a later call for it changes nothing)."""
        self.marks.setdefault(stage, time.time())

    def to_json(self) -> dict:
        return {"launched": self.launched, "marks": dict(self.marks)}


def _env_float(name: str) -> float | None:
    try:
        return float(os.environ[name])
    except (KeyError, ValueError):
        return None


class StageTimer:
    """Summed wall time per stage; `split()` is ms per frame over the frames counted so far. Also the process's
    CPU time (every thread, user + system) from its first timed stage on: on a loaded machine a stage's wall time
    includes the time the process waited for a core, its CPU time does not.

    Thread-safe: the ego's scoring thread times its stages on the same timer the main thread reads for
    `method_ms` while fusing (a stage first timed mid-read once grew the dict under the reader)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.total_ms: dict[str, float] = defaultdict(float)
        self.frames = 0
        self._cpu0: float | None = None  # process CPU seconds when the first stage began (start-up excluded)

    def _start_cpu(self) -> None:
        if self._cpu0 is None:
            self._cpu0 = cpu_s()

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self._start_cpu()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, (time.perf_counter() - t0) * 1000)

    def add(self, name: str, ms: float) -> None:
        self._start_cpu()
        with self._lock:
            self.total_ms[name] += ms

    def _totals(self) -> dict[str, float]:
        with self._lock:
            return dict(self.total_ms)

    def frame_done(self) -> None:
        self.frames += 1

    def split(self) -> dict[str, float]:
        n = max(self.frames, 1)
        return {k: round(v / n, 3) for k, v in self._totals().items()}

    def compute_ms(self) -> float:
        """ms per frame of the process's own work (every stage but the waits)."""
        return round(sum(v for k, v in self.split().items() if not k.startswith("wait")), 3)

    def method_ms(self) -> dict[str, float]:
        """Each fusion method's fusion + decoding ms summed so far (the ego's stages "fusion.M", "decoding.M"):
        which methods take longest."""
        out: dict[str, float] = defaultdict(float)
        for k, v in self._totals().items():
            stage, _, method = k.partition(".")
            if method and stage in ("fusion", "decoding"):
                out[method] += v
        return dict(out)

    def cpu_ms(self) -> float | None:
        """CPU milliseconds per frame (all threads) since the first stage; None before any."""
        if self._cpu0 is None:
            return None
        return round((cpu_s() - self._cpu0) * 1000 / max(self.frames, 1), 3)

    def to_json(self) -> dict:
        return {"frames": self.frames, "ms_per_frame": self.split(), "compute_ms_per_frame": self.compute_ms(),
                "cpu_ms_per_frame": self.cpu_ms(), "peak_rss_mib": peak_rss_mib()}


def cpu_s() -> float:
    """This process's CPU seconds so far, every thread, user + system."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def peak_rss_mib() -> float:
    """This process's peak resident memory so far (MiB): what a flood of messages would raise."""
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)  # Linux reports KiB


def write_timing(out: str, process: str, timer: StageTimer,
                 control_rejections: Mapping[tuple[str, str], int] | None = None,
                 startup: Startup | None = None) -> None:
    """<out>/timing/<process>.json (nothing when the process has no output directory, e.g. a remote CAV); with
    the control messages this process refused ({kind: {reason: n}}, its Bus.control_rejections): the ego's are
    in metrics.json, the driver's and the CAVs' (a forged ack, a world from the future) only here."""
    if not out:
        return
    doc = timer.to_json()
    if startup is not None:
        doc["startup"] = startup.to_json()
    if control_rejections is not None:
        by_kind: dict[str, dict[str, int]] = {}
        for (kind, reason), n in sorted(control_rejections.items()):
            by_kind.setdefault(kind, {})[reason] = n
        doc["control_rejections"] = by_kind
    d = Path(out) / "timing"
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{process}.json").write_text(json.dumps(doc, indent=1))
