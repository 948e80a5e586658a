"""How a run ended, as the runner reads and writes it: each ego's metrics.json status (for the terminal's last
line) and, when a run failed before an ego wrote its results, the runner's own metrics.json saying why."""

from __future__ import annotations

import json
from pathlib import Path

from v2vsim.config import Scenario


def ego_folder(out: Path, egos: list[str] | tuple[str, ...], ego: str) -> Path:
    """Where an ego writes its metrics.json: the run's folder for the first ego, ego_<id>/ for the others."""
    return out if ego == egos[0] else out / f"ego_{ego}"


def write_failure_metrics(out: Path, sc: Scenario, egos: list[str], failures: list[str]) -> None:
    """A run that failed before an ego wrote its results (the ego killed, a crash before it started) still
    leaves metrics.json, with the contract's keys empty and `status` saying what happened, so that a sweep or
    a script reading the folder sees why instead of nothing."""
    why = "; ".join(failures) or "the run failed"
    for e in egos:
        folder = ego_folder(out, egos, e)
        if (folder / "metrics.json").exists():
            continue
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "metrics.json").write_text(json.dumps({
            "scenario": sc.name, "seed": sc.seed, "overrides": list(sc.overrides), "frames": 0,
            "cavs": sc.cavs.count, "modality": sc.perception.modality, "real_time_factor": None, "comm": {},
            "methods": {}, "ego": e, "status": f"failed: {why} (no results; written by the runner)",
            "encoder": sc.perception.encoder, "preset": sc.perception.preset}, indent=2))


def ego_statuses(out: Path, egos: list[str]) -> dict[str, str]:
    """Each ego's metrics.json status (v2vsim.evaluation.status), for the runner's last line."""
    got = {}
    for e in egos:
        try:
            got[e] = str(json.loads((ego_folder(out, egos, e) / "metrics.json").read_text())
                         .get("status", "no status in metrics.json"))
        except (OSError, ValueError, AttributeError):
            got[e] = "no readable metrics.json"
    return got
