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


def run_once(scenario: str, frames: int, pipeline: int, overrides: list[str], out: Path) -> dict:
    cmd = [sys.executable, "-m", "v2vsim.cli", "run", scenario, "--frames", str(frames), "--out", str(out),
           "--set", f"transport.pipeline={pipeline}"]
    for o in overrides:
        cmd += ["--set", o]
    print(f"bench run: pipeline {pipeline}: {' '.join(cmd[3:])}", file=sys.stderr, flush=True)
    rc = subprocess.run(cmd, cwd=REPO).returncode
    if rc != 0:
        raise SystemExit(f"bench run: `v2vsim run` exited with {rc}")
    metrics = json.loads((out / "metrics.json").read_text())
    timing = {p.stem: json.loads(p.read_text()) for p in sorted((out / "timing").glob("*.json"))}
    return {"metrics": metrics, "timing": timing}


def summary_row(pipeline: int, res: dict) -> dict:
    m = res["metrics"]
    ego = m["timing"]
    compute = ego["compute_ms_per_frame"]
    wall = m["wall_s"]
    return {"pipeline": pipeline, "frames": m["frames"], "wall_s": wall, "rtf": m["real_time_factor"],
            "ego_compute_ms": compute, "ratio": wall / max(compute * m["frames"] / 1000, 1e-9)}


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
    print("\n| pipeline | frames | wall s | real-time factor | ego compute ms/frame | wall / (ego compute x frames) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['pipeline']} | {r['frames']} | {r['wall_s']:.1f} | {r['rtf']:.3f}x | {r['ego_compute_ms']:.1f} "
              f"| {r['ratio']:.2f} |")
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
