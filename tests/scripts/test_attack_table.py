"""scripts/attack_table.py on a hand-made benchmark directory: episodes pair by configuration and seed across the
lies, "attacked - clean" and "defended - attacked" are the paired differences of the same method, collisions are
counted per cell, and the liar's and the honest senders' flagged frames come from the defended runs' metrics.json."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SPEED = "traffic.hidden_foe.speed_mps"
LIES = [[], [{"cavs": ["cav1"], "kind": "remove_vehicle"}]]


def _row(method: str, seed: int, speed: int, score: float, iou: float, coll: int, lie: list | None = None,
         run: str = "") -> dict:
    row = {"driving_method": method, "method": method, "seed": seed, SPEED: speed, "status": "complete",
           "driving_driving_score": score, "driving_success": float(coll == 0), "driving_collisions": coll,
           "driving_route_completion": 1.0, "driving_finished_at_s": 10.0, "iou_vehicle": iou, "ap50": iou,
           "run": run}
    if lie is not None:
        row["misbehaviour"] = lie
    return row


def _sweep(d: Path, rows: list[dict], lies: bool) -> None:
    d.mkdir(parents=True)
    grid = [{"key": "control.method", "values": ["cobevt"]}, {"key": SPEED, "values": [8, 11]}]
    if lies:
        grid.append({"key": "misbehaviour", "values": LIES})
    (d / "sweep.json").write_text(json.dumps({"grid": grid, "rows": rows}))


def test_paired_differences_collisions_and_flags(tmp_path: Path) -> None:
    fam = tmp_path / "families" / "blind_pullout"
    eps = [(s, v) for s in (0, 1) for v in (8, 11)]
    _sweep(fam / "reference", [_row(m, s, v, 1.0 if m == "oracle" else 0.8, 0.5, 0) for m in ("oracle", "none")
                               for s, v in eps], False)
    # clean cobevt 0.9 everywhere; the lie costs 0.4 and one collision; the defence buys back 0.3
    _sweep(fam / "attack", [_row("cobevt", s, v, 0.9, 0.6, 0, LIES[0]) for s, v in eps]
           + [_row("cobevt", s, v, 0.5, 0.2, int(s == 0 and v == 8), LIES[1]) for s, v in eps], True)
    dfd = [_row("cobevt", s, v, 0.9, 0.6, 0, LIES[0]) for s, v in eps]
    for k, (s, v) in enumerate(eps):
        run = f"runs/r{k}"
        (fam / "attack_defended" / run).mkdir(parents=True)
        flagged = 30 if k < 2 else 10  # of 40 compared: 80 of 160 over the four runs
        (fam / "attack_defended" / run / "metrics.json").write_text(json.dumps(
            {"defence": {"senders": {"cav1": {"frames_flagged": flagged, "frames_compared": 40},
                                     "cav2": {"frames_flagged": int(k == 3), "frames_compared": 50}}}}))
        dfd.append(_row("cobevt", s, v, 0.8, 0.55, 0, LIES[1], run))
    (fam / "attack_defended" / "sweep.json").write_text(json.dumps(
        {"grid": [{"key": "control.method", "values": ["cobevt"]}, {"key": SPEED, "values": [8, 11]},
                  {"key": "misbehaviour", "values": LIES}], "rows": dfd}))
    out_csv = tmp_path / "t.csv"
    png = tmp_path / "study.png"
    cmd = [sys.executable, "scripts/attack_table.py", str(tmp_path), "--boot", "200", "--csv", str(out_csv), "--plot",
           str(png)]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert "### blind_pullout: 4 episodes" in out
    line = next(ln for ln in out.splitlines() if ln.startswith("| cav1 remove_vehicle | cobevt |"))
    cells = [c.strip() for c in line.split("|")[1:-1]]
    assert cells[2] == "0.900 / 0.500 / 0.800"
    assert cells[3].startswith("-0.400")
    assert cells[4].startswith("+0.300")
    assert cells[5] == "0/4 / 1/4 / 0/4"
    assert cells[6] == "0.600 / 0.200 / 0.550"
    assert cells[9] == "80/160 (4 runs)"  # the liar
    assert cells[10] == "1/200 (1 run)"  # an honest sender flagged: a false positive
    assert "none driving score 0.800, collisions 0/4" in out
    assert png.stat().st_size > 5000
    got = {(r["lie"], r["measure"], r["difference"]): float(r["mean"]) for r in csv.DictReader(out_csv.open())
           if r["mean"]}
    assert abs(got[("cav1 remove_vehicle", "iou_vehicle", "att-clean")] + 0.4) < 1e-9
    assert abs(got[("cav1 remove_vehicle", "collision", "def-att")] + 0.25) < 1e-9


def test_a_directory_without_an_attack_sweep_is_refused(tmp_path: Path) -> None:
    r = subprocess.run([sys.executable, "scripts/attack_table.py", str(tmp_path)], cwd=REPO, capture_output=True,
                       text=True)
    assert r.returncode == 2 and "no " in r.stderr and "attack/sweep.json" in r.stderr


def test_a_lie_that_scores_better_but_drives_closer_shows_as_worse_in_the_safety_weighted_score(tmp_path: Path) -> None:
    """Issue 67's case: the honest drive waits (0.4) and the lie makes it cross at once (1.0) with close calls; the
    CARLA-style difference is positive and the safety-weighted one, against the honest drive, negative."""
    def row(s: int, v: int, score: float, calls: int, safety: float, lie: list) -> dict:
        r = _row("cobevt", s, v, score, 0.5, 0, lie)
        r.update(driving_close_calls=calls, driving_safety_score=safety)
        return r

    fam = tmp_path / "families" / "blind_pullout"
    eps = [(s, v) for s in (0, 1) for v in (8, 11)]
    _sweep(fam / "reference", [_row(m, s, v, 1.0, 0.5, 0) for m in ("oracle", "none") for s, v in eps], False)
    _sweep(fam / "attack", [row(s, v, 0.4, 0, 0.4, LIES[0]) for s, v in eps]
           + [row(s, v, 1.0, 1, 0.775, LIES[1]) for s, v in eps], True)
    _sweep(fam / "attack_defended", [row(s, v, 0.4, 0, 0.4, LIES[0]) for s, v in eps]
           + [row(s, v, 0.3, 0, 0.3, LIES[1]) for s, v in eps], True)
    out = subprocess.run([sys.executable, "scripts/attack_table.py", str(tmp_path), "--boot", "200"], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout
    main = next(ln for ln in out.splitlines() if ln.startswith("| cav1 remove_vehicle | cobevt | 0.400"))
    assert [c.strip() for c in main.split("|")[1:-1]][3].startswith("+0.600")  # the CARLA-style score rose
    safe = next(ln for ln in out.splitlines() if ln.startswith("| cav1 remove_vehicle | cobevt | -0.100"))
    cells = [c.strip() for c in safe.split("|")[1:-1]]
    assert cells[3] == "0/4 / 4/4 / 0/4"  # close calls clean / attacked / defended
    assert cells[4] == "0.400 / 0.775 / 0.300"
    assert cells[5].startswith("+0.375") and cells[6].startswith("-0.100")
