"""What a run leaves behind: `write_outputs` writes metrics.json (metrics_doc), report.md (report_md) and the PNG
plots (run_plots) from the ego's `RunSummary` (run_summary) and scores."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from v2vsim.comm.stats import CommStats
from v2vsim.evaluation.metrics import MethodScore
from v2vsim.evaluation.metrics_doc import metrics_json
from v2vsim.evaluation.report_md import report_md
from v2vsim.evaluation.run_plots import plot
from v2vsim.evaluation.run_summary import RunSummary


def write_outputs(out: Path, summary: RunSummary, scores: dict[str, MethodScore], comm: CommStats,
                  comm_by_kind: dict[str, CommStats], iou_fn: Callable | None) -> dict:
    """Write metrics.json, report.md and plots into `out`; returns the metrics document."""
    out.mkdir(parents=True, exist_ok=True)
    doc = metrics_json(summary, scores, comm, comm_by_kind, iou_fn)
    (out / "metrics.json").write_text(json.dumps(doc, indent=2))
    (out / "report.md").write_text(report_md(doc, summary))
    if doc["methods"]:
        plot(out, doc, scores, summary.scenario.comm.channel)
    return doc
