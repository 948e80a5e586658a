"""The scenario schema's `misbehaviour` and `defence` sections (docs/scenario.md): the CAVs that lie on purpose in
an attacked run (`Lie`), and the ego's check of what trusted senders say (`DefenceConfig`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from v2vsim.config.schema_fields import _f, _nonneg, _pos


@dataclass(frozen=True)
class Lie:
    """A misbehaviour told on purpose by trusted CAVs (v2vsim/comm/misbehaviour.py, docs/scenario.md
    "misbehaviour"): who, from which frame, and how."""

    cavs: tuple[str, ...] = _f((), "a non-empty list of CAV ids of this run (the liars)", lambda v: len(v) > 0)
    kind: Literal["scale", "flip", "zero", "pose", "remove_vehicle", "add_vehicle"] = "scale"
    from_frame: int = _f(0, ">= 0 (the first frame it lies in)", _nonneg)
    factor: float = _f(8.0, "a finite number (scale: the features times it; negative flips their sign)",
                       lambda v: math.isfinite(v))
    shift_m: tuple[float, float] = _f((0.0, 0.0), "[forward, left] metres (pose: the claimed position moved)",
                                      lambda v: all(math.isfinite(x) for x in v))
    rotate_deg: float = _f(0.0, "-180..180 (pose: the claimed heading turned)", lambda v: -180 <= v <= 180)
    targets: tuple[str, ...] = ("foe0",)  # remove_vehicle: the actors it hides (the hidden foe by default)
    at_m: tuple[float, float] = _f((10.0, 0.0), "[forward, left] metres in the liar's frame (add_vehicle: the "
                                   "phantom car's centre)", lambda v: all(math.isfinite(x) for x in v))
    # defence.evidence: its free-space evidence stays honest, or is made to agree with the lie (an attacker that
    # knows the defence; v2vsim/comm/misbehaviour.py)
    evidence: Literal["honest", "consistent"] = "honest"


LIDAR_ROAD_THRESHOLD, CAMERA_ROAD_THRESHOLD = 0.2, 0.45  # DefenceConfig.road_threshold's defaults


@dataclass(frozen=True)
class DefenceConfig:
    """The ego's check of what trusted senders say (issue 55; v2vsim/perception/consistency.py, docs/scenario.md
    "defence"): each frame, each sender's single-agent maps are compared with the consensus of the ego and the other
    senders where they are near the same cells; a sender that disagrees beyond a threshold is flagged that frame."""

    detect: bool = False  # score and flag senders each frame (one single-agent decoding per sender and frame)
    # every LiDAR CAV sends what its rays establish, occupied / free / unknown per cell of a grid twice as fine as
    # its features' (4 KB at the 64 x 64 zoo; v2vsim/perception/evidence.py, issue 67) with its feature and output
    # messages, and the ego records each sender's claims against the agents' rays (v2vsim/perception/
    # evidence_check.py; implies detect)
    evidence: bool = False
    # with evidence, a sender is flagged at a frame where a figure of evidence_check passes its threshold; null:
    # recorded, not judged by. Calibrated (2026-12-03, scripts/evidence_study.sh): 1.25 x the largest figure of any
    # honest sender-frame in clean runs of tuning seed 100, every shipped scenario (2,121 sender-frames;
    # docs/results.md "Free-space evidence")
    phantom_threshold_m2: float | None = _f(9.91, "null or >= 0 (m^2 of its claimed vehicles where another agent's "
                                                  "rays passed)", _nonneg)
    removed_threshold_m2: float | None = _f(15.26, "null or >= 0 (m^2 of vehicles others see where its rays reached "
                                                  "and it claims none)", _nonneg)
    unclaimed_threshold_m2: float | None = _f(27.46, "null or >= 0 (m^2 of its own hits on the road it claims no "
                                                    "vehicle at)", _nonneg)
    pose_gain_threshold: float | None = _f(0.32, "null or 0..1 (the share of its wall hits a pose correction puts "
                                                 "on the map's buildings beyond the claimed pose's)",
                                           lambda v: 0 <= v <= 1)
    # the pose over frames: per sender a one-sided CUSUM of its pose gain, S = max(0, S + gain - drift) (Page 1954),
    # flagged while S passes the threshold; a persistent small pose lie adds up where one frame's gain stays under
    # pose_gain_threshold. Calibrated on tuning seed 100 (scripts/evidence_study.sh): the drift half the median gain
    # of its 1 m / 2 deg lie (0.321), the threshold 1.25 x the largest S of any honest sender in its clean runs
    pose_cusum_drift: float = _f(0.16, "> 0 (pose gain a frame that an honest sender may have without adding up)",
                                 _pos)
    pose_cusum_threshold: float | None = _f(0.11, "null or > 0 (the CUSUM of its pose gain past which it is "
                                                   "flagged; null: recorded, not judged by)",
                                            lambda v: v > 0)
    # the ego's own later view (evidence_check.later_view_check): a sender's claims are checked against the ego's
    # own rays this many frames later (0: never), allowing for a vehicle's move at up to later_speed_mps since
    later_frames: int = _f(3, ">= 0 (frames)", lambda v: v >= 0)
    later_speed_mps: float = _f(15.0, "> 0 (m/s: how fast a claimed vehicle may have moved on since)", _pos)
    later_threshold_m2: float | None = _f(35.1, "null or >= 0 (m^2 of its claimed vehicles the ego's rays later find "
                                                "nowhere, or of vehicles the ego sees where it vouched empty)", _nonneg)
    exclude: bool = False  # the defence: every method fuses without the senders flagged at that frame (implies detect)
    near_m: float = _f(30.0, "> 0 (m: a cell is compared where the sender and another agent are within this of it)",
                       _pos)
    # calibrated on clean runs of tuning seed 100, every shipped scenario (docs/results.md "A lying CAV"): the largest
    # honest road_vs_map was 0.26 with LiDAR senders only (two frames) and 0.41 where camera CAVs send; 30.5 m^2
    road_threshold: float | None = _f(None, "null (0.2; 0.45 where a CAV of the run has cameras) or 0..1 (the "
                                            "sender's mean |road - map| near it, less the ego's own near it)",
                                      lambda v: 0 <= v <= 1)
    vehicle_threshold_m2: float = _f(40.0, ">= 0 (m^2 of shared cells where the sender and the others' mean "
                                           "differ on a vehicle by more than 0.5)", _nonneg)
    min_shared_m2: float = _f(100.0, ">= 0 (m^2: fewer shared cells is no evidence, nothing is flagged)", _nonneg)
    # with exclude: a sender that shares too few cells with the others to be judged this frame is fused ("fuse") or
    # left out like a flagged one ("exclude": no lie goes unchallenged, nor does a far honest sender's help)
    unjudged: Literal["fuse", "exclude"] = "fuse"
    min_frames: int = _f(3, ">= 1 (frames a sender is flagged in before the run's status says so)",
                         lambda v: v >= 1)
    # trust that remembers (v2vsim/perception/reputation.py): with exclude, a sender flagged once stays out until
    # its reputation, built from the frames it passed and failed, has recovered
    remember: bool = False
    forget: float = _f(0.95, "0..1 (the share of a sender's past evidence kept from one frame to the next)",
                       lambda v: 0 < v < 1)
    lie_weight: float = _f(10.0, "> 0 (the evidence against a sender one flagged frame adds; a clean one adds 1)",
                           _pos)

    @property
    def on(self) -> bool:
        """The ego checks its senders (evidence implies detect)."""
        return self.detect or self.exclude or self.evidence

    def road_limit(self, cameras: bool) -> float:
        """road_threshold as set, or the calibrated default: camera BEV road maps are far less consistent from
        one viewpoint to the next than LiDAR ones."""
        if self.road_threshold is not None:
            return self.road_threshold
        return CAMERA_ROAD_THRESHOLD if cameras else LIDAR_ROAD_THRESHOLD
