"""scripts/gpu_compare.py: two runs' metrics.json side by side, failing when a method's vehicle IoU moved by more
than the tolerance (scripts/gpu_check.sh's verdict)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "gpu_compare.py"


def _script():
    spec = importlib.util.spec_from_file_location("gpu_compare", SCRIPT)
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def _run(folder: Path, device: str, rtf: float, ious: dict[str, float]) -> Path:
    folder.mkdir()
    doc = {"frames": 40, "status": "complete", "real_time_factor": rtf,
           "device": {"asked": device, "used": "cuda:0" if device == "cuda" else "cpu", "name": "X"},
           "methods": {m: {"iou_vehicle": v, "ap50": 0.8, "ap70": 0.6} for m, v in ious.items()}}
    (folder / "metrics.json").write_text(json.dumps(doc))
    return folder


def test_within_the_tolerance_passes_and_beyond_it_fails_naming_the_method(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture) -> None:
    gpu_compare = _script()
    cpu = _run(tmp_path / "cpu", "cpu", 0.4, {"none": 0.700, "cobevt": 0.800})
    close = _run(tmp_path / "close", "cuda", 2.5, {"none": 0.705, "cobevt": 0.7915})
    far = _run(tmp_path / "far", "cuda", 2.5, {"none": 0.700, "cobevt": 0.780})
    assert gpu_compare.main([str(cpu), str(close)]) == 0
    out = capsys.readouterr()
    assert "real-time factor 0.4" in out.out and "real-time factor 2.5" in out.out and "cuda:0" in out.out
    assert "| cobevt | 0.8000 | 0.7915 | -0.0085 | 0.0000 | 0.0000 |" in out.out and not out.err
    assert gpu_compare.main([str(cpu), str(far)]) == 1
    err = capsys.readouterr().err
    assert "cobevt" in err and "none" not in err
    assert gpu_compare.main([str(cpu), str(far), "--tol", "0.03"]) == 0  # the tolerance is the caller's


def test_a_method_in_one_run_only_fails_and_one_run_alone_is_printed(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    gpu_compare = _script()
    cpu = _run(tmp_path / "cpu", "cpu", 0.4, {"none": 0.7, "late": 0.72})
    gpu = _run(tmp_path / "gpu", "cuda", 2.5, {"none": 0.7})
    assert gpu_compare.main([str(cpu), str(gpu)]) == 1
    assert "late: scored on the cpu only" in capsys.readouterr().err
    assert gpu_compare.main([str(cpu)]) == 0
    assert "| late | 0.7200 | 0.8000 | 0.6000 |" in capsys.readouterr().out
