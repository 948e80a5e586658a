"""scripts/evidence_table.py's false-alarm count: an honest sender-frame is flagged when any evidence figure passes
its threshold or the consistency check flagged it (a camera sender sends no evidence and is judged by the latter
alone); the liars' frames are not counted as false alarms."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _table():
    spec = importlib.util.spec_from_file_location("evidence_table", REPO / "scripts" / "evidence_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _ev(frame: int, phantom: float) -> list:
    # [frame, phantom, removed, unclaimed, witnessed, shift, turn, on_map, on_map_corrected, flagged, later...]
    return [frame, phantom, 0.0, 0.0, 0.0, 0.0, 0.0, 0.9, 0.9, False, None, None, None]


def test_false_alarms_count_evidence_and_consistency_flags_of_honest_senders_only(tmp_path: Path) -> None:
    t = _table()
    run = tmp_path / "clean_x"
    run.mkdir()
    doc = {"misbehaviour": [{"cavs": ["cav9"], "kind": "scale"}], "defence": {
        "senders": {"cam1": {"per_frame": [[1, 0.1, 0.0, 200.0, True], [2, 0.1, 0.0, 200.0, False]]},
                    "cav2": {"per_frame": [[1, 0.1, 0.0, 200.0, False], [3, 0.1, 0.0, 200.0, True]]},
                    "cav9": {"per_frame": [[1, 0.9, 90.0, 200.0, True]]}},
        "evidence": {"cav2": {"per_frame": [_ev(1, 0.0), _ev(2, 9.0), _ev(3, 0.0)]},
                     "cav9": {"per_frame": [_ev(1, 50.0)]}}}}
    (run / "metrics.json").write_text(json.dumps(doc))
    # cam1: 2 frames, 1 flagged (consistency); cav2: frames 1-3, frame 2 by its phantom, frame 3 by consistency
    assert t.honest_alarms(run, {"phantom_m2": 5.0}) == (5, 3)
    assert t.honest_alarms(run, {"phantom_m2": 10.0}) == (5, 2)
