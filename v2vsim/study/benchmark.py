"""`v2vsim benchmark`: the catalogue's families x methods x configurations x seeds in closed loop, then the
leaderboard (docs/benchmark.md).

    DIR/families/<family>/      that family's sweep (v2vsim.study.sweep): its runs, sweep.csv/json/md and plots;
                                resumable, its complete runs are reused
    DIR/leaderboard.md|csv|json every method per family and overall, against none and pairwise
                                (v2vsim.study.leaderboard)
    DIR/leaderboard_*.png

Each family is one sweep over control.method x the family's grid (as the profile thins it) on the split's first
seeds, every run with control.perceive=driving: the ego computes only the method it drives on.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from v2vsim.config import ConfigError, check_output_dir
from v2vsim.study.catalogue import SPLITS, Catalogue, load_catalogue
from v2vsim.study.leaderboard import episodes_of, write_leaderboard
from v2vsim.study.plan import RunSpec
from v2vsim.study.runs import Job
from v2vsim.study.stats import DEFAULT_B
from v2vsim.study.sweep import EXIT_INTERRUPTED, SweepArgs, prepare, sweep

DRIVING_ONLY = "control.perceive=driving"


@dataclass(frozen=True)
class BenchmarkArgs:
    out: Path
    profile: str = "quick"
    catalogue: Path | None = None  # default: the shipped one
    split: str = "heldout"  # tuning: the calibration's seeds
    families: tuple[str, ...] = ()  # default: every family
    methods: tuple[str, ...] = ()  # default: the profile's
    seeds: int | None = None  # default: the profile's count
    jobs: int | None = None
    engine: str = "local"
    scheduler: str | None = None
    overrides: tuple[str, ...] = ()
    bootstrap: int = DEFAULT_B


def family_sweeps(args: BenchmarkArgs, cat: Catalogue) -> list[tuple[str, SweepArgs]]:
    """(family, its sweep's arguments), in catalogue order; ConfigError for a bad option."""
    if args.profile not in cat.profiles:
        raise ConfigError(f"--profile {args.profile}: allowed: {', '.join(cat.profiles)}")
    if args.split not in SPLITS:
        raise ConfigError(f"--split {args.split}: allowed: {', '.join(SPLITS)}")
    prof = cat.profiles[args.profile]
    methods = args.methods or prof.methods
    stray = [m for m in methods if m not in cat.methods]
    if stray:
        raise ConfigError(f"--methods: {stray[0]!r} is not among the catalogue's methods ({', '.join(cat.methods)})")
    fams = [cat.family(n) for n in args.families] if args.families else list(cat.families)
    n = args.seeds or prof.seeds
    pool = cat.seeds[args.split]
    if n > len(pool):
        raise ConfigError(f"--seeds {n}: the catalogue's {args.split} split has {len(pool)} seeds")
    seeds = pool[:n]
    if list(seeds) != list(range(seeds[0], seeds[0] + n)):
        raise ConfigError(f"{cat.source}: seeds.{args.split}: the first {n} seeds must be consecutive")
    text = f"{seeds[0]}-{seeds[-1]}"
    out = []
    for f in fams:
        grid = (f"control.method={','.join(methods)}",
                *(f"{a.key}={','.join(a.texts)}" for a in f.axes(prof.levels)))
        out.append((f.name, SweepArgs(scenario=f.scenario, grid=grid, seeds=text, out=args.out / "families" / f.name,
                                      jobs=args.jobs, overrides=(DRIVING_ONLY, *args.overrides),
                                      bootstrap=args.bootstrap, engine=args.engine, scheduler=args.scheduler,
                                      replay=False)))
    return out


def benchmark(args: BenchmarkArgs, start: Callable[[RunSpec], Job] | None = None, stream: TextIO | None = None
              ) -> int:
    """Run every family's sweep, then write the leaderboard; the exit code (0, 1 if a run failed, 130 when
    interrupted: what finished is kept, and the same command resumes)."""
    stream = stream or sys.stderr
    cat = load_catalogue(args.catalogue)
    plan = family_sweeps(args, cat)
    check_output_dir(args.out, "--out")
    designs = [prepare(s) for _, s in plan]  # every family's every point validated before anything runs
    total = sum(len(d.specs) for d in designs)
    print(f"v2vsim benchmark: profile {args.profile}, {len(plan)} famil{'y' if len(plan) == 1 else 'ies'}, "
          f"{total} runs ({args.split} seeds) -> {args.out}", file=stream)
    code = 0
    for i, ((name, s), d) in enumerate(zip(plan, designs, strict=True), 1):
        print(f"v2vsim benchmark: family {i}/{len(plan)} {name}: {len(d.points)} points x {len(d.seeds)} seeds",
              file=stream)
        rc = sweep(s, start=start, stream=stream)
        if rc == EXIT_INTERRUPTED:
            print("v2vsim benchmark: interrupted; run the same command again to resume", file=stream)
            return EXIT_INTERRUPTED
        code = code or rc
    per_family = {}
    for name, s in plan:
        doc = json.loads((s.out / "sweep.json").read_text())
        per_family[name] = episodes_of(name, doc)
    prof = cat.profiles[args.profile]
    meta = {"catalogue": str(cat.source), "profile": args.profile, "split": args.split,
            "seeds": plan[0][1].seeds, "families": [n for n, _ in plan],
            "methods": list(args.methods or prof.methods), "overrides": list(args.overrides)}
    paths = write_leaderboard(args.out, per_family, meta["methods"], meta, args.bootstrap)
    print(f"v2vsim benchmark: leaderboard: {paths[0]}", file=stream)
    return code
