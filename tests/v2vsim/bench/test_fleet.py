"""v2vsim bench fleet: the figures of one run read from its metrics.json and timing files, the resumable grid,
and bad arguments refused (the runs themselves are real `v2vsim run`s, measured by hand, not in tests)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from v2vsim.bench import fleet
from v2vsim.bench.run import read_run


def _run_dir(out: Path, frames: int = 10, status: str = "complete") -> Path:
    (out / "timing").mkdir(parents=True)
    metrics = {"frames": frames, "status": status, "real_time_factor": 0.25, "wall_s": 4.0,
               "neighbours_in_range": {"0": 0.5, "1": 0.25, "3": 0.25},
               "timing": {"ms_per_frame": {"fusion.none": 1.0, "fusion.cobevt": 60.0, "decoding.none": 10.0,
                                           "decoding.cobevt": 11.0, "wait": 300.0},
                          "compute_ms_per_frame": 82.0, "cpu_ms_per_frame": 90.0}}
    (out / "metrics.json").write_text(json.dumps(metrics))
    for name, cpu in (("cav.cav0", 100.0), ("cav.cav1", 120.0), ("driver", 5.0)):
        (out / "timing" / f"{name}.json").write_text(json.dumps({"cpu_ms_per_frame": cpu, "ms_per_frame": {}}))
    return out


def test_row_sums_every_process_cpu_and_splits_the_ego(tmp_path: Path) -> None:
    out = _run_dir(tmp_path / "run")
    row = fleet.fleet_row(2, "none,cobevt", read_run(out))
    assert row["cpu_ms_per_frame"] == 90 + 100 + 120 + 5
    assert row["cav_cpu_ms_mean"] == 110 and row["ego_cpu_ms"] == 90
    assert row["ego_fusion_ms"] == 61 and row["ego_decoding_ms"] == 21
    assert row["wall_ms_per_frame"] == 400 and row["neighbours_mean"] == 1.0  # 0.25 x 1 + 0.25 x 3


def test_a_complete_run_is_read_not_run_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = _run_dir(tmp_path / "none+cobevt_n2")
    monkeypatch.setattr(fleet, "run_command", lambda *a, **k: pytest.fail("ran again"))
    res = fleet.run_point("intersection", 2, "none,cobevt", 10, [], out)
    assert res["metrics"]["frames"] == 10 and "cav.cav0" in res["timing"]


@pytest.mark.parametrize("status,frames", [("interrupted after 3 frames", 10), ("complete", 20)])
def test_an_incomplete_or_shorter_run_is_run_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, status: str,
                                                   frames: int) -> None:
    out = _run_dir(tmp_path / "all_n2", frames=10, status=status)
    called = []
    monkeypatch.setattr(fleet, "run_command", lambda scenario, n, extra, o: called.append(extra) or {})
    fleet.run_point("intersection", 2, fleet.ALL, frames, ["seed=3"], out)
    assert called == [["--set", "cavs.count=2", "--set", "output.rerun=false", "--set", "seed=3"]]


@pytest.mark.parametrize("cavs", ["2,x", "0,4"])
def test_bad_fleet_sizes_are_refused(cavs: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as e:
        fleet.main(["--cavs", cavs, "--out", str(tmp_path)])
    assert e.value.code == 2 and f"--cavs {cavs!r}" in capsys.readouterr().err
