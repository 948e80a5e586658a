"""`v2vsim bench fleet`: what a run costs as the fleet grows.

    v2vsim bench fleet [SCENARIO] [--cavs 2,4,8,16] [--methods all --methods none,cobevt] [--frames 60]
                       [--set KEY=VALUE ...] --out DIR [--plot PNG] [--json FILE]

Runs `v2vsim run` (every process, real zenoh, the recording off) once per fleet size and method set, and
prints per run: the real-time factor, wall ms per frame, the CPU every process spent per frame (all threads,
user + system, from each process's first frame on; start-up excluded), the ego's own split (fusion, decoding,
the rest) and one CAV's CPU, and the mean number of other CAVs within range of the ego (what the fusion methods
pay for). Resumable: a run already complete in DIR with the same frames is read, not run again.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from v2vsim.bench.run import cpu_per_frame, read_run, run_command, set_args

ALL = "all"  # the scenario's own perception.methods


def _tag(methods: str) -> str:
    return "all" if methods == ALL else methods.replace(",", "+")


def run_point(scenario: str, cavs: int, methods: str, frames: int, overrides: list[str], out: Path) -> dict:
    """One run of the grid (or the complete one already in `out`): its metrics.json and timing/*.json."""
    if (out / "metrics.json").exists():
        res = read_run(out)
        m = res["metrics"]
        if m.get("frames") == frames and str(m.get("status", "")).startswith("complete"):
            print(f"bench fleet: {cavs} CAVs, {methods}: complete in {out}, read", file=sys.stderr, flush=True)
            return res
    extra = ["--set", f"cavs.count={cavs}", "--set", "output.rerun=false", *set_args(overrides)]
    if methods != ALL:
        extra += ["--methods", methods]
    print(f"bench fleet: {cavs} CAVs, methods {methods}", file=sys.stderr, flush=True)
    return run_command(scenario, frames, extra, out)


def fleet_row(cavs: int, methods: str, res: dict) -> dict:
    """The figures of one run (see the module docstring)."""
    m = res["metrics"]
    frames = max(int(m["frames"]), 1)
    split = m["timing"]["ms_per_frame"]
    cpu = cpu_per_frame(res)
    cav_cpu = [v for k, v in cpu.items() if k.startswith("cav.")]
    near = m.get("neighbours_in_range") or {}
    return {
        "cavs": cavs, "methods": methods, "frames": frames, "status": m["status"],
        "rtf": m["real_time_factor"], "wall_ms_per_frame": round(1000 * m["wall_s"] / frames, 1),
        "cpu_ms_per_frame": round(sum(cpu.values()), 1),
        "ego_cpu_ms": cpu.get("ego"), "cav_cpu_ms_mean": round(sum(cav_cpu) / len(cav_cpu), 1) if cav_cpu else None,
        "ego_fusion_ms": round(sum(v for k, v in split.items() if k.startswith("fusion.")), 1),
        "ego_decoding_ms": round(sum(v for k, v in split.items() if k.startswith("decoding.")), 1),
        "ego_compute_ms": m["timing"]["compute_ms_per_frame"],
        "neighbours_mean": round(sum(int(n) * float(share) for n, share in near.items()), 2),
    }


def print_table(rows: list[dict]) -> None:
    print("\n| CAVs | methods | real-time factor | wall ms/frame | CPU ms/frame (all processes) | ego CPU | "
          "CAV CPU (mean) | ego fusion | ego decoding | ego compute | CAVs in range (mean) |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['cavs']} | {r['methods']} | {r['rtf']:.3f}x | {r['wall_ms_per_frame']:.0f} | "
              f"{r['cpu_ms_per_frame']:.0f} | {r['ego_cpu_ms'] or 0:.0f} | {r['cav_cpu_ms_mean'] or 0:.0f} | "
              f"{r['ego_fusion_ms']:.0f} | {r['ego_decoding_ms']:.0f} | {r['ego_compute_ms']:.0f} | "
              f"{r['neighbours_mean']:.2f} |")


def plot(rows: list[dict], path: Path) -> None:
    """Real-time factor and CPU per frame against the fleet size, one line per method set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    for methods in dict.fromkeys(r["methods"] for r in rows):
        rs = sorted((r for r in rows if r["methods"] == methods), key=lambda r: r["cavs"])
        n = [r["cavs"] for r in rs]
        a.plot(n, [r["rtf"] for r in rs], "o-", label=methods)
        b.plot(n, [r["cpu_ms_per_frame"] for r in rs], "o-", label=f"{methods}: all processes")
        b.plot(n, [r["ego_cpu_ms"] or 0 for r in rs], "s--", label=f"{methods}: ego")
    first = min(rows, key=lambda r: (r["methods"] != rows[0]["methods"], r["cavs"]))
    ns = sorted({r["cavs"] for r in rows})
    b.plot(ns, [first["cpu_ms_per_frame"] * n / first["cavs"] for n in ns], ":", color="grey",
           label=f"linear in CAVs (from {first['methods']}, {first['cavs']})")
    for ax in (a, b):
        ax.set_xscale("log", base=2)
        ax.set_xticks([r["cavs"] for r in rows], [str(r["cavs"]) for r in rows])
        ax.set_xlabel("CAVs in the run")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    a.set_ylabel("real-time factor (simulated s / wall s)")
    b.set_ylabel("CPU ms per simulated frame")
    b.set_yscale("log")
    fig.suptitle("Cost against fleet size (recording off)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="v2vsim bench fleet", description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="intersection")
    ap.add_argument("--cavs", default="2,4,8,16", help="comma-separated fleet sizes")
    ap.add_argument("--methods", action="append", default=None,
                    help=f"a method set, comma-separated, or {ALL!r} (the scenario's); repeatable "
                         f"(default: {ALL} and none,cobevt)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--out", required=True, help="keep the runs here (resumable)")
    ap.add_argument("--plot", default=None, help="write the plot to this PNG")
    ap.add_argument("--json", default=None, help="also write the rows as JSON to this file")
    a = ap.parse_args(argv)
    try:
        sizes = [int(n) for n in a.cavs.split(",") if n]
    except ValueError:
        ap.error(f"--cavs {a.cavs!r}: expected comma-separated integers, e.g. 2,4,8,16")
    if any(n < 1 for n in sizes):
        ap.error(f"--cavs {a.cavs!r}: every fleet size must be at least 1")
    sets = a.methods or [ALL, "none,cobevt"]
    root = Path(a.out)
    rows = [fleet_row(n, ms, run_point(a.scenario, n, ms, a.frames, a.overrides, root / f"{_tag(ms)}_n{n}"))
            for ms in sets for n in sizes]
    print_table(rows)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    if a.plot:
        plot(rows, Path(a.plot))
    return 0
