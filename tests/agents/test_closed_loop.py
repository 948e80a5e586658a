"""The closed loop with real processes (issue 46): the driver, four CAV agents and the ego over zenoh, the ego's
vehicle driven by its planner on `none` (its own LiDAR only) on the occlusion-critical T-junction. The plan
travels in the ego's signed ack and acts after the actuation delay; metrics.json says what the driving came to,
the report says which method drove, and the run is the same run again for the same seed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
OCCLUDED = str(REPO / "scenarios" / "t_junction_occluded.yaml")
ARGS = ("--frames", "30", "--set", "seed=2", "--set", "control.method=none", "--set", "perception.methods=[none]",
        "--set", "output.rerun=false")


def _run(out: Path) -> dict:
    done = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", OCCLUDED, "--out", str(out), *ARGS],
                          capture_output=True, text=True, timeout=400)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text())


def test_a_closed_loop_run_drives_reports_and_repeats_itself(tmp_path: Path) -> None:
    a, b = _run(tmp_path / "a"), _run(tmp_path / "b")
    assert a["status"] == "complete"
    d = a["driving"]
    assert d["method"] == "none" and d["driven"] == ["cav0"] and d["actuation_delay_frames"] == 2
    v = d["vehicles"]["cav0"]
    assert v["frames"] == 30 and v["progress_m"] > 0 and v["min_gap_m"] is not None
    assert d["total"]["collisions"] == v["collisions"]
    assert v["ssm"]["conflicts"] is not None  # the driver's done carried SUMO's SSM log
    assert (tmp_path / "a" / "ssm.xml").is_file()
    report = (tmp_path / "a" / "report.md").read_text()
    assert "## Driving (closed loop)" in report and "planned on **none**" in report
    # lockstep: the same seed drives the same way, and perceives the same
    assert b["driving"] == d and b["methods"]["none"]["iou_vehicle"] == a["methods"]["none"]["iou_vehicle"]
    # the driver applied plans (no refused commands) and the ego sent one per frame
    timing = json.loads((tmp_path / "a" / "timing" / "driver.json").read_text())
    assert not timing.get("control_rejections"), timing
