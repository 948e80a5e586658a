"""A mixed fleet end to end with real processes (issue 48): two LiDAR CAVs (PointPillars) and two camera CAVs (SinBEVT
aligned into the LiDAR zoo's space), the shipped scenarios/intersection_mixed.yaml and zoo; every method scores,
every feature message is accepted (each names its space), the report and metrics name each agent's type."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
MIXED = str(REPO / "scenarios" / "intersection_mixed.yaml")
METHODS = ["none", "late", "early", "attfuse", "fcooper", "v2vnet", "disconet", "cobevt"]


def _run(out: Path, *extra: str) -> tuple[dict, str]:
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", MIXED, "--frames", "3", "--out", str(out),
                        "--set", "comm.range_m=300", *extra], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr
    return json.loads((out / "metrics.json").read_text()), r.stderr


def test_two_lidar_and_two_camera_cavs_score_every_method(tmp_path: Path) -> None:
    m, err = _run(tmp_path / "mixed")
    assert "fleet: cav0 LiDAR (pointpillars), cav1 LiDAR (pointpillars), cav2 camera (sinbevt), cav3 camera" in err
    assert m["status"] == "complete" and m["frames"] == 3
    assert list(m["methods"]) == METHODS
    assert all(r["iou_vehicle"] is not None and r["ap50"] is not None for r in m["methods"].values())
    # three neighbours x three frames, each message naming the ego's space: none refused
    assert m["comm"]["delivered"] == 9 and m["comm"]["rejected"] == 0
    types = m["fleet"]["types"]
    assert types["LiDAR (pointpillars)"]["cavs"] == ["cav0", "cav1"]
    assert types["camera (sinbevt)"]["cavs"] == ["cav2", "cav3"]
    # the ego's own map never crossed the air: one LiDAR message a frame, two camera ones, the same wire size
    lidar_b, cam_b = (types[t]["feature_bytes_per_frame"] for t in ("LiDAR (pointpillars)", "camera (sinbevt)"))
    assert lidar_b > 0 and abs(cam_b - 2 * lidar_b) <= 64
    assert m["checkpoints"]["cobevt"] == "pointpillars_tiny/cobevt.pt"
    report = (tmp_path / "mixed" / "report.md").read_text()
    assert "## Fleet (cavs.fleet)" in report and "| camera (sinbevt) | cav2, cav3 |" in report
    assert (tmp_path / "mixed" / "recording.rrd").stat().st_size > 0


def test_a_camera_ego_fuses_lidar_neighbours_without_early_fusion(tmp_path: Path) -> None:
    m, err = _run(tmp_path / "cam_ego", "--set", "output.rerun=false", "--methods", "none,late,early,cobevt",
                  "--set", "cavs.fleet=[{cavs: [cav0, cav3], modality: camera, encoder: sinbevt}]")
    assert "early left out: early fusion ships LiDAR points and an ego of this mixed fleet carries no LiDAR" in err
    assert list(m["methods"]) == ["none", "late", "cobevt"] and m["status"] == "complete"
    assert m["fleet"]["cavs"]["cav0"] == "camera (sinbevt)" and m["comm"]["rejected"] == 0
    report = (tmp_path / "cam_ego" / "report.md").read_text()
    assert "Not run with cav0's camera (sinbevt) sensor: early" in report
