"""Which runs a sweep makes: every (point, seed) of the grid, the request that makes two runs the same run (the
scenario as loaded with the run's overrides, the frames, and the sha256 of the weights it loads), and which runs
record and which replay (v2vsim.study.runs starts them).

Record once, replay the rest (docs/run.md "In a sweep"): the CAV side of a run (traffic, sensing,
encoding, what goes on the air) depends only on the seed and the sender-side keys, so at each seed the first
point of every group of points that differ only in receiver-side keys (v2vsim.recording.messages.RECEIVER_SIDE) is
run with `output.record_messages=true`, and every other point of the group is `v2vsim evaluate` over that
recording once it is complete: bit for bit the run it stands for, at the cost of the ego alone.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from v2vsim.config import Scenario, load_scenario
from v2vsim.study.grid import Axis, Point

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


def effective_config(scenario: Path, overrides: Sequence[str]) -> dict:
    """The scenario as a run will load it, as plain JSON data: two requests are the same run when these
    match, however the overrides were spelled or ordered."""
    sc = load_scenario(scenario, overrides)
    doc = {k: v for k, v in dataclasses.asdict(sc).items() if k not in ("source", "overrides")}
    if doc.get("control") is None:  # open loop: the same request as before closed loops existed
        doc.pop("control", None)
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
    (nothing to record: what its ego holds depends on the wall clock); so is a closed-loop point (`lockstep` False
    for it too)."""
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
    # a closed-loop point runs live: what its CAVs sensed depends on how its ego drove, which every key can change
    groups = (replay_groups(axes, pts, [c["transport"]["clock"] == "lockstep" and c.get("control") is None
                                        for c in configs]) if replay
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
