"""Do the CAVs meet? Per scenario and seed, how many other CAVs are within comm range of the ego.

    v2vsim bench placement [SCENARIO ...] [--seeds 0-19] [--set key=value ...]

Runs the traffic backend alone (no sensors, no agents) for the scenario's duration and counts,
in every frame from frame 0, the other CAVs whose centre is within `comm.range_m` of the first
ego's centre (cav0 by default) -- the figure the CAV placement aims for (v2vsim/traffic/sumo.py,
`cavs.arrival_s` / `cavs.meet`). Prints one row per seed: the share of frames with 0, 1, 2, ...
neighbours, the share with at least two, whether the ego was still there at the last frame, the
approach arms the CAVs came from and (SUMO) which look-ahead candidate won; then the minimum
over the seeds. Default: the three shipped scenarios, seeds 0-19. Not a test: see
tests/v2vsim/traffic/test_sumo.py for the checked version.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from v2vsim.config import Scenario, load_scenario
from v2vsim.traffic import make_backend

DEFAULT = ("intersection", "t_junction", "highway_intersection")  # shipped scenarios, by name


def ego_of(sc: Scenario) -> str:
    return sc.cavs.ego[0] if isinstance(sc.cavs.ego, tuple) else "cav0"


def neighbour_counts(sc: Scenario) -> tuple[list[int], int, object]:
    """Per frame, the other CAVs within comm.range_m of the ego (0 once it left); frames it was there."""
    ego = ego_of(sc)
    counts, present = [], 0
    with make_backend(sc) as tb:
        for k in range(sc.frames):
            s = tb.reset() if k == 0 else tb.step()
            e = s.actor(ego)
            if e is None:
                counts.append(0)
                continue
            present += 1
            counts.append(sum(1 for a in s.cavs if a.id != ego and
                              math.hypot(a.pose.x - e.pose.x, a.pose.y - e.pose.y) <= sc.comm.range_m))
        info = getattr(tb, "placement", None), getattr(tb, "cav_plans", ())
    return counts, present, info


def seeds_arg(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="v2vsim bench placement", description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="*", default=list(DEFAULT))
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-19"))
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    args = ap.parse_args(argv)
    summary = []
    for path in args.scenarios:
        worst, worst_alive, t_total = 1.0, None, 0.0
        for seed in args.seeds:
            sc = load_scenario(path, [*args.overrides, f"seed={seed}"])
            t0 = time.perf_counter()
            counts, present, (placement, plans) = neighbour_counts(sc)
            dt = time.perf_counter() - t0
            t_total += dt
            n = len(counts)
            hist = np.bincount(counts, minlength=sc.cavs.count) / n
            ge2 = sum(1 for c in counts if c >= 2) / n
            worst = min(worst, ge2)
            worst_alive = present if worst_alive is None else min(worst_alive, present)
            arms = sorted({p.route.approach for p in plans}) if plans else []
            extra = f" arms {len(arms)} ({','.join(arms)})" if arms else ""
            if placement is not None:
                extra += f" candidate {placement.trial} of {placement.trials_run} tried"
            print(f"{sc.name:22s} seed {seed:2d}  >=2: {ge2:5.3f}  ego frames {present:3d}/{n}  "
                  f"0..{len(hist) - 1}: {' '.join(f'{h:.2f}' for h in hist)}{extra}  {dt:.2f} s", flush=True)
        summary.append((Path(path).stem, worst, worst_alive, t_total / len(args.seeds)))
    print()
    print("| scenario | min over seeds: share of frames with >= 2 neighbours | min ego frames | s per seed |")
    print("|---|---|---|---|")
    for name, worst, alive, per in summary:
        print(f"| {name} | {worst:.3f} | {alive} | {per:.2f} |")
    return 0
