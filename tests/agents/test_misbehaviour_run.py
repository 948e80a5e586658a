"""A lying CAV in a real run (issue 55 item 1): `misbehaviour` needs no modified agent; the liar's messages carry the
lie (an all-zero map leaves CoBEVT where the ego alone is and changes it from the clean run), and the run says it was
attacked on the terminal, in metrics.json and in the report."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TJ = str(REPO / "scenarios" / "t_junction.yaml")
ARGS = ("--frames", "6", "--set", "seed=1", "--set", "cavs.count=2", "--set", "perception.methods=[none,cobevt]",
        "--set", "output.rerun=false")


def _run(out: Path, *sets: str) -> tuple[dict, str, str]:
    r = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", TJ, "--out", str(out), *ARGS,
                        *(x for s in sets for x in ("--set", s))],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((out / "metrics.json").read_text()), (out / "report.md").read_text(), r.stderr


def test_a_lying_cav_changes_the_fusion_and_the_run_says_it_was_attacked(tmp_path: Path) -> None:
    clean, clean_report, clean_err = _run(tmp_path / "clean")
    lied, report, err = _run(tmp_path / "lied", "misbehaviour=[{cavs: [cav1], kind: zero, from_frame: 0}]")
    assert "ATTACKED RUN (misbehaviour): cav1: zero (all-zero features and outputs) from frame 0" in err
    assert "v2vsim-cav cav1: lied on purpose (misbehaviour): zero in 6 frames" in err.replace("[cav.cav1] ", "")
    assert lied["misbehaviour"][0]["kind"] == "zero" and lied["misbehaviour"][0]["cavs"] == ["cav1"]
    assert "**Attacked run** (`misbehaviour`): cav1: zero" in report
    assert "misbehaviour" not in clean and "Attacked run" not in clean_report and "ATTACKED" not in clean_err
    # its messages still arrive, signed by its genuine identity: nothing is rejected
    assert lied["comm"]["delivered"] == clean["comm"]["delivered"] > 0 and lied["comm"]["rejected"] == 0
    assert lied["methods"]["none"]["iou_vehicle"] == clean["methods"]["none"]["iou_vehicle"]  # the ego's own map
    assert lied["methods"]["cobevt"]["iou_vehicle"] != clean["methods"]["cobevt"]["iou_vehicle"]
