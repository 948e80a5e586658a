"""Running a sweep's runs (v2vsim.study.plan makes them): each is `v2vsim run` (or `v2vsim evaluate` of a replayed
point) as a child process, up to `jobs` at a time, resumable, with one progress line over runs on stderr; Ctrl-C
stops the children cleanly.

A run counts as done when its metrics.json says status "complete" and its `sweep_run.json` (what the
sweep asked for: the run's request, v2vsim.study.plan) matches the current request; anything else is (re)run,
a degraded run too (agents lost: v2vsim.evaluation.status), so that a resumed sweep gives it another chance. A
degraded run that has just finished is not a failure: its rows are kept with their status (v2vsim.study.rows).
A run's own output (its progress lines, errors) goes to `sweep-run.log` in its directory.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TextIO

from v2vsim.evaluation.status import COMPLETE, as_configured, finished
from v2vsim.launch import Launcher
from v2vsim.study.plan import RunSpec, same_config

STOP_GRACE_S = 20.0  # after SIGINT a run stops its own processes (up to 5 s) and writes partial results
TAIL_LINES = 8
HEARTBEAT_S = 60.0
LOG = "sweep-run.log"
REQUEST = "sweep_run.json"


@dataclass(frozen=True)
class RunResult:
    spec: RunSpec
    ok: bool
    reused: bool = False
    code: int | None = None
    wall_s: float = 0.0
    why: str = ""  # for a failed run: exit code / status
    tail: tuple[str, ...] = ()  # for a failed run: its last output lines
    status: str = COMPLETE  # metrics.json's, for a run that went through every frame: complete or degraded: ...


class Job(Protocol):
    """A started run (a child process, or a fake in tests)."""

    def poll(self) -> int | None: ...
    def interrupt(self) -> None: ...
    def kill(self) -> None: ...


def read_metrics(run_dir: Path) -> dict | None:
    try:
        doc = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def recording_complete(run_dir: Path) -> bool:
    """Whether run_dir holds a recording this v2vsim reads, of every frame of its run."""
    from v2vsim.recording.messages import Recording

    try:
        return Recording(run_dir / "messages").complete
    except (OSError, ValueError):
        return False


def is_done(spec: RunSpec) -> bool:
    """Complete metrics.json from the same request (a run from before the sweep wrote requests counts); a
    recording run also needs its complete recording."""
    doc = read_metrics(spec.out)
    if doc is None or not as_configured(doc.get("status")):
        return False
    if spec.records and not recording_complete(spec.out):
        return False
    try:
        asked = json.loads((spec.out / REQUEST).read_text())
    except FileNotFoundError:
        return True
    except (OSError, ValueError):
        return False
    if not isinstance(asked, dict) or asked.get("frames") != spec.request["frames"]:  # not the overrides' spelling
        return False
    if not same_config(asked.get("config"), spec.request["config"]):
        return False
    # other weights (a retrained zoo) are another run; requests written before weights were recorded count
    return "weights" not in asked or asked["weights"] == spec.request.get("weights")


class ProcessJob:
    """`v2vsim run` in its own process group (a terminal's Ctrl-C reaches the sweep only, which passes it
    on), output to the run's log file; on Linux it gets SIGTERM if the sweep dies."""

    def __init__(self, spec: RunSpec, scenario: Path, launch: Launcher) -> None:
        spec.out.mkdir(parents=True, exist_ok=True)
        if spec.together:
            spec.plan_file.write_text(json.dumps(spec.plan_doc(), indent=2))
            for other in spec.together:
                other.out.mkdir(parents=True, exist_ok=True)
                (other.out / LOG).write_text(f"replayed in one process with {spec.out.parent.name}; its output: "
                                             f"{spec.out / LOG}\n")
        env = launch.child_env(dict(os.environ, PYTHONUNBUFFERED="1"))  # the run's agents: the sweep's zygote
        argv = spec.argv(scenario)
        assert argv[0] == "-m", argv
        with open(spec.out / LOG, "wb") as log:  # a killed sweep leaves no runs (v2vsim.launch)
            self.proc = launch.start(argv[1], argv[2:], env, stdout=log)

    def poll(self) -> int | None:
        return self.proc.poll()

    def _signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, sig)

    def interrupt(self) -> None:
        self._signal(signal.SIGINT)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)
        self.proc.wait()


def start_process(scenario: Path, launch: Launcher) -> Callable[[RunSpec], Job]:
    """Each run a process of its own, started through `launch` (warm: forked by the sweep's zygote)."""
    return lambda spec: ProcessJob(spec, scenario, launch)


def _tail(path: Path, n: int = TAIL_LINES) -> tuple[str, ...]:
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return ()
    return tuple(ln for ln in lines if ln.strip())[-n:]


def _finish(spec: RunSpec, code: int, wall_s: float, log: Path | None = None) -> RunResult:
    """The result of a finished run; `log`: where its output went (replays started together: the first's)."""
    doc = read_metrics(spec.out)
    status = None if doc is None else doc.get("status")
    if finished(status) and (code == 0 or log is not None):  # together: another point's failure is not its
        return RunResult(spec, True, code=code, wall_s=wall_s, status=str(status))
    why = f"exit code {code}" + (f", status {status!r}" if status else ", no metrics.json")
    return RunResult(spec, False, code=code, wall_s=wall_s, why=why, tail=_tail(log or spec.out / LOG))


def _duration(s: float) -> str:
    s = int(round(s))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


@dataclass
class Progress:
    """One line over runs: done / total, reused, failed, running, elapsed, ETA (from this session's runs)."""

    total: int
    jobs: int
    stream: TextIO
    t0: float = 0.0
    done: int = 0
    reused: int = 0
    failed: int = 0
    degraded: int = 0
    walls: tuple[float, ...] = ()

    def line(self, running: int, now: float) -> str:
        left = self.total - self.done
        eta = "-"
        if self.walls and left:
            mean = sum(self.walls) / len(self.walls)
            eta = _duration(mean * left / max(1, min(self.jobs, left)))
        elif not left:
            eta = "0 s"
        extra = [f"{self.reused} reused"] if self.reused else []
        extra += [f"{self.failed} failed"] if self.failed else []
        extra += [f"{self.degraded} degraded"] if self.degraded else []
        return (f"v2vsim sweep: {self.done}/{self.total} runs" + (f" ({', '.join(extra)})" if extra else "")
                + f", {running} running, elapsed {_duration(now - self.t0)}, ETA {eta}")

    def show(self, running: int) -> None:
        self.stream.write(self.line(running, time.monotonic()) + "\n")
        self.stream.flush()

    def say(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()


def slots(spec: RunSpec) -> int:
    """Core slots a run takes: a simulated run keeps about two cores busy (driver, CAVs, ego), a replay (or a
    batch of replays together) is one process."""
    return 1 if spec.replayed else 2


def execute(specs: Sequence[RunSpec], jobs: int, start: Callable[[RunSpec], Job], progress: Progress,
            poll_s: float = 0.2) -> tuple[list[RunResult], bool]:
    """Run what is not done yet, up to `jobs` simulated runs at a time, or two replays for each (slots);
    returns (results, interrupted). A failed run is reported and the others go on. On KeyboardInterrupt the
    running children get SIGINT (they write partial results), then SIGKILL after STOP_GRACE_S; finished runs
    are kept."""
    results: list[RunResult] = []
    pending: list[RunSpec] = []
    for s in specs:
        if is_done(s):
            results.append(RunResult(s, True, reused=True))
        else:
            pending.append(s)
    progress.t0 = time.monotonic()
    progress.reused = progress.done = len(results)
    running: list[tuple[RunSpec, Job, float]] = []  # a replay batch: its first spec, with .together
    outcome = {r.spec.out: r for r in results}

    def next_ready(free: int) -> RunSpec | None:
        """The first pending run that can start, if it fits in `free` core slots: a replay once its recording
        run has finished well; one whose recording run failed fails at once, saying so."""
        for i, spec in enumerate(pending):
            if spec.recording is not None:
                source = outcome.get(spec.recording)
                if source is None:
                    continue
                if not (source.ok and recording_complete(spec.recording)):
                    fail_replay(pending.pop(i))
                    return next_ready(free)
            if slots(spec) > free:
                return None
            lead = pending.pop(i)
            if lead.batch is None:
                return lead
            rest = tuple(s for s in pending if s.recording == lead.recording and s.batch == lead.batch)
            pending[:] = [s for s in pending if s not in rest]
            return dataclasses.replace(lead, together=rest) if rest else lead
        return None

    def fail_replay(spec: RunSpec) -> None:
        why = f"not replayed: the run it replays ({spec.recording}) failed or left no complete recording"
        r = RunResult(spec, False, why=why)
        results.append(r)
        outcome[spec.out] = r
        progress.done += 1
        progress.failed += 1
        progress.say(f"v2vsim sweep: run {describe(spec)} failed ({why})")

    def fill() -> None:
        while (spec := next_ready(2 * jobs - sum(slots(x) for x, _, _ in running))) is not None:
            for s in (spec, *spec.together):
                s.out.mkdir(parents=True, exist_ok=True)
                (s.out / "metrics.json").unlink(missing_ok=True)  # stale, or another request's
                (s.out / REQUEST).write_text(json.dumps(s.request, indent=2))
            running.append((spec, start(spec), time.monotonic()))

    try:
        fill()
        progress.show(len(running))
        shown = time.monotonic()
        while running:
            time.sleep(poll_s)
            finished = [(item, code) for item in running if (code := item[1].poll()) is not None]
            if not finished:
                if time.monotonic() - shown > HEARTBEAT_S:  # runs take minutes: say the sweep is alive
                    progress.show(len(running))
                    shown = time.monotonic()
                continue
            running[:] = [item for item in running if item not in [f for f, _ in finished]]
            for (lead, _, t0), code in finished:
                group = (dataclasses.replace(lead, together=()), *lead.together)
                wall = (time.monotonic() - t0) / len(group)  # per run: what the ETA counts
                for spec in group:
                    r = _finish(spec, code, wall, lead.out / LOG if lead.together else None)
                    results.append(r)
                    outcome[spec.out] = r
                    progress.done += 1
                    progress.walls += (r.wall_s,)
                    if r.ok and r.status != COMPLETE:
                        progress.degraded += 1
                        progress.say(f"v2vsim sweep: run {describe(spec)} {r.status}; its rows are kept in "
                                     "sweep.csv with that status (docs/run.md \"How a run ends\")")
                    if not r.ok:
                        progress.failed += 1
                        progress.say(f"v2vsim sweep: run {describe(spec)} failed ({r.why}); last lines of "
                                     f"{lead.out / LOG}:" + "".join(f"\n    {ln}" for ln in r.tail))
            fill()
            progress.show(len(running))
            shown = time.monotonic()
    except KeyboardInterrupt:
        progress.say(f"v2vsim sweep: interrupted; stopping {len(running)} running run(s) (finished runs are kept)")
        _stop(running)
        return results, True
    return results, False


def describe(spec: RunSpec) -> str:
    return f"[{', '.join(spec.grid) or 'no grid'}] seed {spec.seed}"


def _stop(running: Sequence[tuple[RunSpec, Job, float]]) -> None:
    for _, job, _ in running:
        job.interrupt()
    deadline = time.monotonic() + STOP_GRACE_S
    for _, job, _ in running:
        while job.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        if job.poll() is None:
            job.kill()
