"""Record once, evaluate many (issue 32): a lockstep run with output.record_messages, then `v2vsim evaluate`
over its recording with nothing changed gives the same scores and comm counts, bit for bit; a receiver-side
change is scored without re-simulating; a sender-side change is refused in one line (exit 2)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from v2vsim.recording.messages import FORMAT, VERSION, Recording

REPO = Path(__file__).resolve().parents[2]
SCENARIO = str(REPO / "scenarios" / "intersection.yaml")
LOSSY = ["--set", "cavs.count=3", "--set", "comm.range_m=300", "--methods", "none,late,cobevt",
         "--set", "comm.drop.p=0.3", "--set", "comm.latency_ms={mean: 20, jitter: 30}",
         "--set", "comm.fusion_deadline_ms=50", "--set", "comm.pose_noise={xy_std_m: 0.3, yaw_std_deg: 1.0}",
         "--set", "output.rerun=false"]


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "v2vsim.cli", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=timeout)


def _scores(m: dict) -> dict:
    """Everything in metrics.json that must not depend on wall-clock timing (as tests/agents/test_run.py)."""
    methods = {name: {k: v for k, v in r.items() if k != "fusion_ms"} for name, r in m["methods"].items()}
    return {"comm": m["comm"], "methods": methods, "frames": m["frames"], "status": m["status"],
            "lost_agents": m.get("lost_agents")}


def _record(out: Path, *extra: str) -> dict:
    r = _cli("run", SCENARIO, "--frames", "6", "--out", str(out), *LOSSY, "--set", "output.record_messages=true",
             *extra)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text())


def _replay(rec: Path, out: Path, *extra: str) -> dict:
    r = _cli("evaluate", str(rec), "--out", str(out), *extra)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def per_link(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """One recorded lossy run on per-link channels, shared by the tests below (a run costs ~30 s)."""
    out = tmp_path_factory.mktemp("per_link") / "live"
    return out, _record(out)


def _same_as_live(rec: Path, live: dict, out: Path) -> None:
    assert live["status"] == "complete" and live["comm"]["delivered"] > 0 and live["comm"]["dropped"] > 0
    recording = Recording(rec)
    h = recording.header
    assert h["format"] == FORMAT and h["version"] == VERSION and h["frames"] == 6 and h["status"] == "complete"
    assert h["kinds"] == ["features", "outputs"]
    frames = list(recording.frames())
    assert [k for k, _ in frames] == list(range(6))
    assert all(len(f.raw["features"]) == 3 and len(f.raw["outputs"]) == 3 for _, f in frames)  # every live CAV
    replay = _replay(rec, out)
    assert _scores(replay) == _scores(live)
    assert (out / "report.md").exists()


def test_evaluate_over_a_recording_is_the_live_run_bit_for_bit(per_link: tuple[Path, dict], tmp_path: Path) -> None:
    _same_as_live(*per_link, tmp_path / "replay")


def test_evaluate_may_move_the_ego_to_another_device(per_link: tuple[Path, dict], tmp_path: Path) -> None:
    """perception.device is where the replayed ego infers (the CAVs' side is recorded): cpu replays the auto run
    of this CPU host bit for bit; a CUDA device this host lacks is one line naming the key, exit 2."""
    rec, live = per_link
    cpu = _replay(rec, tmp_path / "cpu", "--set", "perception.device=cpu")
    assert _scores(cpu) == _scores(live) and cpu["device"]["asked"] == "cpu" and cpu["device"]["used"] == "cpu"
    if not torch.cuda.is_available():
        r = _cli("evaluate", str(rec), "--out", str(tmp_path / "cuda"), "--set", "perception.device=cuda")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "perception.device: 'cuda' asked" in lines[0], r.stderr


def test_the_same_on_a_shared_tr37885_medium_with_compensation(tmp_path: Path) -> None:
    live = _record(tmp_path / "live", "--set", "comm.medium=shared", "--set", "comm.channel.model=tr37885",
                   "--set", "comm.compensation=true")
    _same_as_live(tmp_path / "live", live, tmp_path / "replay")


def test_evaluate_changes_receiver_side_keys_and_refuses_sender_side_ones(per_link: tuple[Path, dict],
                                                                         tmp_path: Path) -> None:
    rec, live = per_link
    # a receiver-side change: a clean channel, fewer methods, no re-simulation
    clean = _replay(rec, tmp_path / "clean", "--methods", "none,cobevt", "--set", "comm.drop.p=0")
    assert set(clean["methods"]) == {"none", "cobevt"} and clean["comm"]["dropped"] == 0
    assert clean["comm"]["delivered"] > live["comm"]["delivered"]
    assert clean["methods"]["none"] == {**live["methods"]["none"], "fusion_ms": clean["methods"]["none"]["fusion_ms"]}
    for args, key in ((["--set", "cavs.count=2"], "cavs.count"), (["--set", "seed=7"], "seed"),
                      (["--set", "perception.preset=paper"], "perception.preset"),
                      (["--set", "perception.precision=bf16"], "perception.precision"),
                      (["--set", "comm.channel_compression=8"], "comm.channel_compression")):
        r = _cli("evaluate", str(rec), "--out", str(tmp_path / "bad"), *args)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"v2vsim: error: {key}:") and "sender-side" in lines[0]
    # a closed-loop key (issue 46): its vehicles drove on what was perceived, so no replay can stand for it
    r = _cli("evaluate", str(rec), "--out", str(tmp_path / "bad"), "--set", "control.method=cobevt")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("v2vsim: error: control:"), r.stderr
    r = _cli("evaluate", str(rec), "--out", str(tmp_path / "bad"), "--methods", "none,early")
    assert r.returncode == 2 and "perception.methods" in r.stderr and "points" in r.stderr
    r = _cli("evaluate", str(tmp_path / "nothing"), "--out", str(tmp_path / "bad"))
    assert r.returncode == 2 and "no recording" in r.stderr
    r = _cli("evaluate", str(rec), "--out", str(rec))
    assert r.returncode == 2 and "overwritten" in r.stderr


def test_points_replayed_in_one_pass_score_as_each_replayed_alone(per_link: tuple[Path, dict],
                                                                   tmp_path: Path) -> None:
    """evaluate --grid: one ego thread per point over one reading of the recording, sharing decodes and equal
    fusions; each point's scores and comm counts are those of its own replay (and the recorded point's, the
    live run's)."""
    rec, live = per_link
    out = tmp_path / "grid"
    r = _cli("evaluate", str(rec), "--grid", "comm.drop.p=0.3,0", "--grid", "comm.latency_ms.mean=20,120",
             "--out", str(out))
    assert r.returncode == 0, r.stderr[-3000:]
    assert "4 points replayed in one pass" in r.stderr
    shared = r.stderr.split("computed once and shared: ")[1].splitlines()[0]  # "N of M decodes, ..., K of L worlds"
    counts = {part.split(" ", 3)[3]: (int(part.split()[0]), int(part.split()[2])) for part in shared.split(", ")}
    assert counts["worlds"] == (3 * 6, 4 * 6) and counts["ground truths"] == (3 * 6, 4 * 6)
    assert 0 < counts["predictions"][0] < counts["predictions"][1]
    got = {p.name: json.loads((p / "metrics.json").read_text()) for p in out.iterdir()}
    assert sorted(got) == sorted(f"comm.drop.p={d}_comm.latency_ms.mean={m}" for d in ("0.3", "0")
                                 for m in ("20", "120"))
    assert _scores(got["comm.drop.p=0.3_comm.latency_ms.mean=20"]) == _scores(live)  # the recorded settings
    alone = _replay(rec, tmp_path / "alone", "--set", "comm.drop.p=0", "--set", "comm.latency_ms.mean=120")
    assert _scores(got["comm.drop.p=0_comm.latency_ms.mean=120"]) == _scores(alone)
    assert _scores(alone) != _scores(live)
    # a bad point is refused before any runs, naming its folder
    r = _cli("evaluate", str(rec), "--grid", "comm.drop.p=0,0.5", "--grid", "cavs.count=2", "--out",
             str(tmp_path / "bad"))
    assert r.returncode == 2 and "comm.drop.p=0_cavs.count=2: cavs.count" in r.stderr and "sender-side" in r.stderr
    assert not (tmp_path / "bad").exists()


def test_a_recording_moved_where_its_scenario_is_gone_still_replays(per_link: tuple[Path, dict],
                                                                     tmp_path: Path) -> None:
    """Another machine: the recorded scenario path does not exist. evaluate reads the recording's copies of the
    scenario and of the road network and buildings it names (files/, checked by sha256)."""
    import shutil

    rec, live = per_link
    header = json.loads((rec / "messages" / "header.json").read_text())
    files = header["scenario"]["files"]
    assert set(files) == {"traffic.net", "traffic.buildings"}
    for f in files.values():
        assert (rec / "messages" / "files" / f["name"]).is_file() and len(f["sha256"]) == 64
    moved = tmp_path / "elsewhere" / "messages"
    shutil.copytree(rec / "messages", moved)
    header["scenario"]["source"] = str(tmp_path / "gone" / "intersection.yaml")
    (moved / "header.json").write_text(json.dumps(header))
    assert _scores(_replay(moved, tmp_path / "replay")) == _scores(live)
    # a network that is not the recorded one is still a sender-side change
    (moved / "files" / files["traffic.net"]["name"]).write_text("<net/>")
    r = _cli("evaluate", str(moved), "--out", str(tmp_path / "bad"))
    assert r.returncode == 2 and "traffic.net" in r.stderr, r.stderr


def test_record_messages_is_refused_in_realtime(tmp_path: Path) -> None:
    r = _cli("run", SCENARIO, "--frames", "2", "--out", str(tmp_path), "--set", "output.record_messages=true",
             "--set", "transport.clock=realtime")
    assert r.returncode == 2 and "output.record_messages" in r.stderr and "lockstep" in r.stderr


def test_a_cav_killed_mid_run_is_lost_at_the_same_frame_in_the_replay(tmp_path: Path) -> None:
    """A CAV killed mid-run (SIGKILL) is noticed, the run finishes every frame without it, and the replay loses
    it at the same frame (this run also stands for the live-only kill test it replaced)."""
    from tests.agents.test_run import Run

    out = tmp_path / "live"
    run = Run("--frames", "30", "--out", str(out), "--set", "cavs.count=3", "--set", "comm.range_m=300",
              "--methods", "none,cobevt", "--set", "output.rerun=false", "--set", "output.record_messages=true")
    run.wait_frames(10)
    victims = [p for p in run.children() if "agents.cav" in " ".join(p.cmdline()) and "cav2" in p.cmdline()]
    assert len(victims) == 1
    victims[0].send_signal(signal.SIGKILL)
    assert run.finish() == 0, "".join(run.log)  # degraded, not failed: every file is written
    live = json.loads((out / "metrics.json").read_text())
    # issue 45: it said "complete"; a run that lost an agent is degraded, and says from which frame
    assert list(live["lost_agents"]) == ["cav2"]
    assert live["status"] == f"degraded: cav2 lost from frame {live['lost_agents']['cav2']}", live["status"]
    assert run.log[-1].startswith(f"v2vsim: done, not complete: {live['status']}; report: ")
    assert live["frames"] == 30 and 10 <= live["lost_agents"]["cav2"] < 30
    assert "cav2" in live["comm"]["lost_agents"]
    assert live["methods"]["cobevt"]["frames"] == 30
    recording = Recording(out)
    assert recording.header["lost_agents"] == live["lost_agents"] and recording.header["status"] == live["status"]
    assert recording.complete  # every frame recorded: replayed whole, not as a killed run's
    r = _cli("evaluate", str(out), "--out", str(tmp_path / "replay"))
    assert r.returncode == 0 and "never finished" not in r.stderr, r.stderr[-3000:]
    assert f"not complete: {live['status']}" in r.stderr, r.stderr[-3000:]
    replay = json.loads((tmp_path / "replay" / "metrics.json").read_text())
    assert _scores(replay) == _scores(live)  # the same status and lost agents, bit for bit
