"""`v2vsim benchmark`: the catalogue's families x methods x configurations x seeds in closed loop, then the
leaderboard (docs/benchmark.md).

    DIR/families/<family>/      that family's sweep (v2vsim.study.sweep): its runs, sweep.csv/json/md and plots;
                                resumable, its complete runs are reused
    DIR/leaderboard.md|csv|json every method per family and overall, against none and pairwise
                                (v2vsim.study.leaderboard)
    DIR/leaderboard_*.png

With --stress NAME,... (issue 54, v2vsim.study.stress) each family is several sweeps instead: its references (oracle,
none) once, and per stress its cooperative methods x the stress's levels (and with compensation on, for the methods
that have it); then DIR/breaking_points.md|csv|json and DIR/stress_<name>.png instead of the leaderboard.

Each family is one sweep over control.method x the family's grid (as the profile thins it) on the split's first
seeds, every run with control.perceive=driving: the ego computes only the method it drives on.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from v2vsim.config import ConfigError, check_output_dir
from v2vsim.launch import Launcher, launcher
from v2vsim.study.catalogue import ORACLE, SPLITS, Catalogue, Family, load_catalogue
from v2vsim.study.leaderboard import episodes_of, write_leaderboard
from v2vsim.study.plan import RunSpec
from v2vsim.study.runs import Job
from v2vsim.study.stats import DEFAULT_B
from v2vsim.study.stress import COMP, REFERENCE, compensable, reference_of, study_levels, write_stress
from v2vsim.study.sweep import EXIT_INTERRUPTED, SweepArgs, prepare, sweep

DRIVING_ONLY = "control.perceive=driving"
DRIVEN = ("ego", "sees", "all")  # --driven (BenchmarkArgs.driven)
EGO = "cav0"  # the driven vehicle of every family (the catalogue's header)


def driven_override(f: Family, driven: str) -> tuple[str, ...]:
    """The override that makes `driven` drive in family `f` (none for the ego alone: the scenarios' default). With
    several driven vehicles each fuses and drives on what it perceives and receives, and the run's metrics.json
    measures the fleet (v2vsim.evaluation.fleet_report): its score is their mean, a success only when every one
    succeeded."""
    if driven == "ego":
        return ()
    if driven == "all":
        return ("cavs.ego=all",)
    if not f.sees:
        raise ConfigError(f"--driven sees: family {f.name} names no CAV that sees its hidden actor (`sees` in the "
                          "catalogue)")
    return (f"cavs.ego=[{','.join([EGO, *f.sees])}]",)


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
    stresses: tuple[str, ...] = ()  # degradation axes of the catalogue's `stress` section (v2vsim.study.stress)
    driven: str = "ego"  # who drives: the ego alone, the ego and the family's CAVs that see the hidden actor, all


def family_sweeps(args: BenchmarkArgs, cat: Catalogue) -> list[tuple[str, SweepArgs]]:
    """(family, its sweep's arguments), in catalogue order; with stresses (family/part, ...) for each of a family's
    sweeps (v2vsim.study.stress's layout). ConfigError for a bad option."""
    if args.profile not in cat.profiles:
        raise ConfigError(f"--profile {args.profile}: allowed: {', '.join(cat.profiles)}")
    if args.driven not in DRIVEN:
        raise ConfigError(f"--driven {args.driven}: allowed: {', '.join(DRIVEN)}")
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
    stresses = [cat.stress(n) for n in args.stresses]
    if stresses and not [m for m in methods if m not in (ORACLE, "none")]:
        raise ConfigError(f"--stress {','.join(args.stresses)}: no cooperative method among --methods "
                          f"{','.join(methods)}: a stress degrades what the CAVs send, which oracle and none never "
                          "read")

    def one(f: Family, ms: Sequence[str], out: Path, extra: Sequence[str] = (), sets: Sequence[str] = ()
            ) -> SweepArgs:
        grid = (f"control.method={','.join(ms)}", *(f"{a.key}={','.join(a.texts)}" for a in f.axes(prof.levels)),
                *extra)
        return SweepArgs(scenario=f.scenario, grid=grid, seeds=text, out=out, jobs=args.jobs,
                         overrides=(DRIVING_ONLY, *driven_override(f, args.driven), *args.overrides, *sets),
                         bootstrap=args.bootstrap,
                         engine=args.engine, scheduler=args.scheduler, replay=False)

    out = []
    for f in fams:
        folder = args.out / "families" / f.name
        if not stresses:
            out.append((f.name, one(f, methods, folder)))
            continue
        refs = [m for m in methods if m in (ORACLE, "none")]
        if any(not st.sets for st in stresses):
            out.append((f"{f.name}/{REFERENCE}", one(f, refs, folder / REFERENCE)))
        coop = [m for m in methods if m not in (ORACLE, "none")]
        for st in stresses:
            if st.sets:  # its overrides may change the world (cavs.count): references of its own, with them
                out.append((f"{f.name}/{reference_of(st)}", one(f, refs, folder / reference_of(st), (), st.sets)))
            level = f"{st.level.key}={','.join(st.level.texts)}"
            out.append((f"{f.name}/{st.name}", one(f, coop, folder / st.name, [level], st.sets)))
            comp = compensable(f.scenario, coop, args.overrides) if st.compensation else []
            if comp:
                out.append((f"{f.name}/{st.name}{COMP}", one(f, comp, folder / f"{st.name}{COMP}", [level],
                                                              [*st.sets, "comm.compensation=true"])))
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
    nf = len({n.split("/")[0] for n, _ in plan})
    parts = f" ({len(plan)} sweeps: stress {', '.join(args.stresses)})" if args.stresses else ""
    print(f"v2vsim benchmark: profile {args.profile}, {nf} famil{'y' if nf == 1 else 'ies'}{parts}, "
          f"{total} runs ({args.split} seeds) -> {args.out}", file=stream)
    code = 0
    with launcher() if start is None else Launcher() as launch:  # one warm starter for every family's runs
        for i, ((name, s), d) in enumerate(zip(plan, designs, strict=True), 1):
            print(f"v2vsim benchmark: {'sweep' if args.stresses else 'family'} {i}/{len(plan)} {name}: "
                  f"{len(d.points)} points x {len(d.seeds)} seeds", file=stream)
            rc = sweep(s, start=start, stream=stream, launch=launch)
            if rc == EXIT_INTERRUPTED:
                print("v2vsim benchmark: interrupted; run the same command again to resume", file=stream)
                return EXIT_INTERRUPTED
            code = code or rc
    prof = cat.profiles[args.profile]
    meta = {"catalogue": str(cat.source), "profile": args.profile, "split": args.split,
            "seeds": plan[0][1].seeds, "families": list(dict.fromkeys(n.split("/")[0] for n, _ in plan)),
            "methods": list(args.methods or prof.methods), "overrides": list(args.overrides),
            **({"driven": args.driven} if args.driven != "ego" else {})}
    docs = {name: json.loads((s.out / "sweep.json").read_text()) for name, s in plan}
    if args.stresses:
        stresses = [cat.stress(n) for n in args.stresses]
        levels = {st.name: study_levels(st, meta["families"], docs) for st in stresses}
        paths = write_stress(args.out, stresses, levels, {**meta, "stresses": list(args.stresses)}, args.bootstrap)
        print(f"v2vsim benchmark: breaking points: {paths[0]}", file=stream)
        return code
    per_family = {name: episodes_of(name, doc) for name, doc in docs.items()}
    paths = write_leaderboard(args.out, per_family, meta["methods"], meta, args.bootstrap)
    print(f"v2vsim benchmark: leaderboard: {paths[0]}", file=stream)
    return code
