"""perception.device end to end: a device this host lacks stops `v2vsim run` before any process starts, and auto
runs on the CPU where torch sees no GPU, as metrics.json and report.md say."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(torch.cuda.is_available(), reason="checks a host without CUDA")


def _run(out: Path, *sets: str) -> subprocess.CompletedProcess:
    args = ["run", "intersection", "--frames", "3", "--out", str(out), "--set", "output.rerun=false"]
    return subprocess.run([sys.executable, "-m", "v2vsim.cli", *args, *(x for s in sets for x in ("--set", s))],
                          capture_output=True, text=True, cwd=REPO, timeout=300)


def test_cuda_on_a_host_without_it_is_one_line_and_exit_2_before_anything_starts(tmp_path: Path) -> None:
    r = _run(tmp_path / "run", "perception.device=cuda")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("v2vsim: error: ") and "perception.device: 'cuda' asked" in lines[0], lines[0]
    out = tmp_path / "run"
    assert not out.exists() or not any(out.iterdir())  # no process started, nothing written


def test_auto_runs_on_the_cpu_and_says_so(tmp_path: Path) -> None:
    r = _run(tmp_path / "run", "perception.device=auto")
    assert r.returncode == 0, r.stderr
    m = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert m["status"] == "complete" and m["frames"] == 3
    assert m["device"]["asked"] == "auto" and m["device"]["used"] == "cpu" and m["device"]["name"]
    assert "auto ran on the CPU" in (tmp_path / "run" / "report.md").read_text()
