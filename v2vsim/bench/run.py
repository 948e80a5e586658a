"""`v2vsim bench run`: the whole run's speed and where a frame's time goes.

    v2vsim bench run [SCENARIO] [--frames N] [--pipeline 0,2] [--set KEY=VALUE ...] [--out DIR]

Runs `v2vsim run` (all processes, real zenoh, the scenario's methods and recording) once per
`transport.pipeline` value and prints, for each: wall time, real-time factor (simulated s / wall s),
and the ratio wall / (ego's own compute per frame x frames), which is 1.0 when nothing but the ego's
work is on the critical path. Then the split of a frame (ms) for the ego, one CAV and the driver:
sensing, encoding, comm, fusion per method, decoding per method, ground truth, scoring, recording,
and the waits. Timings come from each process's StageTimer (metrics.json "timing" and
<out>/timing/*.json). Start-up (imports, model building, SUMO) is not in the wall time.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def run_command(scenario: str, frames: int, extra: list[str], out: Path) -> dict:
    """`v2vsim run SCENARIO --frames N --out OUT EXTRA...`; its metrics.json and every timing/*.json."""
    cmd = [sys.executable, "-m", "v2vsim.cli", "run", scenario, "--frames", str(frames), "--out", str(out), *extra]
    print(f"bench: {' '.join(cmd[3:])}", file=sys.stderr, flush=True)
    rc = subprocess.run(cmd, cwd=REPO).returncode
    if rc != 0:
        raise SystemExit(f"bench: `v2vsim run` exited with {rc}")
    return read_run(out)


def read_run(out: Path) -> dict:
    """A finished run's metrics.json and every timing/*.json (by process name)."""
    metrics = json.loads((out / "metrics.json").read_text())
    timing = {p.stem: json.loads(p.read_text()) for p in sorted((out / "timing").glob("*.json"))}
    return {"metrics": metrics, "timing": timing}


def set_args(overrides: list[str]) -> list[str]:
    """KEY=VALUE overrides as `v2vsim run` arguments: --set KEY=VALUE each."""
    return [a for o in overrides for a in ("--set", o)]


def run_once(scenario: str, frames: int, pipeline: int, overrides: list[str], out: Path) -> dict:
    return run_command(scenario, frames, ["--set", f"transport.pipeline={pipeline}", *set_args(overrides)], out)


def cpu_per_frame(res: dict) -> dict[str, float]:
    """CPU ms per frame of each process (every thread, user + system, from its first frame on; the ego's from
    metrics.json, the others' from timing/*.json); processes that did not say are left out."""
    out = {"ego": res["metrics"]["timing"].get("cpu_ms_per_frame")}
    out |= {name: t.get("cpu_ms_per_frame") for name, t in res["timing"].items()}
    return {k: v for k, v in out.items() if v is not None}


def summary_row(pipeline: int, res: dict) -> dict:
    m = res["metrics"]
    ego = m["timing"]
    compute = ego["compute_ms_per_frame"]
    wall = m["wall_s"]
    cpu = cpu_per_frame(res)
    cpu_total = sum(cpu.values())
    wall_ms = 1000 * wall / max(m["frames"], 1)
    return {"pipeline": pipeline, "frames": m["frames"], "wall_s": wall, "rtf": m["real_time_factor"],
            "ego_compute_ms": compute, "ratio": wall / max(compute * m["frames"] / 1000, 1e-9),
            "cpu_ms_per_frame": round(cpu_total, 1), "cores_busy": round(cpu_total / max(wall_ms, 1e-9), 2),
            "cpu_by_process": cpu}


def split_table(res: dict) -> list[tuple[str, dict[str, float]]]:
    """(process, ms per frame by stage) for the ego, the first CAV and the driver."""
    out = [("ego", res["metrics"]["timing"]["ms_per_frame"])]
    cavs = [k for k in res["timing"] if k.startswith("cav.")]
    if cavs:
        out.append((cavs[0], res["timing"][cavs[0]]["ms_per_frame"]))
    if "driver" in res["timing"]:
        out.append(("driver", res["timing"]["driver"]["ms_per_frame"]))
    return out


def print_report(rows: list[dict], results: dict[int, dict]) -> None:
    print("\n| pipeline | frames | wall s | real-time factor | ego compute ms/frame | wall / (ego compute x frames) "
          "| CPU ms/frame, all processes | cores busy |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['pipeline']} | {r['frames']} | {r['wall_s']:.1f} | {r['rtf']:.3f}x | {r['ego_compute_ms']:.1f} "
              f"| {r['ratio']:.2f} | {r['cpu_ms_per_frame']:.0f} | {r['cores_busy']:.2f} |")
    for p, res in results.items():
        print(f"\nframe split, pipeline {p} (ms per frame; wait* = waiting for others):\n")
        tables = split_table(res)
        stages = sorted({s for _, t in tables for s in t}, key=_stage_order)
        print("| stage | " + " | ".join(name for name, _ in tables) + " |")
        print("|---|" + "---|" * len(tables))
        for s in stages:
            print(f"| {s} | " + " | ".join(f"{t[s]:.1f}" if s in t else "" for _, t in tables) + " |")
        print("| **compute total** | " + " | ".join(
            f"{sum(v for k, v in t.items() if not k.startswith('wait')):.1f}" for _, t in tables) + " |")
        cpu = cpu_per_frame(res)
        print("| **CPU (all threads)** | " + " | ".join(
            f"{cpu[name]:.1f}" if name in cpu else "" for name, _ in tables) + " |")


def _stage_order(stage: str) -> tuple[int, str]:
    order = ["stepping", "sensing", "encoding", "comm", "ground_truth", "fusion", "decoding", "scoring",
             "recording", "wait"]
    head = stage.split(".")[0]
    return (next((i for i, o in enumerate(order) if head.startswith(o)), len(order)), stage)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="v2vsim bench run", description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="intersection")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--pipeline", default="0,2", help="comma-separated transport.pipeline values to compare")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", default=None, help="keep the runs here (default: a temporary directory)")
    ap.add_argument("--json", default=None, help="also write the results as JSON to this file")
    a = ap.parse_args(argv)
    pipelines = [int(p) for p in a.pipeline.split(",") if p]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(a.out) if a.out else Path(tmp)
        results = {p: run_once(a.scenario, a.frames, p, a.overrides, root / f"pipeline{p}") for p in pipelines}
        rows = [summary_row(p, r) for p, r in results.items()]
        print_report(rows, results)
        if a.json:
            Path(a.json).write_text(json.dumps({"rows": rows, "split": {
                str(p): dict(split_table(r)) for p, r in results.items()}}, indent=1))
    return 0
