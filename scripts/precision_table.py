"""bf16 against fp32 on held-out seeds (issue 47): per junction and method, each score's mean over seeds under
both precisions, the largest per-seed difference, and the seed-to-seed spread (standard deviation of the fp32
scores over seeds) it is judged against; then, per seed, whether the methods' order by vehicle IoU changed.

    python scripts/precision_table.py SWEEP_DIR [SWEEP_DIR ...]   # sweeps with --grid perception.precision=fp32,bf16
"""

from __future__ import annotations

import csv
import statistics
import sys
from pathlib import Path

METRICS = ("iou_vehicle", "ap50", "ap70")


def load(sweep: Path) -> dict[tuple[str, int, str], dict[str, float]]:
    """(precision, seed, method) -> scores of the complete runs."""
    out = {}
    with open(sweep / "sweep.csv") as f:
        for r in csv.DictReader(f):
            if r["status"] != "complete":
                continue
            out[(r["perception.precision"], int(r["seed"]), r["method"])] = {
                m: float(r[m]) for m in METRICS if r[m] not in ("", None)}
    return out


def main(argv: list[str]) -> int:
    verdict = True
    for sweep in map(Path, argv):
        rows = load(sweep)
        seeds = sorted({s for p, s, _ in rows if p == "fp32"} & {s for p, s, _ in rows if p == "bf16"})
        methods = list(dict.fromkeys(m for _, _, m in rows))
        print(f"\n### {sweep.name} (seeds {', '.join(map(str, seeds))})\n")
        print("| method | " + " | ".join(f"{m} fp32 | bf16 | largest seed diff | seed spread (sd)" for m in METRICS)
              + " |")
        print("|---|" + "---:|" * (4 * len(METRICS)))
        for meth in methods:
            cells = []
            for met in METRICS:
                a = [rows[("fp32", s, meth)].get(met) for s in seeds]
                b = [rows[("bf16", s, meth)].get(met) for s in seeds]
                if any(x is None for x in a + b):
                    cells += ["", "", "", ""]
                    continue
                diffs = [y - x for x, y in zip(a, b, strict=True)]
                worst = max(diffs, key=abs)
                sd = statistics.stdev(a) if len(a) > 1 else float("nan")
                within = abs(worst) < sd
                verdict &= within
                cells += [f"{statistics.mean(a):.4f}", f"{statistics.mean(b):.4f}",
                          f"{worst:+.4f}{'' if within else ' **'}", f"{sd:.4f}"]
            print(f"| {meth} | " + " | ".join(cells) + " |")
        print()
        for s in seeds:
            order = {p: sorted(methods, key=lambda m, p=p: -rows[(p, s, m)]["iou_vehicle"]) for p in ("fp32", "bf16")}
            same = order["fp32"] == order["bf16"]
            verdict &= same
            swapped = "" if same else f" (bf16: {' > '.join(order['bf16'])})"
            print(f"- seed {s}: vehicle-IoU order {'unchanged' if same else 'CHANGED'}: "
                  f"{' > '.join(order['fp32'])}{swapped}")
    print(f"\nevery difference below the seed spread and every order unchanged: {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
