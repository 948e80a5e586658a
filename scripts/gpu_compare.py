"""The CPU and the GPU run of one scenario side by side (scripts/gpu_check.sh): each run's device and real-time
factor, and per method the vehicle IoU and AP@0.5 / 0.7 on both and their difference. Exit 1 when a method's
vehicle IoU differs by more than --tol, or a method was scored in one run only; exit 0 otherwise. With one run
folder it prints that run alone (a host without CUDA) and exits 0.

    python scripts/gpu_compare.py CPU_RUN [GPU_RUN] [--tol 0.01]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

KEYS = ("iou_vehicle", "ap50", "ap70")  # what is compared; only iou_vehicle is held to the tolerance


def load(run: Path) -> dict:
    """A run folder's metrics.json."""
    return json.loads((run / "metrics.json").read_text())


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.4f}"


def _diff(a: float | None, b: float | None) -> float | None:
    """b - a, None where either is missing (a camera run has no AP)."""
    return None if a is None or b is None else b - a


def describe(name: str, doc: dict) -> str:
    """One line per run: where it ran and how fast."""
    dev = doc.get("device") or {}
    return (f"{name}: device {dev.get('used', '?')} ({dev.get('name', '?')}), real-time factor "
            f"{doc.get('real_time_factor')}, {doc.get('frames')} frames, status {doc.get('status')}")


def compare(cpu: dict, gpu: dict | None, tol: float) -> tuple[list[str], list[str]]:
    """(the table's lines, the failures): per method its CPU figures and, with a GPU run, the GPU's and the
    differences; a failure per method whose vehicle IoU moved by more than `tol` or that one run lacks."""
    lines = [describe("cpu", cpu)] + ([describe("gpu", gpu)] if gpu is not None else [])
    failures: list[str] = []
    if gpu is None:
        lines += ["", "| method | IoU vehicle | AP@0.5 | AP@0.7 |", "|---|---|---|---|"]
        for m, r in cpu["methods"].items():
            lines.append(f"| {m} | " + " | ".join(_num(r.get(k)) for k in KEYS) + " |")
        return lines, failures
    lines += ["", "| method | IoU vehicle cpu | gpu | diff | AP@0.5 diff | AP@0.7 diff |", "|---|---|---|---|---|---|"]
    for m in sorted(set(cpu["methods"]) | set(gpu["methods"])):
        a, b = cpu["methods"].get(m), gpu["methods"].get(m)
        if a is None or b is None:
            failures.append(f"{m}: scored on the {'gpu' if a is None else 'cpu'} only")
            continue
        d = {k: _diff(a.get(k), b.get(k)) for k in KEYS}
        lines.append(f"| {m} | {_num(a.get('iou_vehicle'))} | {_num(b.get('iou_vehicle'))} | "
                     f"{_num(d['iou_vehicle'])} | {_num(d['ap50'])} | {_num(d['ap70'])} |")
        if d["iou_vehicle"] is None or abs(d["iou_vehicle"]) > tol:
            failures.append(f"{m}: vehicle IoU cpu {_num(a.get('iou_vehicle'))}, gpu {_num(b.get('iou_vehicle'))}: "
                            f"differs by more than {tol:g}")
    return lines, failures


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("cpu", type=Path, help="the run folder of the CPU run")
    p.add_argument("gpu", type=Path, nargs="?", help="the run folder of the GPU run (none: the CPU run alone)")
    p.add_argument("--tol", type=float, default=0.01, help="largest vehicle IoU difference allowed (default 0.01)")
    a = p.parse_args(argv)
    lines, failures = compare(load(a.cpu), None if a.gpu is None else load(a.gpu), a.tol)
    print("\n".join(lines))
    for f in failures:
        print(f"gpu_compare: FAIL: {f}", file=sys.stderr)
    if a.gpu is not None and not failures:
        print(f"gpu_compare: every method's vehicle IoU within {a.tol:g} of the CPU's")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
