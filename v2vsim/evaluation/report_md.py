"""report.md: `report_md` writes a run's report from its metrics.json document and summary, section by section
(status and provenance, the methods' table, each method against no fusion, a mixed fleet, the closed loop's
driving, communication, radio and shared medium, CAVs in range, the CoBEVT paper's figures beside the run)."""

from __future__ import annotations

from models.registry import BUILTIN_METHODS, paper_figures
from v2vsim.comm.misbehaviour import describe
from v2vsim.evaluation.metrics_doc import BASELINE, VS_NONE
from v2vsim.evaluation.run_plots import distance_bins
from v2vsim.evaluation.run_summary import RunSummary
from v2vsim.evaluation.status import explain
from v2vsim.perception.device import device_line

# report.md's line on comm.auth (docs/run.md, "Trust between processes")
TRUST_LINES = {
    "per_process": "Trust: every message signed by the process it names (comm.auth.identity per_process).",
    "shared_key": "Trust: every message signed with the shared run key, bound to this run instance "
                  "(comm.auth.key_file): a holder of the key file could have signed as any process.",
    "off": "Trust: **off** (comm.auth.identity off): nothing was signed; any process on this host or on the zenoh "
           "bus could have altered this run's messages.",
}


def fleet_md(doc: dict, summary: RunSummary) -> list[str]:
    """The report's fleet section (a mixed fleet only)."""
    fleet = doc.get("fleet")
    if not fleet:
        return []
    lines = ["", "## Fleet (cavs.fleet)", "",
             f"Every feature message names its encoder and feature space; {summary.ego} fuses those of its zoo's "
             "space, into which each other type's encoder was aligned (the `align` stage; docs/training.md).", "",
             "| agent type | CAVs | feature bytes / frame received by the ego |", "|---|---|---|"]
    for label, t in fleet["types"].items():
        cavs = ", ".join(f"**{c}** (ego)" if c == summary.ego else c for c in t["cavs"])
        lines.append(f"| {label} | {cavs} | {t['feature_bytes_per_frame']} |")
    return lines


def driving_md(d: dict | None) -> list[str]:
    """The report's closed-loop section: which method drove, and what came of it per driven vehicle."""
    if d is None:
        return []

    def f(v: object, unit: str = "") -> str:
        return "-" if v is None else (f"{v:.2f}{unit}" if isinstance(v, float) else f"{v}{unit}")

    lines = ["", "## Driving (closed loop)", "",
             (f"The driven vehicles ({', '.join(d['driven'])}) each planned on **{d['method']}** on what it perceived "
              "and received" if len(d.get("driven", ())) > 1 else f"The driven vehicle planned on **{d['method']}**")
             + f" ({d['planner']} planner); the other methods above were "
             f"scored open loop on the same frames. A plan made on frame k's perception was applied after frame "
             f"k + {d['actuation_delay_frames']} ({d['actuation_delay_ms']:g} ms later). Background drivers ignore a "
             f"vehicle already in the junction with probability {d['background_ignore_junction_foes']:g}. SSM "
             f"thresholds: TTC {d['ssm_thresholds']['ttc_s']:g} s, DRAC {d['ssm_thresholds']['drac_mps2']:g} m/s², "
             f"PET {d['ssm_thresholds']['pet_s']:g} s.", "",
             "| vehicle | collisions | near miss | min gap m | SSM min TTC s | SSM max DRAC | SSM min PET s "
             "| PET s (trajectories) | hard braking | phantom braking | time to clear s | progress m |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for v, m in d["vehicles"].items():
        if not m.get("frames"):
            lines.append(f"| {v} | not driven |" + " |" * 10)
            continue
        ssm = m["ssm"]
        lines.append(f"| {v} | {m['collisions']}" + (f" ({', '.join(m['collided_with'])}, first at frame "
                                                      f"{m['first_collision_frame']})" if m["collisions"] else "")
                     + f" | {'yes' if m['near_miss'] else 'no'} | {f(m['min_gap_m'])} | {f(ssm['min_ttc_s'])} | "
                     f"{f(ssm['max_drac_mps2'])} | {f(ssm['min_pet_s'])} | {f(m['pet_s'])} | {m['hard_braking']} | "
                     f"{m['phantom_braking']} | {f(m['time_to_clear_s'])} | {f(m['progress_m'])} |")
    scored = [(v, m) for v, m in d["vehicles"].items() if m.get("frames") and "driving_score" in m]
    if scored:
        pen = d.get("penalties", {})
        lines += ["", "Driving score (the CARLA leaderboard's: route completion x "
                  + " x ".join(f"{p:g} per {k.replace('_', ' ')}" for k, p in pen.items())
                  + f"; route {f(d.get('route_m'), ' m') if d.get('route_m') else 'to the end of its SUMO route'}, "
                  "time limit the run's duration). Safety-weighted: x 0.775 for a close call (no collision, yet "
                  "SSM's min TTC under 1.5 s, a PET under 1 s or the gap near miss; v2vsim/control/score.py):", "",
                  "| vehicle | driving score | route completion | success | completed at s | infractions | "
                  "close call | safety-weighted score | peak jerk m/s³ |", "|---|---|---|---|---|---|---|---|---|"]
        for v, m in scored:
            inf = ", ".join(f"{k.replace('_', ' ')} {n}" for k, n in m["infractions"].items() if n) or "none"
            close = "-" if "close_call" not in m else ("yes" if m["close_call"] else "no")
            lines.append(f"| {v} | {f(m['driving_score'])} | {f(m['route_completion'])} | "
                         f"{'yes' if m['success'] else 'no'} | {f(m['finished_at_s'])} | {inf} | {close} | "
                         f"{f(m.get('safety_score'))} | {f(m.get('peak_jerk_mps3'))} |")
    crit = [(v, m) for v, m in d["vehicles"].items() if m.get("critical_actor")]
    if crit:
        lines += ["", f"The critical actor ({crit[0][1]['critical_actor']}) on the map each vehicle drove on: detected "
                  "when a track of its planner lies within 2 m of it; lead time before the conflict (first contact, "
                  "else closest approach); the track's error up to the frame it entered the junction "
                  "(v2vsim/control/critical.py):", "",
                  "| vehicle | first detected (frame) | conflict (frame) | lead time s | held | position error m | "
                  "speed error m/s |", "|---|---|---|---|---|---|---|"]
        for v, m in crit:
            first = "missed" if m["critical_missed"] else m["critical_first_detected_frame"]
            lines.append(f"| {v} | {first} | {m['critical_conflict_frame']} | {f(m['critical_lead_time_s'])} | "
                         f"{f(m['critical_detected_share'])} | {f(m['critical_position_error_m'])} | "
                         f"{f(m['critical_speed_error_mps'])} |")
    lines += ["", "Definitions: docs/scenario.md \"control\" (SUMO's SSM treats conflict areas as orthogonal lanes "
              "and ignores lateral conflicts; the trajectory PET is measured beside it); the score: "
              "v2vsim/control/score.py."]
    return lines


def _fmt(v: float | int | None, pct: bool = False) -> str:
    if v is None:
        return "-"
    if isinstance(v, int):
        return str(v)
    return f"{100 * v:.1f}" if pct else f"{v:.3f}"


def defence_line(d: dict) -> str:
    """report.md's sentence on the misbehaviour check (metrics.json `defence`)."""
    what = "fused without a sender in the frames it was flagged" if d["exclude"] else "detection only"
    per = ", ".join(f"{s} flagged in {v['frames_flagged']} of {v['frames_compared']} frames compared"
                    for s, v in d["senders"].items()) or "no sender shared enough cells to be compared"
    line = (f"**Misbehaviour check** (`defence`, {what}; thresholds road {d['road_threshold']:g}, vehicle "
            f"{d['vehicle_threshold_m2']:g} m^2 within {d['near_m']:g} m): {per}.")
    if (ev := d.get("evidence")) is not None:  # defence.evidence: the rays and the map (issue 67)
        line += (" Against the agents' rays and the map (largest phantom / removed / unclaimed area, frames "
                 "flagged by them): " + (", ".join(
                     f"{s} {v['max_phantom_m2']:g} / {v['max_removed_m2']:g} / {v['max_unclaimed_m2']:g} m^2, "
                     f"{sum(1 for r in v['per_frame'] if r[9])} of {v['frames']}" for s, v in ev.items())
                     or "no sender's evidence arrived") + ".")
    if (rep := d.get("reputation")) is not None:
        line += (" Reputation (`defence.remember`): " + (", ".join(
            f"{s} untrusted in {v['frames_untrusted']} frames (lowest {v['min']:.2f})"
            for s, v in rep["senders"].items()) or "no sender") + ".")
    return line


def report_md(doc: dict, summary: RunSummary) -> str:
    sc = summary.scenario
    lines = [f"# v2vsim run: {sc.name}", ""]
    pen = doc.get("penetration")
    cavs = (f"{len(pen['connected'])} of {sc.cavs.count} placed vehicles connected (penetration {pen['share']:g}: "
            f"{', '.join(pen['connected'])})" if pen else f"{sc.cavs.count} CAVs")
    lines.append(f"Status: **{doc['status']}**, {doc['frames']} frames at {sc.rate_hz:g} Hz, {cavs}, "
                 f"ego {summary.ego}, {sc.perception.modality} / {sc.perception.encoder} ({sc.perception.preset}), "
                 f"clock {sc.transport.clock}, real-time factor {doc['real_time_factor']}.")
    lines += ["", f"**{why}**", ""] if (why := explain(doc["status"])) else [""]
    if sc.misbehaviour:  # nobody should mistake an attacked run for a clean one
        lines += ["**Attacked run** (`misbehaviour`): " + "; ".join(describe(lie) for lie in sc.misbehaviour)
                  + ". The scores below are under attack.", ""]
    if (d := doc.get("defence")) is not None:
        lines += [defence_line(d), ""]
    lines += [TRUST_LINES[sc.comm.auth.mode], ""]
    if summary.device is not None:
        lines += [device_line(summary.device), ""]
    lines.append(f"Scenario `{sc.source}`, seed {sc.seed}" + (
        ", overrides: " + " ".join(f"`--set {o}`" for o in sc.overrides) if sc.overrides else ", no overrides") + ".")
    if summary.grid_cells:
        cell = sc.bev.size_m / summary.grid_cells
        by = "an untrained (seeded random) compressor" if summary.untrained else "the zoo's trained compressor"
        wire = (f"compressed {summary.wire_ratio}x to {summary.channels // summary.wire_ratio} channels by {by}"
                if summary.wire_ratio > 1 else "uncompressed")
        lines += ["", f"Feature messages: {summary.channels} x {summary.grid_cells} x {summary.grid_cells} "
                  f"({cell:.2f} m cells), {wire}, float16."]
    if summary.untrained:
        lines += ["", "**Weights are untrained** (no checkpoint for this encoder/preset; every process uses the same "
                  "seeded random initialisation). The scores below measure the harness, not the methods: do not "
                  "compare them with the paper."]
    elif summary.checkpoints:
        used = ", ".join(f"{m}: `{f}`" if f else f"{m}: **untrained**" for m, f in summary.checkpoints.items())
        lines += ["", f"Trained weights (`perception.weights: {sc.perception.weights}`, verified against the zoo "
                  f"manifest's sha256): {used}."]
    if summary.skipped:
        what = (f"with {sc.perception.modality} input" if not summary.fleet
                else f"with {summary.ego}'s {summary.fleet.get(summary.ego, '')} sensor")
        lines += ["", f"Not run {what}: {', '.join(summary.skipped)} (early fusion ships raw LiDAR points)."]
    if sc.comm.compensation:
        done = ", ".join(f"{m}: {how}" for m, how in summary.compensation.items())
        rest = [m for m in summary.methods if m not in summary.compensation]
        lines += ["", f"Latency compensation (`comm.compensation: true`): {done or 'no method could be compensated'}"
                  + (f"; uncompensated: {', '.join(rest)}." if rest else ".")]
    if summary.lost_agents:
        lines += ["", "Lost agents: " + ", ".join(f"{c} (frame {f})" for c, f in sorted(summary.lost_agents.items()))]
    lines += ["", "## Methods", "",
              "| method | IoU vehicle (visible) | per-frame mean | IoU vehicle (all) | IoU road | IoU lane "
              "| AP@0.5 | AP@0.7 | fusion ms | bytes/frame |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for m, r in doc["methods"].items():
        lines.append(f"| {m} | {_fmt(r['iou_vehicle'], True)} | {_fmt(r['iou_vehicle_frame_mean'], True)} | "
                     f"{_fmt(r['iou_vehicle_all'], True)} | {_fmt(r['iou_road'], True)} | "
                     f"{_fmt(r['iou_lane'], True)} | {_fmt(r['ap50'])} | {_fmt(r['ap70'])} | "
                     f"{_fmt(r['fusion_ms'])} | {r['bytes_per_frame']} |")
    sort = doc.get("ap_sort", "global")
    lines += ["", "AP: BEV rotated boxes, all-point interpolation, detections sorted "
              + ("over the whole run (`evaluation.ap_sort: global`, OpenCOOD's --global_sort_detections)."
                 if sort == "global" else
                 "within each frame, frames in order (`evaluation.ap_sort: per_frame`, OpenCOOD's default).")]
    lines += _vs_none_md(doc)
    lines += fleet_md(doc, summary)
    lines += driving_md(doc.get("driving"))
    c = doc["comm"]
    lat = c["latency_ms"]
    lines += ["", "## Communication (BEV feature messages, receiver side)", "",
              f"sent {c['sent']}, delivered {c['delivered']}, dropped {c['dropped']}, out of range "
              f"{c['out_of_range']}, stale {c['stale']}, rejected {c['rejected']}"
              + (f" ({c['rejected_reasons']})" if c["rejected"] else "")
              + f"; {c['bytes_per_message']} bytes per message; channel time of fused messages (serialisation "
              f"and latency) p50 {lat['p50']} ms, p95 {lat['p95']} ms.",
              *_age_md(doc, 1000.0 * sc.fusion_deadline_s),
              "", f"Channel: range {sc.comm.range_m:g} m, latency {sc.comm.latency_ms.mean:g} ± "
              f"{sc.comm.latency_ms.jitter:g} ms ({sc.comm.latency_ms.distribution}), drop {sc.comm.drop.model} "
              f"p={sc.comm.drop.p:g}, bandwidth {sc.comm.bandwidth_mbps} Mbps, max age {sc.comm.max_age_ms:g} ms, "
              f"fusion deadline {1000.0 * sc.fusion_deadline_s:g} ms, "
              f"compensation {'on' if sc.comm.compensation else 'off'}, "
              f"pose noise {sc.comm.pose_noise.xy_std_m:g} m / {sc.comm.pose_noise.yaw_std_deg:g}°.",
              *_link_states_md(doc, summary),
              *_medium_md(doc),
              *_neighbours_md(doc, summary),
              *(_camera_beside_paper_md(doc) if sc.perception.modality == "camera" else _reference_md())]
    pngs = ["iou_by_method.png", "iou_per_frame.png"] + (["delivery_by_distance.png"] if "los" in c else [])
    recording = (" Recording: `recording.rrd` (open with `v2vsim view` on this directory)." if sc.output.rerun
                 else " No recording (`output.rerun: false`).")
    lines += ["", f"Plots: {', '.join(f'`{p}`' for p in pngs)}.{recording}", ""]
    return "\n".join(lines)


def _vs_none_md(doc: dict) -> list[str]:
    """Each method minus `none` in IoU points, with its bootstrap interval; [] when `none` did not run."""
    rows = [(m, r["vs_none"]) for m, r in doc["methods"].items() if r.get("vs_none")]
    if not rows:
        return []
    level = round(100 * rows[0][1]["level"])
    lines = ["", f"### Difference to no fusion ({level} % moving-block bootstrap over frames)", "",
             f"Method minus `{BASELINE}` in IoU points on the same frames, [{level} % interval]; * where the "
             f"interval excludes 0. Frames are resampled in blocks of consecutive frames (circular, "
             f"{rows[0][1]['replicates']} replicates), since neighbouring frames are alike: the block length "
             "(last column) is the larger of n^(1/3) and the first lag at which the difference's "
             "autocorrelation falls below 1.96/sqrt(n), at most n/4 (docs/run.md).", "",
             "| method | IoU vehicle (visible) | IoU road | IoU lane | block (frames): vehicle / road / lane |",
             "|---|---|---|---|---|"]
    for m, v in rows:
        cells = [v.get(k) for k in VS_NONE]
        blocks = " / ".join("-" if c is None else str(c["block_frames"]) for c in cells)
        lines.append(f"| {m} | " + " | ".join(_diff_cell(c) for c in cells) + f" | {blocks} |")
    return lines


def _diff_cell(d: dict | None) -> str:
    """'+12.3 [+8.1, +16.0] *' in IoU points; '-' without an interval."""
    if d is None:
        return "-"
    star = " *" if d["excludes_zero"] else ""
    return f"{100 * d['diff']:+.1f} [{100 * d['low']:+.1f}, {100 * d['high']:+.1f}]{star}"


def _reference_md() -> list[str]:
    lines = ["", "## Reference (CoBEVT paper, OPV2V; real data, trained models)", "",
             "| method | camera IoU vehicle / road / lane | LiDAR AP@0.7 |", "|---|---|---|"]
    for m in BUILTIN_METHODS:
        ap70 = paper_figures(m)[1]
        lines.append(f"| {m} | {_paper_camera(m)} | {'-' if ap70 is None else ap70} |")
    return lines


def _camera_beside_paper_md(doc: dict) -> list[str]:
    """This run's camera IoU (%) beside the CoBEVT paper's camera table, row by row."""
    lines = ["", "## Beside the CoBEVT paper's camera table",
             "", "The paper's figures are OPV2V (CARLA, real trained models; CoBEVT supplementary Table A2), a "
             "different dataset from this run's synthetic sensors: compare the ordering of the methods, not "
             "the values.", "",
             "| method | this run: IoU vehicle / road / lane | paper (OPV2V): IoU vehicle / road / lane |",
             "|---|---|---|"]
    in_paper = [m for m in BUILTIN_METHODS if paper_figures(m)[0] is not None and m not in doc["methods"]]
    for m in [*doc["methods"], *in_paper]:
        r = doc["methods"].get(m)
        ours = " / ".join(_fmt(r[k], True) for k in ("iou_vehicle", "iou_road", "iou_lane")) if r else "-"
        lines.append(f"| {m} | {ours} | {_paper_camera(m)} |")
    return lines


def _paper_camera(method: str) -> str:
    """The paper's camera IoU vehicle / road / lane of `method`, "-" where it has none."""
    cam = paper_figures(method)[0]
    return " / ".join(f"{v:.1f}" for v in cam) if cam else "-"


def _link_states_md(doc: dict, summary: RunSummary) -> list[str]:
    """Under comm.channel.model tr37885: messages per link state and the delivery ratio by distance."""
    c = doc["comm"]
    if "los" not in c:
        return []
    ch = summary.scenario.comm.channel
    lines = ["", f"Radio (`comm.channel.model: tr37885`, {ch.scenario}, {ch.carrier_ghz:g} GHz, MCS {ch.mcs}, "
             f"{ch.tx_power_dbm:g} dBm): messages in range by link state LOS {c['los']}, NLOS {c['nlos']}, "
             f"NLOSv {c['nlosv']}. Delivery ratio by distance (delivered / sent):", "",
             "| link state | " + " | ".join(f"{b} m" for b in distance_bins(c)) + " |",
             "|---|" + "---|" * len(distance_bins(c))]
    for state, bins in (c.get("delivery_by_distance") or {}).items():
        cells = [f"{bins[b]['ratio']:.2f} ({bins[b]['sent']})" if b in bins else "-" for b in distance_bins(c)]
        lines.append(f"| {state} | " + " | ".join(cells) + " |")
    return lines


def _medium_md(doc: dict) -> list[str]:
    """Under comm.medium shared: the channel busy ratio and what senders dropped, per message kind."""
    kinds = {"features": doc["comm"], **doc["comm"].get("by_kind", {})}
    rows = [(k, c) for k, c in kinds.items() if "cbr" in c]
    if not rows:
        return []
    lines = ["", "Shared medium (`comm.medium: shared`): one broadcast channel for every CAV, one transmission at a "
             "time; channel busy ratio (CBR) per 100 ms window, as if the fleet sent only that kind:", "",
             "| message kind | rate Mbps | CBR mean | CBR p95 | airtime s | sent on air | superseded | too old |",
             "|---|---|---|---|---|---|---|---|"]
    for kind, c in rows:
        cbr, med = c["cbr"], c["medium"]
        lines.append(f"| {kind} | {med['rate_mbps']:g} | {_fmt(cbr['mean'])} | {_fmt(cbr['p95'])} | "
                     f"{med['airtime_s']:.2f} | {med['transmissions']} | {med['superseded']} | {med['aged_out']} |")
    return lines


def _age_md(doc: dict, deadline_ms: float) -> list[str]:
    """How old the neighbour messages were when fused, per kind: why latency costs (or does not)."""
    kinds = {"features": doc["comm"], **doc["comm"].get("by_kind", {})}
    ages = {k: c["age_ms"] for k, c in kinds.items() if k != "control" and c.get("age_ms", {}).get("fused")}
    if not ages:
        return ["", "Age of fused messages: no neighbour message was fused."]
    buckets = sorted({int(b) for a in ages.values() for b in a["buckets"]})
    lines = ["", f"Age of fused neighbour messages at the fused frame's instant t_k (the ego fuses frame k at t_k + "
             f"{deadline_ms:g} ms with what has arrived; 0 ms: captured at t_k, fused aligned; 100 ms: the previous "
             "frame's, warped with its capture pose). Shares of all fusions:", "",
             "| kind | fusions | " + " | ".join(f"{b} ms" for b in buckets) + " | p50 ms | p95 ms |",
             "|---|---|" + "---|" * len(buckets) + "---|---|"]
    for k, a in ages.items():
        n = a["fused"]
        shares = " | ".join(f"{a['buckets'].get(str(b), 0) / n:.2f}" for b in buckets)
        lines.append(f"| {k} | {n} | {shares} | {a['p50']:g} | {a['p95']:g} |")
    return lines


def _neighbours_md(doc: dict, summary: RunSummary) -> list[str]:
    """The share of the fused frames with 0, 1, 2, ... other CAVs within comm range of the ego."""
    shares = doc.get("neighbours_in_range") or {}
    if not shares:
        return []
    at_least_two = sum(v for k, v in shares.items() if int(k) >= 2)
    return ["", f"## CAVs within comm range of {summary.ego}", "",
            f"Other CAVs within {summary.scenario.comm.range_m:g} m (centre distance, whatever the channel "
            f"drops), share of the {doc['frames']} fused frames; at least two in {_fmt(at_least_two, True)} %.", "",
            "| CAVs in range | " + " | ".join(shares) + " |",
            "|---|" + "---|" * len(shares),
            "| share of frames | " + " | ".join(f"{_fmt(v, True)} %" for v in shares.values()) + " |"]
