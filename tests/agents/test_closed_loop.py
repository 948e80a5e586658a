"""The closed loop with real processes (issue 46): the driver, four CAV agents and the ego over zenoh, the ego's
vehicle driven by its planner on `none` (its own LiDAR only) on the occlusion-critical T-junction. The plan
travels in the ego's signed ack and acts after the actuation delay; metrics.json says what the driving came to,
the report says which method drove, and the run is the same run again for the same seed."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from .test_run import Run, _still_running

REPO = Path(__file__).resolve().parents[2]
OCCLUDED = str(REPO / "scenarios" / "t_junction_occluded.yaml")
# two CAVs: the ego plans on `none` (its own LiDAR), so more CAVs would only cost their sensing and encoding
ARGS = ("--frames", "15", "--set", "seed=2", "--set", "cavs.count=2", "--set", "control.method=none",
        "--set", "perception.methods=[none]", "--set", "output.rerun=false")


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
    assert v["frames"] == 15 and v["progress_m"] > 0 and v["min_gap_m"] is not None
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


def _drive(out: Path, frames: int, *sets: str) -> tuple[dict, str]:
    """`v2vsim run` of the occluded T-junction (seed 2, two CAVs, no recording) with `sets`; its metrics and stderr."""
    done = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", OCCLUDED, "--out", str(out), "--frames",
                           str(frames), *(x for s in ("seed=2", "cavs.count=2", "output.rerun=false", *sets)
                                          for x in ("--set", s))],
                          capture_output=True, text=True, timeout=400)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text()), done.stderr


def _stopped_run(tmp_path: Path, stop: str) -> tuple[dict, str, str]:
    """A closed-loop run (CoBEVT driving, 100 frames) stopped at frame 12 by `stop`: "ctrl-c" (SIGINT to the runner,
    as a terminal's Ctrl-C) or "kill-driver" (SIGKILL of the simulator driver). Its metrics.json, report.md and
    stderr."""
    out = tmp_path / "run"
    run = Run("--frames", "100", "--out", str(out), "--set", "seed=2", "--set", "control.method=cobevt",
              "--set", "cavs.count=2", "--set", "perception.methods=[none,cobevt]", "--set", "output.rerun=false",
              scenario=OCCLUDED)
    run.wait_frames(12)
    children = run.children()
    if stop == "ctrl-c":
        run.proc.send_signal(signal.SIGINT)
        assert run.finish(timeout=60) == 130, "".join(run.log)
    else:
        drivers = [p for p in children if "agents.driver" in " ".join(p.cmdline())]
        assert len(drivers) == 1
        drivers[0].send_signal(signal.SIGKILL)
        assert run.finish(timeout=60) == 1, "".join(run.log)
    assert not _still_running(children, timeout=10)
    assert (out / "report.md").is_file(), f"no report.md in {sorted(p.name for p in out.iterdir())}\n{''.join(run.log)}"
    return json.loads((out / "metrics.json").read_text()), (out / "report.md").read_text(), "".join(run.log)


def test_ctrl_c_in_a_closed_loop_run_writes_its_frames_with_the_driving_block(tmp_path: Path) -> None:
    """issue 52 item 0: the ego waited 10 s for the driver's done, which an interrupted driver never sent, and the
    runner killed it after 5 s: nothing written. Now the driver's bye carries its SSM conflicts, and the ego waits
    briefly."""
    m, report, log = _stopped_run(tmp_path, "ctrl-c")
    assert m["status"].startswith("interrupted after"), m["status"]
    assert 12 <= m["frames"] < 100 and m["methods"]["cobevt"]["iou_vehicle"] is not None
    v = m["driving"]["vehicles"]["cav0"]
    assert v["frames"] == m["frames"] and v["progress_m"] > 0
    assert v["ssm"]["conflicts"] is not None  # SUMO closed on the driver's Ctrl-C and its count came in the bye
    assert "## Driving (closed loop)" in report and "partial results are written" in log


def test_a_killed_driver_in_a_closed_loop_run_leaves_its_frames_with_the_driving_block(tmp_path: Path) -> None:
    """issue 52 item 0: a SIGKILLed driver says nothing more; the ego writes what it has without waiting for it."""
    m, report, log = _stopped_run(tmp_path, "kill-driver")
    assert m["status"].startswith("driver died after frame"), m["status"]
    assert 12 <= m["frames"] < 100 and "no results" not in m["status"]
    v = m["driving"]["vehicles"]["cav0"]
    assert v["frames"] == m["frames"] and v["ssm"]["conflicts"] is None  # SUMO never closed its log: unknown
    assert "## Driving (closed loop)" in report
    assert "the simulator driver died (signal 9, SIGKILL)" in log


def test_a_route_completed_early_ends_the_run_complete_with_exit_0(tmp_path: Path) -> None:
    """issue 53: the driven vehicle reaching the end of its route (the best outcome of a drive) ended the run with
    "the simulator driver exited with code 1". Now it arrives, its ego writes a complete run with its score, and the
    run stops there."""
    out = tmp_path / "run"
    m, stderr = _drive(out, 100, "control.method=oracle", "control.route_m=15", "control.perceive=driving")
    assert m["status"] == "complete" and m["frames"] < 100, (m["status"], m["frames"])
    v = m["driving"]["vehicles"]["cav0"]
    assert v["route_completion"] == 1.0 and v["success"] is True and v["driving_score"] == 1.0, v
    assert v["infractions"] == {"collision_vehicle": 0, "red_light": 0, "timeout": 0}
    assert v["route_m"] == 15 and 15 <= v["progress_m"] < 17
    assert v["finished_at_s"] == pytest.approx((m["frames"] - 1) / 10)  # its last frame
    assert m["driving"]["total"]["successes"] == 1 and m["driving"]["total"]["driving_score"] == 1.0
    assert "route completed at frame" in stderr and "every driven vehicle completed its route" in stderr
    assert "error" not in stderr.lower(), stderr[-3000:]
    assert "| cav0 | 1.00 | 1.00 | yes |" in (out / "report.md").read_text()
    # control.perceive driving, oracle: the ego computes `none` alone, and cav1 (no ego) neither encodes nor sends
    assert list(m["methods"]) == ["none"] and m["comm"]["sent"] == 0
    cav1 = json.loads((out / "timing" / "cav.cav1.json").read_text())
    assert "encoding" not in cav1["ms_per_frame"] and cav1["frames"] >= m["frames"] - 1
    assert "encoding" in json.loads((out / "timing" / "cav.cav0.json").read_text())["ms_per_frame"]


def test_every_cav_driven_gives_each_a_driving_block_and_the_run_the_fleet(tmp_path: Path) -> None:
    """issue 54 item 2: with cavs.ego=all each ego wrote only its own vehicle; the run's own metrics.json and report
    now hold every driven CAV's entry and score, and the fleet's totals."""
    out = tmp_path / "run"
    m, _ = _drive(out, 15, "cavs.ego=all", "control.method=oracle", "control.perceive=driving")
    d = m["driving"]
    assert d["driven"] == ["cav0", "cav1"] and set(d["vehicles"]) == {"cav0", "cav1"}
    own1 = json.loads((out / "ego_cav1" / "metrics.json").read_text())["driving"]
    assert d["vehicles"]["cav1"] == own1["vehicles"]["cav1"]  # as cav1's ego measured it
    for v in d["vehicles"].values():
        assert v["frames"] == 15 and v["progress_m"] > 0 and "driving_score" in v
    assert d["total"]["progress_m"] == pytest.approx(sum(v["progress_m"] for v in d["vehicles"].values()), abs=1e-3)
    assert d["total"]["fleet"]["driven"] == 2 and d["total"]["fleet"]["collisions"] == 0
    report = (out / "report.md").read_text()
    assert "| cav0 | " in report and "| cav1 | " in report and "Fleet: 2 driven vehicles" in report


def test_a_penetration_of_0_sends_nothing_and_drives_as_none_bit_for_bit(tmp_path: Path) -> None:
    """issue 54 item 3: with cavs.penetration 0 the placed vehicles besides the ego are SUMO's, silent: no V2V
    message, and late fusion (the ego's own detections and nothing else) drives exactly as `none` does in the same
    traffic with every vehicle connected."""
    zero, _ = _drive(tmp_path / "zero", 15, "cavs.count=3", "cavs.penetration=0", "control.method=late",
                     "perception.methods=[none,late]")
    none, _ = _drive(tmp_path / "none", 15, "cavs.count=3", "control.method=none", "control.perceive=driving")
    assert zero["penetration"] == {"share": 0.0, "connected": ["cav0"]} and "penetration" not in none
    assert zero["comm"]["sent"] == 0 and zero["comm"]["bytes_total"] == 0
    assert zero["driving"]["vehicles"] == none["driving"]["vehicles"] and zero["driving"]["total"] == none["driving"][
        "total"]
    for k in ("iou_vehicle", "ap50", "ap70"):  # (scored on what the connected vehicles saw: here the ego alone)
        assert zero["methods"]["late"][k] == zero["methods"]["none"][k], k
