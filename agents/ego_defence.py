"""The ego's misbehaviour check over a run (`defence`; v2vsim/perception/consistency.py): per frame, each sender's
disagreement with the others, the senders flagged, and (defence.exclude) the frame's inputs without them; over the
run, per sender the frames compared and flagged, for metrics.json `defence` and the run's status."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from v2vsim.config.schema import Scenario
from v2vsim.config.schema_misbehaviour import DefenceConfig
from v2vsim.perception.consistency import MAX_CELLS, VEHICLE, Disagreement, check_frame, decode_alone, without
from v2vsim.perception.evidence_check import (
    EgoGridEvidence,
    EvidenceVerdict,
    LaterClaim,
    LaterVerdict,
    judge_claims,
    later_claims,
    later_view_check,
    on_ego_grid,
    pose_check,
    road_on_grid,
    wall_outlines,
)
from v2vsim.perception.fuse import FusionInputs, Prediction
from v2vsim.perception.precision import Precision
from v2vsim.perception.reputation import Standing, update


@dataclass
class SenderCheck:
    """One run's check. `model`: the single-agent (`none`) model that decodes each sender's features alone."""

    sc: Scenario
    model: nn.Module
    precision: Precision = "fp32"
    # sender -> per frame compared: (frame, road, vehicle_m2, shared_m2, flagged, road_corr, road_vs_map)
    frames: dict[str, list[tuple]] = field(default_factory=dict)
    # defence.evidence: sender -> per frame with evidence (frame, phantom_m2, removed_m2, unclaimed_m2, witnessed_m2,
    # pose_shift_m, pose_turn_deg, on_map, on_map_corrected, flagged, later_frame, later_phantom_m2,
    # later_removed_m2, pose_cusum): its claims against the agents' rays, its pose against the map, its claims of
    # later_frame against the ego's own rays now (v2vsim/perception/evidence_check.py; the three later figures null
    # where no claim of defence.later_frames ago is kept) and its pose gain's CUSUM so far, judged by the
    # thresholds that are set
    evidence: dict[str, list[tuple]] = field(default_factory=dict)
    # defence.pose_cusum_*: sender -> the CUSUM of its pose gain so far
    pose_cusum: dict[str, float] = field(default_factory=dict)
    # defence.later_frames: frame -> sender -> its claims then, kept until the ego's rays judge them
    later: dict[int, dict[str, LaterClaim]] = field(default_factory=dict)
    # defence.remember: each sender's standing, and per frame it was present (frame, reputation, trusted)
    standing: dict[str, Standing] = field(default_factory=dict)
    reputation: dict[str, list[tuple]] = field(default_factory=dict)
    excluded: int = 0  # sender-frames the defence fused without
    excluded_untrusted: int = 0  # ... and, with defence.remember, those not flagged this frame but not trusted yet
    excluded_unjudged: int = 0  # ... and, with defence.unjudged: exclude, those it had no evidence on
    cfg: DefenceConfig = field(init=False)  # the thresholds this run judges by

    def __post_init__(self) -> None:
        cameras = self.sc.perception.modality == "camera" or any(g.modality == "camera" for g in self.sc.cavs.fleet)
        # road_threshold null: the calibrated default of the run's sensors
        self.cfg = dataclasses.replace(self.sc.defence, road_threshold=self.sc.defence.road_limit(cameras))

    def check(self, k: int, inp: FusionInputs, road_map: np.ndarray | None = None,
              buildings: np.ndarray | None = None, ego_pose: tuple[float, float, float] | None = None,
              own: Prediction | None = None) -> tuple[FusionInputs, set[str]]:
        """Frame k: score and flag the senders; the inputs every method fuses (without the flagged ones when the
        defence excludes) and the flagged senders. `road_map`: the drivable area of the ego's map on its grid;
        `buildings` (defence.evidence): its buildings' footprints on a MAX_CELLS grid; `ego_pose`: its world
        (x, y, yaw), for the later view (None: no later view); `own`: the `none` method's prediction of this frame
        (the ego's own features decoded by the same model), reused for the ego instead of decoding them again."""
        cfg = self.cfg
        ego = inp.senders[0]
        scores: dict[str, list[Disagreement]] = {}
        hits: set[str] = set()
        all_maps = self._maps(inp, own)
        ev_judged: set[str] = set()
        if cfg.evidence and inp.evidence:
            ev_judged, ev_flagged = self._record_evidence(k, inp, all_maps, road_map, buildings, ego_pose)
            hits |= ev_flagged
        for kind, maps in all_maps.items():  # flagged on any kind it sent
            poses = inp.poses_by_kind.get(kind, inp.rel_poses)
            rel = {s: poses[inp.senders.index(s)] for s in maps}
            frame_scores, frame_flagged = check_frame(maps, rel, ego, self.sc.bev.size_m, cfg, road_map)
            hits |= frame_flagged
            for s, d in frame_scores.items():
                scores.setdefault(s, []).append(d)
        flagged: set[str] = set()
        unjudged = {s for s in [*inp.features, *inp.outputs, *inp.points] if s != ego}
        for s in ev_judged:  # judged by the rays or the map: the consistency check's shared area is not needed
            unjudged.discard(s)
            if s in hits:
                flagged.add(s)
        for s, ds in scores.items():
            judged = [d for d in ds if d.road is not None and d.shared_m2 >= cfg.min_shared_m2]
            if not judged:  # too few shared cells in every kind: no evidence either way
                continue
            unjudged.discard(s)
            self.frames.setdefault(s, []).append((k, max(d.road or 0.0 for d in judged),
                                                  max(d.vehicle_m2 or 0.0 for d in judged),
                                                  min(d.shared_m2 for d in judged), s in hits,
                                                  min(d.road_corr or 0.0 for d in judged),
                                                  max((d.road_vs_map for d in judged if d.road_vs_map is not None),
                                                      default=None)))
            if s in hits:
                flagged.add(s)
        # remembered: out while its reputation has not recovered from an earlier flag (judged clean or not now)
        untrusted = self._remember(k, set(scores) | unjudged, unjudged, flagged) - flagged if cfg.remember else set()
        drop = flagged | untrusted | (unjudged if cfg.unjudged == "exclude" else set())
        if cfg.exclude and drop:
            self.excluded += len(flagged)
            self.excluded_untrusted += len(untrusted)
            self.excluded_unjudged += len(drop - flagged - untrusted)
            return without(inp, drop), flagged
        return inp, flagged

    def _remember(self, k: int, present: set[str], unjudged: set[str], flagged: set[str]) -> set[str]:
        """Every present sender's standing after frame k; the ones not trusted now (v2vsim/perception/reputation.py)."""
        cfg = self.cfg
        out = set()
        for s in sorted(present):
            st = update(self.standing.get(s, Standing()), s not in unjudged, s in flagged, cfg.forget, cfg.lie_weight)
            self.standing[s] = st
            self.reputation.setdefault(s, []).append((k, round(st.reputation, 4), st.trusted))
            if not st.trusted:
                out.add(s)
        return out

    def _record_evidence(self, k: int, inp: FusionInputs, maps: dict[str, dict[str, np.ndarray]],
                         road_map: np.ndarray | None, buildings: np.ndarray | None,
                         ego_pose: tuple[float, float, float] | None) -> tuple[set[str], set[str]]:
        """Each sender's vehicle claims (its features decoded alone, else its outputs) against the agents' rays,
        the pose it claims against the map's buildings, and its claims of defence.later_frames ago against the
        ego's own rays now; the senders judged by a figure that has a threshold, and those flagged by one."""
        cfg = self.cfg
        limits = {1: cfg.phantom_threshold_m2, 2: cfg.removed_threshold_m2, 3: cfg.unclaimed_threshold_m2}
        judged: set[str] = set()
        flagged: set[str] = set()
        vehicle = {s: m[VEHICLE] for kind in ("outputs", "features") for s, m in maps.get(kind, {}).items()}
        kind_of = {s: kind for kind in ("outputs", "features") for s in maps.get(kind, {})}
        poses = {s: inp.poses_by_kind.get(kind_of[s], inp.rel_poses)[inp.senders.index(s)] for s in vehicle}
        ego, size_m = inp.senders[0], self.sc.bev.size_m
        vehicle = {ego: vehicle.pop(ego), **vehicle} if ego in vehicle else vehicle  # the ego first on the grid
        grid = on_ego_grid(vehicle, inp.evidence, poses, size_m, MAX_CELLS)
        if grid is None:
            return judged, flagged
        road = None if road_map is None else road_on_grid(road_map, MAX_CELLS)
        verdicts = self._claims_without_liars(grid, road, ego)
        later = self._later_view(k, grid, poses, road, ego_pose) if grid.names[0] == ego else {}  # the ego's rays
        outlines = None if buildings is None else wall_outlines(buildings)  # once a frame, for every sender
        for s, v in verdicts.items():
            if s == ego:
                continue
            pv = None if outlines is None else pose_check(inp.evidence[s], poses[s], buildings, size_m, outlines)
            lv = later.get(s)
            row = (k, v.phantom_m2, v.removed_m2, v.unclaimed_m2, v.witnessed_m2,
                   *((None,) * 4 if pv is None else (pv.shift_m, pv.turn_deg, pv.on_map, pv.on_map_corrected)))
            past = [row[i] > lim for i, lim in limits.items() if lim is not None]
            if pv is not None and cfg.pose_gain_threshold is not None:
                past.append(pv.on_map_corrected - pv.on_map > cfg.pose_gain_threshold)
            # a frame without walls to judge by adds nothing and lets the sum fall by the drift
            gain = 0.0 if pv is None else pv.on_map_corrected - pv.on_map
            cusum = round(max(0.0, self.pose_cusum.get(s, 0.0) + gain - cfg.pose_cusum_drift), 4)
            self.pose_cusum[s] = cusum
            if pv is not None and cfg.pose_cusum_threshold is not None:
                past.append(cusum > cfg.pose_cusum_threshold)
            if lv is not None and cfg.later_threshold_m2 is not None:
                past.append(max(lv.phantom_m2, lv.removed_m2) > cfg.later_threshold_m2)
            if past:
                judged.add(s)
            if any(past):
                flagged.add(s)
            self.evidence.setdefault(s, []).append(
                (*row, any(past), *((None,) * 3 if lv is None else (lv.frame, lv.phantom_m2, lv.removed_m2)),
                 cusum))
        return judged, flagged

    def _claims_without_liars(self, grid: EgoGridEvidence, road: torch.Tensor | None,
                              ego: str) -> dict[str, EvidenceVerdict]:
        """judge_claims, then as check_frame does for the consistency check: while a sender not yet left out passes
        the phantom or removed threshold, the one furthest past it is left out of every witness and the others are
        judged again (a liar's garbled map and its rays would otherwise make honest senders look like removers;
        the closed-loop attack study, docs/results.md). Each sender keeps its verdict from the last round it was
        judged in."""
        cfg, size_m = self.cfg, self.sc.bev.size_m
        limits = {"phantom_m2": cfg.phantom_threshold_m2, "removed_m2": cfg.removed_threshold_m2}
        verdicts = judge_claims(grid, size_m, road)
        out: dict[str, EvidenceVerdict] = dict(verdicts)
        left_out: set[str] = set()

        def excess(v: EvidenceVerdict) -> float:  # > 1: past a threshold
            return max([getattr(v, k) / lim for k, lim in limits.items() if lim], default=0.0)

        while True:
            suspects = {s: excess(v) for s, v in verdicts.items() if s != ego and s not in left_out}
            suspects = {s: x for s, x in suspects.items() if x > 1.0}
            if not suspects:
                return out
            left_out.add(max(suspects, key=lambda s: suspects[s]))
            verdicts = judge_claims(grid, size_m, road, frozenset(left_out))
            out.update({s: v for s, v in verdicts.items() if s not in left_out})

    def _later_view(self, k: int, grid: EgoGridEvidence, poses: dict[str, np.ndarray], road: torch.Tensor | None,
                    ego_pose: tuple[float, float, float] | None) -> dict[str, LaterVerdict]:
        """Keep frame k's claims; judge those of defence.later_frames ago by the ego's rays now (sender ->
        LaterVerdict; empty where the ego's own evidence or pose is missing or the later view is off)."""
        cfg, d = self.cfg, self.cfg.later_frames
        if d == 0 or ego_pose is None:
            return {}
        size_m = self.sc.bev.size_m
        self.later[k] = later_claims(grid, poses, k, ego_pose, size_m)
        for old in [f for f in self.later if f < k - d]:
            del self.later[old]
        # reach: the move of a vehicle at later_speed_mps over the frames between, and one frame more for the age
        # of the message the claim came in
        reach = cfg.later_speed_mps * (d + 1) * self.sc.dt
        return {s: later_view_check(c, grid, ego_pose, road, reach, size_m)
                for s, c in self.later.get(k - d, {}).items()}

    def _maps(self, inp: FusionInputs, own: Prediction | None = None) -> dict[str, dict[str, np.ndarray]]:
        """Per message kind, each sender's single-agent maps [3, S, S]: its features decoded alone (the ego's taken
        from `own` where its grid is the decoder's); late fusion's outputs as sent (a lie may touch one kind and
        not the other)."""
        out = {"features": self._decoded(inp.features, inp.senders[0], own)} if inp.features else {}
        if inp.outputs:
            out["outputs"] = {s: v[0] for s, v in inp.outputs.items()}
        return out

    def _decoded(self, features: dict[str, np.ndarray], ego: str, own: Prediction | None) -> dict[str, np.ndarray]:
        """decode_alone of every sender, the ego's map taken from `own` (the `none` prediction) when it is on the
        decoder's own grid (a scenario grid that differs is resized: then the ego is decoded with the rest)."""
        if own is None or ego not in features:
            return decode_alone(self.model, features, self.precision)
        mine = np.stack([own.probs[c] for c in ("vehicle", "road", "lane")]).astype(np.float32)  # [3, S, S]
        others = decode_alone(self.model, {s: f for s, f in features.items() if s != ego}, self.precision)
        if others and next(iter(others.values())).shape != mine.shape:
            return decode_alone(self.model, features, self.precision)
        return {s: mine if s == ego else others[s] for s in features}

    def flagged_counts(self) -> dict[str, tuple[int, int]]:
        """Sender -> (frames flagged, frames compared), for the senders flagged in at least defence.min_frames."""
        out = {}
        for s in sorted(set(self.frames) | set(self.evidence)):
            compared = {r[0]: bool(r[4]) for r in self.frames.get(s, [])}  # the consistency check's frames ...
            for r in self.evidence.get(s, []):  # ... and the rays' and the map's (a frame counts once)
                compared[r[0]] = compared.get(r[0], False) or bool(r[9])
            n = sum(compared.values())
            if n >= self.cfg.min_frames:
                out[s] = (n, len(compared))
        return out

    def to_json(self) -> dict:
        """metrics.json `defence`: the settings, per sender its frames compared and flagged and its scores'
        median and maximum, and the per-frame scores (frame, road, vehicle_m2, shared_m2, flagged, road_corr,
        road_vs_map)."""
        cfg = self.cfg
        senders = {}
        for s, rows in sorted(self.frames.items()):
            road = np.array([r[1] for r in rows])
            veh = np.array([r[2] for r in rows])
            flagged = [r[0] for r in rows if r[4]]
            senders[s] = {"frames_compared": len(rows), "frames_flagged": len(flagged),
                          "first_flagged": flagged[0] if flagged else None,
                          "road": {"median": round(float(np.median(road)), 4), "max": round(float(road.max()), 4)},
                          "vehicle_m2": {"median": round(float(np.median(veh)), 2),
                                         "max": round(float(veh.max()), 2)},
                          "per_frame": [list(r) for r in rows]}
        return {"exclude": cfg.exclude, "near_m": cfg.near_m, "road_threshold": cfg.road_threshold,
                "vehicle_threshold_m2": cfg.vehicle_threshold_m2, "min_shared_m2": cfg.min_shared_m2,
                "min_frames": cfg.min_frames, "flagged": {s: {"frames": n, "of": m}
                                                          for s, (n, m) in self.flagged_counts().items()},
                "excluded_sender_frames": self.excluded, "unjudged": cfg.unjudged,
                "excluded_unjudged_sender_frames": self.excluded_unjudged, "senders": senders,
                **({"evidence": self._evidence_json()} if cfg.evidence else {}),
                **({"reputation": {"forget": cfg.forget, "lie_weight": cfg.lie_weight,
                                   "excluded_untrusted_sender_frames": self.excluded_untrusted,
                                   "senders": {s: {"frames_untrusted": sum(1 for r in rows if not r[2]),
                                                   "min": min(r[1] for r in rows),
                                                   "per_frame": [list(r) for r in rows]}
                                               for s, rows in sorted(self.reputation.items())}}}
                   if cfg.remember else {})}

    def _evidence_json(self) -> dict:
        """Per sender: frames with evidence, the largest phantom / removed / unclaimed area, the per-frame rows
        (frame, phantom_m2, removed_m2, unclaimed_m2, witnessed_m2, pose_shift_m, pose_turn_deg, on_map,
        on_map_corrected, flagged; the four pose figures null where its rays hit no building)."""
        out = {}
        for s, rows in sorted(self.evidence.items()):
            a = np.array([r[1:5] for r in rows], dtype=float)
            out[s] = {"frames": len(rows), **{f"max_{name}": round(float(a[:, i].max()), 2)
                                              for i, name in enumerate(("phantom_m2", "removed_m2", "unclaimed_m2"))},
                      "per_frame": [list(r) for r in rows]}
        return out
