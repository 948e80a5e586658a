"""`v2vsim bandwidth`: the curve's rows, table and plot from a tiny run of the env."""

from __future__ import annotations

import csv
import io
import subprocess
import sys
from pathlib import Path

import pytest

from v2vsim.env.bandwidth import bandwidth_curve, parse_fractions

REPO = Path(__file__).resolve().parents[3]
SCENARIO = str(REPO / "scenarios" / "intersection.yaml")


def test_curve_rows_bytes_grow_with_the_share_and_nothing_costs_nothing(tmp_path: Path) -> None:
    rows = bandwidth_curve(SCENARIO, [0.0, 0.1, 1.0], [3], 2, ["cobevt"], tmp_path,
                           overrides={"comm.range_m": 300, "comm.bandwidth_mbps": None}, log=io.StringIO())
    by = {(r["fraction"], r["method"]): r for r in rows}
    assert {m for _, m in by} == {"cobevt", "none"}
    assert by[(0.0, "cobevt")]["bytes_per_frame"] == 0
    assert 0 < by[(0.1, "cobevt")]["bytes_per_frame"] < by[(1.0, "cobevt")]["bytes_per_frame"]
    assert by[(1.0, "cobevt")]["bytes_per_frame"] > 3 * 8 * 64 * 64 * 2  # three neighbours, whole maps on the 8x wire
    assert by[(0.0, "cobevt")]["iou_vehicle"] == by[(0.0, "none")]["iou_vehicle"]  # nothing sent: nothing fused
    with open(tmp_path / "bandwidth.csv") as f:
        assert len(list(csv.DictReader(f))) == 6
    table = (tmp_path / "bandwidth.md").read_text()
    assert "| share | bytes / frame | cobevt | none |" in table and "| 0.1 |" in table
    assert (tmp_path / "bandwidth.png").stat().st_size > 10_000


def test_bad_fractions_and_cli_errors(tmp_path: Path) -> None:
    assert parse_fractions("1,0,0.5,0.5") == [0.0, 0.5, 1.0]
    for bad in ("", "a", "-0.1", "1.5"):
        with pytest.raises(ValueError, match="--fractions"):
            parse_fractions(bad)
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "bandwidth", SCENARIO, "--seeds", "1", "--fractions",
                        "2", "--out", str(tmp_path)], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 2 and "--fractions '2'" in r.stderr and "Traceback" not in r.stderr


def test_ctrl_c_keeps_the_finished_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from v2vsim.env.parallel import CooperativePerceptionEnv

    step = CooperativePerceptionEnv.step
    calls = {"n": 0}

    def interrupted_on_the_third(self, actions):  # noqa: ANN001, ANN202
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return step(self, actions)

    monkeypatch.setattr(CooperativePerceptionEnv, "step", interrupted_on_the_third)
    log = io.StringIO()
    with pytest.raises(KeyboardInterrupt):
        bandwidth_curve(SCENARIO, [0.0, 1.0], [3], 2, ["cobevt"], tmp_path, log=log)
    with open(tmp_path / "bandwidth.csv") as f:
        rows = list(csv.DictReader(f))
    assert {(r["fraction"], r["method"]) for r in rows} == {("0.0", "cobevt"), ("0.0", "none")}
    assert "interrupted; 1 (share, seed) runs written" in log.getvalue()
