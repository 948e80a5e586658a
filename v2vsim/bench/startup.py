"""`v2vsim bench startup`: where a run's start goes, from `v2vsim run` to the ego's first fused frame, by stage and
process, cold beside warm.

    v2vsim bench startup [SCENARIO] [--repeats N] [--modes cold,warm,pool] [--frames N] [--set KEY=VALUE ...]
                         [--json FILE]

Each repeat runs `v2vsim run SCENARIO --frames N` (default 1, output.rerun off) in a fresh process under each mode:

    cold    every process `python -m ...` (V2VSIM_START=cold): what a run cost before the warm starter
    warm    the run starts its own warm starter and forks its agents from it (a lone `v2vsim run`)
    pool    the run and its agents forked from a warm starter already up (a sweep's or benchmark's point)

and reads each process's start-up instants (agents.timing.Startup: metrics.json "timing.startup" for the ego,
timing/<process>.json for the driver and CAVs). The table gives medians over the repeats, in seconds:

    runner      command -> its first agent launched (interpreter, imports, scenario checks, the model checks)
    imports     launched -> the agent's main() (interpreter and imports; a warm fork: the fork)
    zenoh       -> its session and bus up
    sumo        driver: -> the network loaded, the traffic warmed up, the CAVs placed
    models      CAV / ego: -> its models built and their checkpoints verified
    map         CAV / ego: -> the static map fetched and rasterised
    alive       driver: -> every agent up (the slowest agent's start)
    first frame -> its first frame done
    total       command -> the ego's first fused frame; and the whole command (its frames and teardown too)

Compare modes side by side in one session, on an otherwise idle machine (this machine is noisy).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from v2vsim.launch import MODE_ENV, ZYGOTE_ENV, Launcher, Zygote

REPO = Path(__file__).resolve().parents[2]
MODES = ("cold", "warm", "pool")
DEFAULT_SCENARIO = "left_turn_truck"  # a shipped scenario by name, or a path
DEFAULT_SETS = ("control.method=none",)  # the measurement: a closed-loop family point driven blind
ROWS = ("runner", "imports", "zenoh", "sumo", "models", "map", "alive", "first frame")
# stage -> (the mark that ends it, the mark that starts it); "launched" is the runner's clock at the launch
STAGES = {"imports": ("imports", "launched"), "zenoh": ("zenoh", "imports"), "sumo": ("sumo", "zenoh"),
          "models": ("models", "zenoh"), "map": ("map", "models"), "alive": ("agents_alive", "sumo"),
          "first frame": ("first_frame", None)}
PREVIOUS = {"driver": "agents_alive", "cav": "map", "ego": "map"}  # what a process's first frame follows


def _startups(out: Path) -> dict[str, dict]:
    """process -> its Startup document (launched, marks), from a finished run's files."""
    got = {}
    metrics = json.loads((out / "metrics.json").read_text())
    if "startup" in metrics.get("timing", {}):
        got["ego"] = metrics["timing"]["startup"]
    for f in sorted((out / "timing").glob("*.json")):
        doc = json.loads(f.read_text())
        if "startup" in doc:
            got[f.stem] = doc["startup"]
    return got


def split(t_cmd: float, t_end: float, startups: dict[str, dict]) -> dict[str, dict[str, float]]:
    """One run's start-up, stage -> process kind (driver, cav: the slowest CAV, ego) -> seconds."""
    rows: dict[str, dict[str, float]] = {r: {} for r in (*ROWS, "total")}
    launched = [s["launched"] for s in startups.values() if s.get("launched") is not None]
    if launched:
        rows["runner"]["all"] = min(launched) - t_cmd
    for proc, s in startups.items():
        kind = proc.split(".")[0]
        marks = {**s["marks"], "launched": s.get("launched")}
        for stage, (end, start) in STAGES.items():
            start = start if start is not None else PREVIOUS.get(kind)
            if marks.get(end) is None or marks.get(start) is None:
                continue
            v = marks[end] - marks[start]
            rows[stage][kind] = max(rows[stage].get(kind, v), v)  # the slowest CAV: the one the run waits for
    ego = startups.get("ego")
    if ego is not None and "first_frame" in ego["marks"]:
        rows["total"]["to first fused frame"] = ego["marks"]["first_frame"] - t_cmd
    rows["total"]["whole command"] = t_end - t_cmd
    return rows


def run_once(scenario: str, frames: int, sets: list[str], mode: str, zygote: Zygote | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != ZYGOTE_ENV}
    env[MODE_ENV] = "cold" if mode == "cold" else "warm"
    if mode == "pool":
        assert zygote is not None
        env[ZYGOTE_ENV] = zygote.path
    with tempfile.TemporaryDirectory(prefix="v2vsim-bench-startup-") as tmp:
        out = Path(tmp) / "run"
        cmd = [sys.executable, "-m", "v2vsim.cli", "run", scenario, "--frames", str(frames), "--out", str(out),
               "--set", "output.rerun=false", *(x for s in sets for x in ("--set", s))]
        t0 = time.time()
        if mode == "pool":  # the run itself forked from the starter, as a sweep starts its points
            with open(Path(tmp) / "log", "wb") as log, Launcher(zygote.path) as launch:
                code = launch.start("v2vsim.cli", cmd[3:], env, stdout=log).wait()
            tail = (Path(tmp) / "log").read_text(errors="replace")[-2000:]
        else:
            r = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True)
            code, tail = r.returncode, r.stderr[-2000:]
        t1 = time.time()
        if code != 0:
            raise SystemExit(f"bench startup: `v2vsim run` ({mode}) exited with {code}:\n{tail}")
        return split(t0, t1, _startups(out))


def median_table(runs: dict[str, list[dict]]) -> dict[str, dict[str, dict[str, float]]]:
    """mode -> stage -> process -> the median over the repeats."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for mode, reps in runs.items():
        out[mode] = {}
        for stage in (*ROWS, "total"):
            cols = {k for r in reps for k in r[stage]}
            out[mode][stage] = {k: round(statistics.median(r[stage][k] for r in reps if k in r[stage]), 3)
                                for k in sorted(cols)}
    return out


def markdown(table: dict[str, dict[str, dict[str, float]]], repeats: int) -> str:
    kinds = ("all", "driver", "cav", "ego")
    lines = [f"Start-up, seconds, median of {repeats} (cav: the slowest CAV of the run)", "",
             "| stage | " + " | ".join(f"{m}: " + " / ".join(k for k in kinds) for m in table) + " |",
             "|---|" + "---|" * len(table)]
    for stage in ROWS:
        cells = []
        for m in table:
            row = table[m][stage]
            cells.append(" / ".join(f"{row[k]:.2f}" if k in row else "-" for k in kinds))
        lines.append(f"| {stage} | " + " | ".join(cells) + " |")
    for total in ("to first fused frame", "whole command"):
        lines.append(f"| **{total}** | " + " | ".join(
            f"**{table[m]['total'][total]:.2f}**" if total in table[m]["total"] else "-" for m in table) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="v2vsim bench startup", description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", nargs="?", default=DEFAULT_SCENARIO)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--frames", type=int, default=1)
    p.add_argument("--modes", default=",".join(MODES), help=f"comma-separated among {', '.join(MODES)}")
    p.add_argument("--set", dest="sets", action="append", default=None,
                   help=f"scenario override (default: {' '.join(DEFAULT_SETS)})")
    p.add_argument("--json", default=None, help="also write the medians and every repeat here")
    a = p.parse_args(argv)
    modes = [m for m in a.modes.split(",") if m]
    bad = [m for m in modes if m not in MODES]
    if bad or a.repeats < 1:
        p.error(f"--modes {a.modes}: allowed: {', '.join(MODES)}" if bad else "--repeats: at least 1")
    sets = list(DEFAULT_SETS) if a.sets is None else a.sets
    scenario = str(Path(a.scenario).resolve()) if Path(a.scenario).exists() else a.scenario
    runs: dict[str, list[dict]] = {m: [] for m in modes}
    zygote = None
    try:
        if "pool" in modes:
            zygote = Zygote()
            zygote.wait_ready()
        for i in range(a.repeats):  # modes interleaved, so that a slow minute of the machine hits each alike
            for m in modes:
                print(f"bench startup: repeat {i + 1}/{a.repeats}, {m}", file=sys.stderr, flush=True)
                runs[m].append(run_once(scenario, a.frames, sets, m, zygote))
    finally:
        if zygote is not None:
            zygote.close()
    table = median_table(runs)
    print(markdown(table, a.repeats))
    if a.json:
        Path(a.json).write_text(json.dumps({"scenario": a.scenario, "sets": sets, "frames": a.frames,
                                            "medians": table, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
