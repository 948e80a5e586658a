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


def test_a_message_of_a_foreign_space_is_refused_and_counted(tmp_path: Path) -> None:
    """The ego of a mixed fleet (its real loop, decoders and models; a bus stand-in delivers one frame): a neighbour's
    map that names another feature space (here the camera zoo's own) is refused as foreign_space and counted, the
    one naming the ego's space is delivered, and the ego carries on to the end of its run."""
    import numpy as np

    import agents.ego as ego_mod
    from agents.args import AgentArgs
    from tests.agents.test_hostile import FakeBus
    from tests.v2vsim.sensors._worlds import car, static_map
    from v2vsim.comm.codec import Message, encode
    from v2vsim.config import load_scenario
    from v2vsim.perception.aligned import feature_space
    from v2vsim.perception.plan import plan_models
    from v2vsim.world.serialize import static_to_bytes, world_to_bytes
    from v2vsim.world.state import WorldState

    sc = load_scenario(MIXED, ["output.rerun=false", "perception.methods=[none, cobevt]", "transport.clock=realtime"])
    static = static_map()
    world = WorldState(0.0, 0, (car("cav0", 0.0, 0.0, cav=True), car("cav1", 20.0, 0.0, cav=True),
                                car("cav2", -20.0, 5.0, cav=True)), static)
    args = AgentArgs(scenario=sc, scenario_path=MIXED, overrides=(), run_id="mixed", listen="", peers=(),
                     cavs=("cav0", "cav1", "cav2"), egos=("cav0",), cav="cav0", frames=1, out=str(tmp_path))

    def features(sender: str, space: str, pose: tuple[float, float, float, float]) -> bytes:
        rng = np.random.default_rng(len(sender))
        return encode(Message(kind="features", run_id="mixed", sender_id=sender, frame=0, capture_time=0.0,
                              sender_pose=pose, payload=rng.random((8, 64, 64), dtype=np.float32),
                              channel_compression=8, space=space))

    class Deliver(FakeBus):
        def ready(self) -> None:
            super().ready()
            for cb in self.subs["features"]:
                cb("cav1", features("cav1", "sinbevt@sinbevt_tiny:0123456789ab", (20.0, 0.0, 0.0, 0.0)))
                cb("cav2", features("cav2", f"sinbevt@{feature_space(plan_models(sc))}", (-20.0, 5.0, 0.0, 0.0)))

    assert ego_mod.ego_loop(args, Deliver(static_to_bytes(static), world_to_bytes(world))) == 0  # type: ignore[arg-type]
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["frames"] == 1 and m["comm"]["rejected_reasons"] == {"foreign_space": 1}, m["comm"]
    assert m["comm"]["delivered"] == 1 and m["comm"]["rejected"] == 1
