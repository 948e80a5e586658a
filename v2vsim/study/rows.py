"""A sweep's data: one row per (grid point, seed, method) from each run's metrics.json, with the run's
per-frame visible-vehicle IoU: from metrics.json's `iou_vehicle_counts` (intersection, union per fused
frame, keyed by the frame indices in `iou_vehicle_frames`), or, for runs written before that key existed,
from the run's recording.rrd (`metrics/iou_vehicle/<method>` on the `frame` timeline); without either the
statistics resample seeds only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from v2vsim.evaluation.status import COMPLETE, as_configured
from v2vsim.study.grid import Point
from v2vsim.study.runs import RunResult, read_metrics

# The contract's method metrics first, in this order; any others a run reports follow, sorted.
CONTRACT_METRICS = ("iou_vehicle", "iou_vehicle_frame_mean", "iou_road", "iou_lane", "ap50", "ap70",
                    "fusion_ms", "bytes_per_frame")
COUNTS_KEY = "iou_vehicle_counts"  # per-frame lists: read into Row.per_frame, not a CSV column
FRAMES_KEY = "iou_vehicle_frames"  # the frame index of each of those counts (absent in older runs: 0, 1, ...)
# a run's own intervals against `none` (over its frames); the sweep computes its own over seeds and frames
RUN_ONLY_KEYS = ("vs_none",)
RANGE_KEY = "iou_vehicle_by_range"  # {ring: IoU}: flattened into a column per ring
IOU_ENTITY = "/metrics/iou_vehicle/"


@dataclass(frozen=True)
class Row:
    point: Point
    seed: int
    method: str
    metrics: dict[str, Any]
    run_dir: Path
    per_frame: dict[int, float] | None = None  # frame index -> this method's visible-vehicle IoU
    status: str = COMPLETE  # the run's metrics.json status: complete, or degraded: ... (sweep.csv's last column)


def per_frame_vehicle_iou(rrd: Path) -> dict[str, dict[int, float]]:
    """Per method, frame index -> visible-vehicle IoU, as the run logged it to its recording; {} when the
    recording cannot be read (then the run counts without per-frame values)."""
    try:
        from rerun.chunk import RrdReader

        chunks = RrdReader(str(rrd)).store().stream().filter(content=f"{IOU_ENTITY}**", is_static=False).to_chunks()
    except Exception:  # noqa: BLE001 - a truncated or foreign recording: fall back to seed-level statistics
        return {}
    out: dict[str, dict[int, float]] = {}
    for c in chunks:
        method = str(c.entity_path).removeprefix(IOU_ENTITY)
        rb = c.to_record_batch()
        if "frame" not in rb.schema.names or "Scalars:scalars" not in rb.schema.names:
            continue
        for f, v in zip(rb.column("frame").to_pylist(), rb.column("Scalars:scalars").to_pylist(), strict=True):
            if f is not None and v:
                out.setdefault(method, {})[int(f)] = float(v[0])
    return out


def driving_columns(driving: dict[str, Any] | None) -> dict[str, Any]:
    """A closed-loop run's driving totals as sweep columns (`driving_collisions`, ...), the same on each of its
    method rows: one method drove (control.method, its own column of the grid); {} for an open-loop run."""
    if not driving:
        return {}
    out: dict[str, Any] = {"driving_method": driving.get("method")}
    for k, v in (driving.get("total") or {}).items():
        if isinstance(v, dict):  # infraction counts by kind: a column each (driving_infractions_timeout, ...)
            out |= {f"driving_{k}_{kind}": n for kind, n in v.items()}
        else:
            out[f"driving_{k}"] = int(v) if isinstance(v, bool) else v
    return out


def collect(results: Sequence[RunResult]) -> list[Row]:
    """Rows of every run that went through its frames (complete or degraded), in plan order (point, seed),
    methods in the run's order."""
    rows = []
    for r in results:
        if not r.ok:
            continue
        doc = read_metrics(r.spec.out)
        if doc is None:
            continue
        rrd = r.spec.out / "recording.rrd"
        methods = doc.get("methods") or {}
        logged = None
        status = str(doc.get("status", r.status))
        driving = driving_columns(doc.get("driving"))
        for method, metrics in methods.items():
            metrics = {**dict(metrics), **driving}
            counts = metrics.pop(COUNTS_KEY, None)
            frames = metrics.pop(FRAMES_KEY, None)
            for key in RUN_ONLY_KEYS:
                metrics.pop(key, None)
            # the per-ring IoU (v2vsim.evaluation.metrics.RANGE_RINGS) as one column per ring: iou_vehicle_range_0-20
            metrics |= {f"iou_vehicle_range_{ring}": v for ring, v in (metrics.pop(RANGE_KEY, None) or {}).items()}
            if counts is not None:
                keys = frames if frames is not None else range(len(counts))
                per_frame = {int(k): i / u for k, (i, u) in zip(keys, counts, strict=True) if u}
            else:
                logged = logged if logged is not None else per_frame_vehicle_iou(rrd) if rrd.is_file() else {}
                per_frame = logged.get(method)
            rows.append(Row(r.spec.point, r.spec.seed, method, metrics, r.spec.out, per_frame, status))
    return rows


def counted(rows: Sequence[Row], include_degraded: bool = False) -> list[Row]:
    """The rows a study's statistics take: runs that went as configured (complete, or flagged senders only:
    v2vsim.evaluation.status.as_configured), unless `include_degraded` (a degraded run's scores are not those of
    the configured run: its lost agents sent nothing from a frame on)."""
    return [r for r in rows if include_degraded or as_configured(r.status)]


def metric_columns(rows: Sequence[Row]) -> list[str]:
    extra = sorted({k for r in rows for k in r.metrics} - set(CONTRACT_METRICS))
    return [*CONTRACT_METRICS, *extra]


def methods_of(rows: Sequence[Row]) -> list[str]:
    """Methods in the order runs report them (the scenario's order)."""
    seen: dict[str, None] = {}
    for r in rows:
        seen.setdefault(r.method)
    return list(seen)
