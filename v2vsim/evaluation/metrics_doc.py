"""metrics.json (DESIGN.md contract): the document `metrics_json` builds from a run's summary, scores and
communication statistics, with its blocks (each method's difference to no fusion, a mixed fleet's agent types,
the shared medium's busy ratio per method)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from v2vsim.comm.stats import CommStats
from v2vsim.comm.wire_spec import message_kind
from v2vsim.evaluation.block_bootstrap import LEVEL, REPLICATES, paired_difference
from v2vsim.evaluation.metrics import MethodScore, neighbour_shares, paired_counts
from v2vsim.evaluation.run_summary import RunSummary
from v2vsim.perception.precision import resolve as resolve_precision
from v2vsim.traffic.penetration import connected_cavs

BASELINE = "none"  # no fusion: what every other method's difference is taken against
VS_NONE = {"iou_vehicle": "vehicle", "iou_road": "road", "iou_lane": "lane"}  # metrics.json key -> accumulator


def metrics_json(summary: RunSummary, scores: dict[str, MethodScore], comm: CommStats,
                 comm_by_kind: dict[str, CommStats], iou_fn: Callable | None) -> dict:
    sc = summary.scenario
    sim_s = summary.sim_s or summary.frames / sc.rate_hz
    comm_doc = comm.to_json()
    connected = connected_cavs(sc)  # every placed vehicle, unless cavs.penetration left some unconnected
    comm_doc["by_kind"] = {k: s.to_json() for k, s in comm_by_kind.items() if k != "features"}
    return {
        "scenario": sc.name,
        "seed": sc.seed,
        "overrides": list(sc.overrides),  # --set as given: the run again is `v2vsim run SOURCE --set ...`
        "frames": summary.frames,
        "cavs": sc.cavs.count,
        "modality": sc.perception.modality,
        "real_time_factor": round(sim_s / summary.wall_s, 3) if summary.wall_s > 0 else None,
        "comm": comm_doc,
        "methods": {m: {**scores[m].to_json(iou_fn), **_method_cbr(m, comm, comm_by_kind),
                        **({} if m == BASELINE else {"vs_none": vs_none(scores[m], scores.get(BASELINE))})}
                    for m in summary.methods if m in scores},
        "ego": summary.ego,
        "status": summary.status,
        "lost_agents": summary.lost_agents,
        "encoder": sc.perception.encoder,
        "preset": sc.perception.preset,
        "grid": {"cells": summary.grid_cells, "cell_m": round(sc.bev.size_m / summary.grid_cells, 3)
                 if summary.grid_cells else None, "channels": summary.channels, "wire_ratio": summary.wire_ratio,
                 "wire_channels": summary.channels // summary.wire_ratio if summary.channels else None},
        "weights": "untrained (seeded random init)" if summary.untrained else sc.perception.weights,
        "checkpoints": {m: summary.checkpoints.get(m) for m in summary.methods},
        "compensation": {m: summary.compensation.get(m, "none") for m in summary.methods},
        "clock": sc.transport.clock,
        # comm.auth as it ran (docs/run.md "Trust between processes"): per_process, shared_key, or off (unsigned:
        # any process on the host or the bus could have altered the run's messages)
        "trust": sc.comm.auth.mode,
        # the models' forward passes on this host (v2vsim.perception.precision); remote CAVs resolve 'auto' on theirs
        "precision": {"asked": sc.perception.precision, "used": resolve_precision(sc.perception.precision)},
        # where the ego's models ran (v2vsim.perception.device): asked, used ("cpu" or "cuda:N"), that device's name;
        # the CAVs resolve perception.device on their own hosts
        "device": summary.device,
        "neighbours_in_range": neighbour_shares(summary.neighbours, len(connected)),
        "ap_sort": sc.evaluation.ap_sort,
        "pipeline": sc.transport.pipeline,
        "wall_s": round(summary.wall_s, 3),
        "timing": summary.timing,  # the ego's own split of a frame (ms), as `v2vsim bench run` prints it
        # closed loop only (an open-loop run's metrics.json is as before)
        **({"driving": summary.driving} if summary.driving is not None else {}),
        # misbehaviour: an attacked run says so in its metrics (v2vsim/comm/misbehaviour.py)
        **({"misbehaviour": [dataclasses.asdict(lie) for lie in sc.misbehaviour]} if sc.misbehaviour else {}),
        # the ego's misbehaviour check (defence.detect / exclude): per sender the frames compared and flagged;
        # with defence.evidence its claims against the rays and its pose against the map (`evidence`), with
        # defence.remember its reputation per frame (`reputation`)
        **({"defence": summary.defence} if summary.defence is not None else {}),
        # cavs.penetration: which placed vehicles were connected (the others drove as SUMO's, silent)
        **({"penetration": {"share": sc.cavs.penetration, "connected": connected}}
           if sc.cavs.penetration is not None else {}),
        # a mixed fleet only: each agent type's CAVs and the feature bytes the ego received from them per frame
        **({"fleet": fleet_json(summary)} if summary.fleet else {}),
    }


def fleet_json(summary: RunSummary) -> dict:
    """metrics.json `fleet`: {"cavs": {id: type}, "types": {type: {"cavs", "feature_bytes_per_frame"}}}; the bytes
    are those of the feature messages that reached this ego over the air (its own map never crossed it)."""
    frames = max(summary.frames, 1)
    types: dict[str, dict] = {}
    for cav, label in summary.fleet.items():
        t = types.setdefault(label, {"cavs": [], "feature_bytes_per_frame": 0})
        t["cavs"].append(cav)
        t["feature_bytes_per_frame"] += summary.feature_bytes.get(cav, 0)
    for t in types.values():
        t["feature_bytes_per_frame"] = round(t["feature_bytes_per_frame"] / frames)
    return {"cavs": dict(summary.fleet), "types": types}


def vs_none(score: MethodScore, base: MethodScore | None) -> dict | None:
    """A method's IoU minus no fusion's on the frames both were scored on, per metric, with a 95% circular
    moving-block bootstrap interval over frames (v2vsim.evaluation.block_bootstrap: the block length, in
    frames, is chosen per metric from the run's own autocorrelation). A metric is None where it has no
    interval (fewer than 2 frames, or an IoU without any union); the whole entry None without `none`."""
    if base is None:
        return None

    def r(v: float) -> float:
        return round(v, 4)

    out: dict = {}
    for key, attr in VS_NONE.items():
        d = paired_difference(*paired_counts(getattr(score, attr), getattr(base, attr)))
        out[key] = None if d is None else {"diff": r(d.diff), "low": r(d.low), "high": r(d.high),
                                           "excludes_zero": d.excludes_zero, "block_frames": d.block,
                                           "frames": d.frames}
    return {**out, "replicates": REPLICATES, "level": LEVEL,
            "method": "circular moving-block bootstrap over frames, percentile interval"}


def _method_cbr(method: str, comm: CommStats, comm_by_kind: dict[str, CommStats]) -> dict:
    """Under comm.medium shared: the busy ratio of the channel carrying this method's messages (a sweep
    column); {} on per-link channels, and for `none`, which sends nothing."""
    kind = message_kind(method)
    stats = comm if kind == "features" else comm_by_kind.get(kind or "")
    if stats is None or stats.medium is None:
        return {}
    cbr = stats.to_json()["cbr"]
    return {"cbr_mean": cbr["mean"], "cbr_p95": cbr["p95"]}
