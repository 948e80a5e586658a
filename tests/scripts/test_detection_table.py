"""scripts/detection_table.py on hand-made metrics.json files: a liar's frames count from the lie's first frame, an
honest sender's flags in a clean run are false positives, and thresholds given recompute the flags."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _run(d: Path, rows: dict[str, list[list]], lies: list[dict] | None = None) -> None:
    d.mkdir(parents=True)
    doc = {"defence": {"senders": {s: {"per_frame": r} for s, r in rows.items()}}}
    if lies:
        doc["misbehaviour"] = lies
    (d / "metrics.json").write_text(json.dumps(doc))


def test_rates_per_lie_and_on_clean_runs(tmp_path: Path) -> None:
    # frame, road, vehicle_m2, shared_m2, flagged, road_corr, road_vs_map
    _run(tmp_path / "lie", {"cav1": [[0, 0, 0, 500, False, 1, 0.0], [1, 0, 90, 500, True, 1, 0.0],
                                     [2, 0, 0, 500, True, 1, 0.3], [3, 0, 0, 500, True, 1, 0.3]],
                            "cav2": [[0, 0, 0, 500, False, 1, 0.0]]},
         [{"cavs": ["cav1"], "kind": "scale", "from_frame": 1}])
    _run(tmp_path / "clean", {"cav1": [[f, 0, 50 if f < 3 else 0, 500, f < 3, 1, 0.0] for f in range(10)]})
    out = subprocess.run([sys.executable, "scripts/detection_table.py", str(tmp_path)], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout
    assert "| scale | 3 / 3 (1.00) | 1 / 1 | 0 |" in out  # frame 0 came before the lie
    assert "honest sender-frames flagged (FPR) 3 / 10 (0.300); runs with a sender flagged in >= 3 frames: 1 / 1" in out
    strict = subprocess.run([sys.executable, "scripts/detection_table.py", str(tmp_path), "--road-threshold", "0.2",
                             "--vehicle-threshold", "60"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    assert "| scale | 3 / 3 (1.00) |" in strict and "(FPR) 0 / 10 (0.000)" in strict
