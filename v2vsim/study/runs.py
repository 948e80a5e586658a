"""Running a sweep's runs: each is `v2vsim run` as a child process, up to `jobs` at a time, resumable,
with one progress line over runs on stderr; Ctrl-C stops the children cleanly.

A run counts as done when its metrics.json says status "complete" and its `sweep_run.json` (what the
sweep asked for: the scenario as loaded with the run's overrides, the frames, and the sha256 of the
weights it loads) matches the current request; anything else is (re)run. A run's own output (its
progress lines, errors) goes to `sweep-run.log` in its directory.

Record once, replay the rest (docs/run.md "In a sweep"): the CAV side of a run (traffic, sensing,
encoding, what goes on the air) depends only on the seed and the sender-side keys, so at each seed the first
point of every group of points that differ only in receiver-side keys (v2vsim.recording.messages.RECEIVER_SIDE) is run
with `output.record_messages=true`, and every other point of the group is `v2vsim evaluate` over that
recording once it is complete: bit for bit the run it stands for, at the cost of the ego alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TextIO

from v2vsim.config import Scenario, load_scenario
from v2vsim.runner import die_with_parent
from v2vsim.study.grid import Axis, Point

STOP_GRACE_S = 20.0  # after SIGINT a run stops its own processes (up to 5 s) and writes partial results
TAIL_LINES = 8
HEARTBEAT_S = 60.0
LOG = "sweep-run.log"
REQUEST = "sweep_run.json"
PLAN = "replay_plan.json"


@dataclass(frozen=True)
class RunSpec:
    point: Point
    seed: int
    out: Path
    grid: tuple[str, ...]  # the point's overrides, KEY=VALUE
    request: dict  # scenario digest, overrides (seed first), frames: what makes two runs the same run
    recording: Path | None = None  # a replayed run: the run folder whose messages/ it replays
    records: bool = False  # a recording run: other points of its seed replay it
    batch: int | None = None  # replays of one recording with the same batch run in one process (evaluate --plan)
    together: tuple[RunSpec, ...] = ()  # as started: the other replays of its batch, in this spec's process

    @property
    def replayed(self) -> bool:
        return self.recording is not None

    @property
    def plan_file(self) -> Path:
        return self.out / PLAN

    def plan_doc(self) -> list[dict]:
        """`v2vsim evaluate --plan` of this spec and those `together` with it."""
        return [{"out": str(s.out), "overrides": list(s.request["overrides"])} for s in (self, *self.together)]

    def argv(self, scenario: Path, out: Path | None = None) -> list[str]:
        """`python` arguments of the run (`out`: write elsewhere than self.out, e.g. on a cluster worker). Replays
        started together read their points from plan_file (ProcessJob writes it)."""
        if self.recording is not None and self.together:
            args = ["-m", "v2vsim.cli", "evaluate", str(self.recording), "--plan", str(self.plan_file)]
            return args + (["--frames", str(self.request["frames"])] if self.request["frames"] is not None else [])
        if self.recording is not None:
            args = ["-m", "v2vsim.cli", "evaluate", str(self.recording), "--out", str(out or self.out)]
        else:
            args = ["-m", "v2vsim.cli", "run", str(scenario), "--out", str(out or self.out)]
        args += [x for o in self.request["overrides"] for x in ("--set", o)]
        if self.request["frames"] is not None:
            args += ["--frames", str(self.request["frames"])]
        return args


@dataclass(frozen=True)
class RunResult:
    spec: RunSpec
    ok: bool
    reused: bool = False
    code: int | None = None
    wall_s: float = 0.0
    why: str = ""  # for a failed run: exit code / status
    tail: tuple[str, ...] = ()  # for a failed run: its last output lines


class Job(Protocol):
    """A started run (a child process, or a fake in tests)."""

    def poll(self) -> int | None: ...
    def interrupt(self) -> None: ...
    def kill(self) -> None: ...


def effective_config(scenario: Path, overrides: Sequence[str]) -> dict:
    """The scenario as a run will load it, as plain JSON data: two requests are the same run when these
    match, however the overrides were spelled or ordered."""
    sc = load_scenario(scenario, overrides)
    doc = {k: v for k, v in dataclasses.asdict(sc).items() if k not in ("source", "overrides")}
    return json.loads(json.dumps(doc, default=str))


_MISSING = object()


def _default_at(path: Sequence[str]) -> object:
    """The schema default of a scenario key path as effective_config writes it; _MISSING if there is none."""
    cls: object = Scenario
    for name in path:
        if not dataclasses.is_dataclass(cls):
            return _MISSING
        f = next((f for f in dataclasses.fields(cls) if f.name == name), None)
        if f is None:
            return _MISSING
        if f.default is not dataclasses.MISSING:
            value = f.default
        elif f.default_factory is not dataclasses.MISSING:
            value = f.default_factory()
        else:
            return _MISSING
        cls = value
    value = dataclasses.asdict(cls) if dataclasses.is_dataclass(cls) else cls  # type: ignore[arg-type]
    return json.loads(json.dumps(value, default=str))


def same_config(old: object, new: object, path: tuple[str, ...] = ()) -> bool:
    """Whether a run recorded with config `old` is the run `new` asks for. A key `old` lacks counts as equal
    when `new` has its schema default there: keys are added with defaults that keep earlier results, so a
    scenario key added since (comm.share, say) does not make every finished run of a sweep run again."""
    if isinstance(old, dict) and isinstance(new, dict):
        if set(old) - set(new):
            return False
        return all(same_config(old[k], v, (*path, k)) if k in old else v == _default_at((*path, k))
                   for k, v in new.items())
    return old == new


def weights_fingerprint(scenario: Path, overrides: Sequence[str]) -> str | None:
    """What identifies the weights a run loads: the zoo manifest's sha256 (it holds every checkpoint's) under
    `weights: auto`, the checkpoint's own for a path, None for untrained; so that a retrained zoo reruns."""
    from models.zoo import MANIFEST, WEIGHTS_DIR, sha256

    sc = load_scenario(scenario, overrides)
    w = sc.perception.weights
    if w == "none":
        return None
    path = WEIGHTS_DIR / MANIFEST if w == "auto" else Path(w)
    return sha256(path) if path.is_file() else None


RECORD = "output.record_messages=true"


def replay_groups(axes: Sequence[Axis], pts: Sequence[Point], lockstep: Sequence[bool]) -> list[int]:
    """For each point, the index of the point whose recording it can replay (itself when it must be run):
    the first point with the same values on every axis that is not receiver-side. The methods, the output keys
    and duration_s count as sender-side here: a recording holds the kinds its own methods took, its scans only
    with output.rerun on, and the frames its own duration gave. A point on the realtime clock is its own group
    (nothing to record: what its ego holds depends on the wall clock)."""
    from v2vsim.recording.messages import receiver_side

    def sender_side(key: str) -> bool:
        return not receiver_side(key) or key.startswith(("perception.methods", "output", "duration_s"))

    first: dict[tuple[str, ...], int] = {}
    out = []
    for i, p in enumerate(pts):
        key = tuple(t for a, t in zip(axes, p.texts, strict=True) if sender_side(a.key))
        out.append(first.setdefault(key, i) if lockstep[i] else i)
    return out


def replay_refusal(sc: Scenario) -> str | None:
    """Why none of the sweep's runs can be recorded and replayed (`sc`: the scenario with the sweep's own
    overrides), or None when they can."""
    if sc.transport.clock != "lockstep":
        return "transport.clock is realtime: its runs depend on the wall clock, and a recording needs lockstep"
    return None


def plan(scenario: Path, axes: Sequence[Axis], pts: Sequence[Point], seeds: Sequence[int], base: Sequence[str],
         frames: int | None, out: Path, replay: bool = False, jobs: int = 1) -> list[RunSpec]:
    """Every (point, seed) run, point-major: the same seeds at every point (a paired design). With `replay`,
    a point that differs from an earlier one only in receiver-side keys replays that point's recording of the
    same seed (replay_groups): the earlier point's runs record. The replays of one recording run in one process
    (they share decoding, ground truth and equal fusions: agents.evaluate.evaluate_points), split into as many
    batches of neighbouring points as keep the 2 x `jobs` replay slots busy (batches_per_recording)."""
    configs = [effective_config(scenario, [*p.overrides(axes), *base]) for p in pts]
    groups = (replay_groups(axes, pts, [c["transport"]["clock"] == "lockstep" for c in configs]) if replay
              else list(range(len(pts))))
    recorders = {g for i, g in enumerate(groups) if g != i}

    def run_dir(p: Point, seed: int) -> Path:
        return out / "runs" / p.pid / f"seed{seed}"

    specs: list[RunSpec] = []
    for i, p in enumerate(pts):
        records = i in recorders
        extra = [RECORD] if records else []
        config = effective_config(scenario, [*p.overrides(axes), *base, *extra]) if records else configs[i]
        weights = weights_fingerprint(scenario, [*p.overrides(axes), *base])
        for s in seeds:
            request = {"scenario": str(scenario), "overrides": [f"seed={s}", *p.overrides(axes), *base, *extra],
                       "frames": frames, "config": config | {"seed": s}, "weights": weights}
            recording = run_dir(pts[groups[i]], s) if groups[i] != i else None
            if recording is not None:
                request["replay_of"] = str(recording)
            specs.append(RunSpec(p, s, run_dir(p, s), tuple(p.overrides(axes)), request, recording, records))
    return _batched(specs, jobs)


def batches_per_recording(recordings: int, replays: int, jobs: int) -> int:
    """Into how many processes the `replays` replays of one recording are split, with `recordings` recordings
    replayed in all: enough for the sweep's 2 x jobs replay slots, no more (each split shares less)."""
    return max(1, min(replays, -(-2 * jobs // max(1, recordings))))


def _batched(specs: list[RunSpec], jobs: int) -> list[RunSpec]:
    """Number each replay's batch: its recording's replays, in grid order, cut into contiguous runs of points
    (neighbouring points share the most fusion inputs) at the grid's coarsest boundaries (cut_points)."""
    by_recording: dict[Path, list[int]] = {}
    for i, s in enumerate(specs):
        if s.recording is not None:
            by_recording.setdefault(s.recording, []).append(i)
    out = list(specs)
    batch = 0
    for idx in by_recording.values():
        n = batches_per_recording(len(by_recording), len(idx), jobs)
        cuts = cut_points([specs[i].point.texts for i in idx], n)
        for j, i in enumerate(idx):
            out[i] = dataclasses.replace(specs[i], batch=batch + sum(j >= c for c in cuts))
        batch += n
    return out


def cut_points(texts: Sequence[tuple[str, ...]], n: int) -> list[int]:
    """Where to cut a list of grid points (their values, in grid order) into n contiguous batches of about equal
    size: near each equal-size cut, the position where the earliest axis changes value (between two latencies
    rather than two loss levels of one latency: points of one latency share fusions, across latencies hardly)."""
    def strength(p: int) -> int:  # the earliest axis whose value changes between points p-1 and p
        return next((a for a, (x, y) in enumerate(zip(texts[p - 1], texts[p], strict=True)) if x != y), len(texts[0]))

    cuts: list[int] = []
    size = len(texts) / n
    for i in range(1, n):
        target = round(i * size)
        lo = max(cuts[-1] + 1 if cuts else 1, round(target - size / 2))
        hi = min(len(texts) - (n - i), round(target + size / 2))
        cuts.append(min(range(lo, hi + 1), key=lambda p: (strength(p), abs(p - target))) if lo <= hi else target)
    return cuts


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
    if doc is None or doc.get("status") != "complete":
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

    def __init__(self, spec: RunSpec, scenario: Path) -> None:
        spec.out.mkdir(parents=True, exist_ok=True)
        if spec.together:
            spec.plan_file.write_text(json.dumps(spec.plan_doc(), indent=2))
            for other in spec.together:
                other.out.mkdir(parents=True, exist_ok=True)
                (other.out / LOG).write_text(f"replayed in one process with {spec.out.parent.name}; its output: "
                                             f"{spec.out / LOG}\n")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        with open(spec.out / LOG, "wb") as log:
            self.proc = subprocess.Popen([sys.executable, *spec.argv(scenario)], stdin=subprocess.DEVNULL,
                                         stdout=log, stderr=subprocess.STDOUT, env=env, process_group=0,
                                         preexec_fn=die_with_parent(os.getpid()))  # a killed sweep leaves no runs

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


def start_process(scenario: Path) -> Callable[[RunSpec], Job]:
    return lambda spec: ProcessJob(spec, scenario)


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
    if status == "complete" and (code == 0 or log is not None):  # together: another point's failure is not its
        return RunResult(spec, True, code=code, wall_s=wall_s)
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
