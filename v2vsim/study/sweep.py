"""`v2vsim sweep`: run a scenario over a grid of overrides x seeds, then tabulate and plot the methods'
metrics with 95% bootstrap intervals (DESIGN.md "Studies, channel and environment").

    DIR/runs/<point>/seed<k>/   each run's own output (metrics.json, report.md, sweep-run.log, ...); a
                                run other points replay keeps its recording there (messages/)
    DIR/sweep.csv               one row per (grid point, seed, method): swept keys, seed, method, metrics,
                                then the run's status (complete, or degraded: ...)
    DIR/sweep.json              grid, seeds, frames, rows, statistics, failed and degraded runs
    DIR/sweep.md                per swept key: mean [95% CI] per method and point, paired differences
    DIR/sweep_<key>_<metric>.png
    DIR/sweep_driving_<key>.png a closed-loop sweep's collisions, near misses and min TTC per control.method;
                                sweep.json and sweep.md then also compare each method with `none` by seed

A degraded run (it went through every frame, but lost agents or scored nothing for a method:
v2vsim.evaluation.status) is no failure: its rows are in sweep.csv and sweep.json with its status, but the
intervals, tables and plots leave it out unless --include-degraded, since its scores are not the configured
run's. Exit 0 with degraded runs, as `v2vsim run` does; 1 when a run failed.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from v2vsim.config import ConfigError, check_output_dir, find_scenario, load_scenario
from v2vsim.evaluation.status import COMPLETE, as_configured
from v2vsim.launch import Launcher, launcher
from v2vsim.study.grid import Axis, Point, base_overrides, parse_axes, parse_seeds, points, validate
from v2vsim.study.plan import RunSpec, plan, replay_refusal
from v2vsim.study.rows import collect, counted, methods_of
from v2vsim.study.runs import LOG, Job, Progress, RunResult, execute, start_process
from v2vsim.study.stats import DEFAULT_B, DEFAULT_RNG_SEED, LEVEL

EXIT_FAILED, EXIT_INTERRUPTED = 1, 130


@dataclass(frozen=True)
class SweepArgs:
    scenario: Path
    grid: tuple[str, ...]
    seeds: str
    out: Path
    frames: int | None = None
    jobs: int | None = None  # default: 1 locally, the cluster's worker threads under dask
    overrides: tuple[str, ...] = ()
    methods: str | None = None
    bootstrap: int = DEFAULT_B
    engine: str = "local"  # local | dask (v2vsim/study/cluster.py)
    scheduler: str | None = None  # dask: the scheduler's address, e.g. tcp://10.0.0.1:8786
    replay: bool = True  # record once per seed, replay the points that differ only in receiver-side keys
    include_degraded: bool = False  # count degraded runs in the intervals, tables and plots


@dataclass(frozen=True)
class Design:
    """What a sweep will run, validated."""

    scenario: Path
    name: str
    axes: list[Axis]
    points: list[Point]
    seeds: list[int]
    base: list[str]
    specs: list[RunSpec]
    no_replay: str | None  # why nothing is replayed (None: replays where the grid allows)


def prepare(args: SweepArgs) -> Design:
    """Parse and validate everything (ConfigError names the bad option, key or value); nothing runs."""
    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames {args.frames}: expected a number of frames >= 1")
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs {args.jobs}: expected >= 1")
    if args.engine not in ("local", "dask"):
        raise ConfigError(f"--engine {args.engine}: allowed: local, dask")
    if (args.engine == "dask") != (args.scheduler is not None):
        raise ConfigError("--engine dask needs --scheduler ADDRESS (and --scheduler goes with --engine dask)")
    if args.bootstrap < 100:
        raise ConfigError(f"--bootstrap {args.bootstrap}: expected >= 100 resamples")
    scenario = find_scenario(args.scenario).resolve()  # a shipped name too; runs get the file's absolute path
    sc = load_scenario(args.scenario, list(args.overrides))
    axes = parse_axes(args.grid)
    seeds = parse_seeds(args.seeds)
    base = base_overrides(axes, args.overrides, args.methods)
    pts = points(axes)
    validate(Path(args.scenario), axes, pts, base, seeds)
    check_output_dir(args.out, "--out")
    no_replay = ("--no-replay" if not args.replay else
                 "--engine dask (a recording stays on the worker that made it)" if args.engine == "dask" else
                 replay_refusal(sc))
    specs = plan(scenario, axes, pts, seeds, base, args.frames, args.out, replay=no_replay is None,
                 jobs=args.jobs or 1)
    return Design(scenario, sc.name, axes, pts, seeds, base, specs, no_replay)


def replay_line(d: Design) -> str:
    """What the sweep simulates and what it replays, in words."""
    replayed = [s for s in d.specs if s.replayed]
    if not replayed:
        why = d.no_replay or "every grid point differs from the others in a sender-side key"
        return f"v2vsim sweep: every run is simulated ({why})"
    recorders = sorted({s.point.pid for s in d.specs if s.records})
    points = sorted({s.point.pid for s in replayed})
    batches = len({(s.recording, s.batch) for s in replayed})
    return (f"v2vsim sweep: {len(d.specs) - len(replayed)} runs simulated, {len(replayed)} replayed "
            f"({batches} v2vsim evaluate process(es)) from the recordings of point(s) {', '.join(recorders)} at the "
            f"same seed; replayed point(s): {', '.join(points)}")


def sweep(args: SweepArgs, start: Callable[[RunSpec], Job] | None = None, stream: TextIO | None = None,
          launch: Launcher | None = None) -> int:
    """Run the sweep and write its files; the exit code (0, 1 if a run failed, 130 when interrupted). Its runs
    start through `launch` (default: a launcher of its own, v2vsim.launch: warm, every run and agent forked from
    one zygote)."""
    d = prepare(args)
    stream = stream or sys.stderr
    client = None
    own = None
    jobs = args.jobs or 1
    if start is None and args.engine == "dask":
        from v2vsim.study.cluster import DaskJob, connect, worker_threads

        client = connect(args.scheduler or "")
        jobs = args.jobs or worker_threads(client)
        start = lambda spec: DaskJob(client, spec, d.scenario)  # noqa: E731
    where = f" on the Dask cluster at {args.scheduler}" if client is not None else ""
    print(f"v2vsim sweep: {len(d.points)} point(s) x {len(d.seeds)} seed(s) = {len(d.specs)} runs, "
          f"{jobs} at a time{where}" + (f" (or {2 * jobs} replays)" if any(s.replayed for s in d.specs) else "")
          + f" -> {args.out}", file=stream)
    print(replay_line(d), file=stream)
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # `kill` stops it like Ctrl-C
    try:
        if start is None:
            if launch is None:
                launch = own = launcher()
            start = start_process(d.scenario, launch)
        results, interrupted = execute(d.specs, jobs, start, Progress(len(d.specs), jobs, stream))
        paths = write_outputs(args, d, results, interrupted)
    finally:
        signal.signal(signal.SIGTERM, previous)
        if client is not None:
            client.close()
        if own is not None:
            own.close()
    failed = [r for r in results if not r.ok]
    degraded = [r for r in results if r.ok and r.status != COMPLETE]
    flagged = sum(as_configured(r.status) for r in degraded)  # degraded only by the misbehaviour check's flags
    lost = len(degraded) - flagged
    where = "counted in" if args.include_degraded else "left out of"
    print(f"v2vsim sweep: {'interrupted' if interrupted else 'done'}: {sum(r.ok for r in results) - len(degraded)} "
          f"of {len(d.specs)} runs complete, "
          + (f"{flagged} with a sender flagged by the misbehaviour check (counted in the intervals), "
             if flagged else "")
          + (f"{lost} degraded ({where} the intervals), " if lost else "")
          + f"{len(failed)} failed; {paths[0]}", file=stream)
    kept = [s.out / "messages" for s in d.specs if s.records and (s.out / "messages").is_dir()]
    if kept:
        size = sum(f.stat().st_size for m in kept for f in m.iterdir() if f.is_file())
        print(f"v2vsim sweep: {len(kept)} recording(s) kept for later `v2vsim evaluate` ({size / 1e6:.0f} MB, "
              f"{args.out}/runs/*/seed*/messages); delete them when the study is done", file=stream)
    if interrupted:
        return EXIT_INTERRUPTED
    return EXIT_FAILED if failed else 0


def write_outputs(args: SweepArgs, d: Design, results: Sequence[RunResult], interrupted: bool) -> list[Path]:
    """sweep.csv, sweep.json, sweep.md and the plots from the runs that completed."""
    from v2vsim.study.driving import driving_study, has_driving
    from v2vsim.study.plots import plot_all, plot_driving
    from v2vsim.study.summary import STAT_METRICS, point_stats, sweep_json, sweep_md, write_csv, write_json

    order = {s.out: i for i, s in enumerate(d.specs)}
    results = sorted(results, key=lambda r: order[r.spec.out])
    rows = collect(results)
    kept = counted(rows, args.include_degraded)  # what the statistics, tables and plots take
    stats = [s for m in STAT_METRICS for s in point_stats(kept, d.points, m, args.bootstrap, DEFAULT_RNG_SEED)]
    # closed loop only (any run drove a vehicle): an open-loop sweep's files stay as they were
    driving = driving_study(kept, d.axes, d.points, args.bootstrap, DEFAULT_RNG_SEED) if has_driving(rows) else None
    failed = [{"point": ", ".join(r.spec.grid), "seed": r.spec.seed, "code": r.code, "why": r.why,
               "tail": list(r.tail), "log": str(r.spec.out / LOG)} for r in results if not r.ok]
    degraded = [{"point": ", ".join(r.spec.grid), "seed": r.spec.seed, "status": r.status,
                 "run": str(r.spec.out.relative_to(args.out))} for r in results if r.ok and r.status != COMPLETE]
    meta = {"scenario": str(args.scenario), "scenario_name": d.name, "seeds": d.seeds, "frames": args.frames,
            "points": [p.pid for p in d.points], "overrides": d.base, "jobs": args.jobs, "engine": args.engine,
            "bootstrap": {"b": args.bootstrap, "rng_seed": DEFAULT_RNG_SEED, "level": LEVEL,
                          "method": "paired two-level bootstrap (seeds, then frames within each seed), "
                                    "expanded percentile intervals"},
            "runs": {"total": len(d.specs), "complete": sum(r.ok for r in results) - len(degraded),
                     "reused": sum(r.reused for r in results), "failed": failed, "degraded": degraded,
                     "include_degraded": args.include_degraded,
                     "simulated": sum(not s.replayed for s in d.specs), "replayed": sum(s.replayed for s in d.specs),
                     "replayed_points": sorted({s.point.pid for s in d.specs if s.replayed}),
                     "no_replay": d.no_replay},
            "interrupted": interrupted}
    out = args.out
    paths = [out / "sweep.csv", out / "sweep.json", out / "sweep.md"]
    write_csv(paths[0], d.axes, rows)
    pngs = plot_all(out, d.axes, methods_of(kept), stats, d.name) if kept else []
    if driving is not None:
        pngs += plot_driving(out, driving, d.name)
    write_json(paths[1], sweep_json(meta, d.axes, rows, stats, out, driving) | {"plots": [p.name for p in pngs]})
    paths[2].write_text(sweep_md(meta, d.axes, kept, stats, failed, [p.name for p in pngs], driving))
    return paths + pngs
