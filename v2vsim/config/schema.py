"""The scenario schema (DESIGN.md "Scenario YAML"): frozen dataclasses, one per YAML section, whose field
metadata says what is allowed; the constants they use."""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from dataclasses import dataclass, field
from typing import Any, Literal

from models.registry import BUILTIN_METHODS, METHODS  # (imports no torch)

SEED_MAX = 2**31 - 1  # SUMO (libsumo --seed) takes a signed 32-bit seed
ENCODERS_BY_MODALITY = {"lidar": ("pointpillars",), "camera": ("sinbevt", "lara")}
DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")  # perception.device (v2vsim.perception.device resolves it)


# ---- field helpers: metadata says what is allowed -------------------------------------------


def _f(default: Any, allowed: str = "", check: typing.Callable[[Any], bool] | None = None,
       path: str | None = None) -> Any:
    """A dataclass field with a range check. `path`: "file" (must exist) or "file?" (optional)."""
    meta = {"allowed": allowed, "check": check, "path": path}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        return field(default_factory=lambda: default, metadata=meta)
    return field(default=default, metadata=meta)


def _pos(x: float) -> bool:
    return x > 0


def _nonneg(x: float) -> bool:
    return x >= 0


def _prob(x: float) -> bool:
    return 0.0 <= x <= 1.0


class _Methods:
    """What perception.methods allows, spelled when an error needs it: the registry's methods (models.registry:
    the built-ins and every installed fusion plugin, whose entry points are read only then)."""

    def __str__(self) -> str:
        return f"a non-empty list of {', '.join(METHODS)}"


# ---- the schema ------------------------------------------------------------------------------


@dataclass(frozen=True)
class HiddenFoeConfig:
    """One extra main-road vehicle, foe0, that buildings hide from the ego (v2vsim/traffic/sumo_hidden_foe.py): it
    reaches the main junction `arrival_offset_s` (drawn per seed) after the ego's free-flow arrival at its stop line.
    attentive false: it does not brake for a vehicle already in the junction (SUMO's priority-road drivers do)."""

    arrival_offset_s: tuple[float, float] = _f((0.5, 2.5), "[lo, hi] with -10 <= lo <= hi <= 10 (seconds after the "
                                               "ego's free-flow arrival at its stop line)",
                                               lambda v: -10 <= v[0] <= v[1] <= 10)
    attentive: bool = False
    # auto: the main-road arm that buildings hide from the ego; opposite: oncoming traffic (an ego turning left)
    side: Literal["auto", "left", "right", "opposite"] = "auto"
    # its free-flow speed: null = the lane's speed limit; a benchmark grid's second factor (as Coopernaut's)
    speed_mps: float | None = _f(None, "0 < v <= 40 (m/s) or null (the lane's speed limit)",
                                 lambda v: 0 < v <= 40)
    # true: it drives through a red light (SUMO's junctionModel.jmDriveAfterRedTime), a red-light runner at a
    # signalised junction where the ego has green (scenarios/red_light_runner.yaml)
    runs_red: bool = False


@dataclass(frozen=True)
class StandingVehicle:
    """A vehicle that stands in a lane for the whole run (v2vsim/traffic/sumo_standing.py): a truck queued to turn
    left, a parked van, a broken-down car. It is there from the start of the warm-up; traffic behind it queues or
    changes lane. Its type's extents (car 4.5 x 1.9 x 1.5 m, van 5.4 x 2.0 x 2.4, truck 8.5 x 2.5 x 3.4) make it an
    occluder for LiDAR and cameras as any vehicle is."""

    edge: str = _f("", "an edge id of traffic.net", lambda v: bool(v))
    lane: int = _f(0, ">= 0 (lane index on the edge, 0 = its rightmost)", _nonneg)
    to_end_m: float = _f(0.5, ">= 0 (m from its front bumper to the lane's end: 0.5 = at the stop line)", _nonneg)
    type: Literal["car", "van", "truck", "bus"] = "truck"


@dataclass(frozen=True)
class HiddenStopConfig:
    """A vehicle standing in the ego's exit lane just past the main junction (v2vsim/traffic/sumo_standing.py
    insert_hidden_stop): a lead vehicle stopped around a blind corner (NHTSA "lead vehicle stopped"). It is
    inserted with the CAVs, `distance_m` from the start of the lane the ego leaves the junction by (its rear), and
    drives off `until_s` after frame 0."""

    distance_m: float = _f(10.0, ">= 0 (m from the start of the ego's exit lane to its rear bumper)", _nonneg)
    until_s: float = _f(15.0, "> 0 (s after frame 0 at which it drives off)", _pos)
    type: Literal["car", "van", "truck", "bus"] = "car"


@dataclass(frozen=True)
class VehicleMix:
    """The background traffic's classes (SUMO vTypes with their extents, v2vsim/traffic/sumo.py: car 4.5 x 1.9 x
    1.5 m, van 5.4 x 2.0 x 2.4, truck 8.5 x 2.5 x 3.4, bus 12.0 x 2.55 x 3.2), as shares of the vehicles entering.
    The default is the mix every shipped scenario was calibrated with; the generated towns vary it."""

    car: float = _f(0.80, ">= 0 (share)", _nonneg)
    van: float = _f(0.12, ">= 0 (share)", _nonneg)
    truck: float = _f(0.08, ">= 0 (share)", _nonneg)
    bus: float = _f(0.0, ">= 0 (share)", _nonneg)

    def shares(self) -> tuple[tuple[str, float], ...]:
        """(vType, share) of the classes with a share above 0, normalised to sum to 1 (the default's three as
        written: 0.8 + 0.12 + 0.08 is exactly 1.0, so the shipped scenarios draw as they always did)."""
        items = [(k, float(getattr(self, k))) for k in ("car", "van", "truck", "bus") if getattr(self, k) > 0]
        total = sum(v for _, v in items)
        return tuple((k, v / total) for k, v in items) if total != 1.0 else tuple(items)


@dataclass(frozen=True)
class TrafficConfig:
    backend: Literal["sumo", "highway-env"] = "sumo"
    net: str | None = _f(None, "path to a SUMO .net.xml, relative to the YAML", path="file?")
    buildings: str | None = _f(None, "path to a SUMO .poly.xml, relative to the YAML", path="file?")
    background_per_hour: float = _f(900.0, ">= 0", _nonneg)
    warmup_s: float = _f(10.0, ">= 0 (background traffic runs this long before frame 0)", _nonneg)
    building_height_m: tuple[float, float] = _f((8.0, 15.0), "[lo, hi] with 0 < lo <= hi",
                                                lambda v: 0 < v[0] <= v[1])
    hidden_foe: HiddenFoeConfig | None = None  # null: no foe (SUMO backend only)
    standing: tuple[StandingVehicle, ...] = ()  # vehicles standing in a lane all run (SUMO backend only)
    vehicle_mix: VehicleMix = field(default_factory=VehicleMix)  # the background's classes (SUMO backend only)
    hidden_stop: HiddenStopConfig | None = None  # null: none (SUMO backend only)


@dataclass(frozen=True)
class MeetConfig:
    """What CAV placement aims for (see v2vsim/traffic/sumo.py): at least `neighbours` other CAVs
    within comm.range_m of the first ego in at least `share` of the frames, counted from frame 0 over the first
    `horizon_s` seconds (null: the whole run)."""

    neighbours: int = _f(2, ">= 0 (capped at cavs.count - 1)", _nonneg)
    share: float = _f(0.9, "0..1", _prob)
    trials: int = _f(24, "1..200 (candidate placements simulated ahead; 1 = the first candidate only)",
                     lambda v: 1 <= v <= 200)
    # why: a closed-loop run's duration is its time limit; the cast (where the CAVs start) must not change when
    # only the time limit does, so the look-ahead can span the encounter rather than the whole run
    horizon_s: float | None = _f(None, "> 0 (s) or null (duration_s): the frames the look-ahead scores", _pos)

    def frames(self, duration_frames: int, rate_hz: float) -> int:
        """The frames placement scores: the run's, or the first horizon_s seconds of them."""
        if self.horizon_s is None:
            return duration_frames
        return max(1, min(duration_frames, round(self.horizon_s * rate_hz)))


@dataclass(frozen=True)
class FleetGroup:
    """CAVs that carry another sensor and encoder than perception.modality / perception.encoder (a mixed fleet,
    docs/scenario.md): their features join the run's feature space through an encoder aligned to it (the
    `align` training stage, HEAL's backward alignment)."""

    cavs: tuple[str, ...] = _f((), "a non-empty list of CAV ids (cav0, cav1, ...)", lambda v: len(v) > 0)
    modality: Literal["lidar", "camera"] = "camera"
    encoder: Literal["pointpillars", "sinbevt", "lara"] = "sinbevt"


@dataclass(frozen=True)
class CavsConfig:
    count: int = _f(4, "1..16", lambda v: 1 <= v <= 16)
    ego: str | tuple[str, ...] = _f("first", "'first', 'all' or a list of CAV ids",
                                    lambda v: not isinstance(v, str) or v in ("first", "all"))
    arrival_s: tuple[float, float] = _f((0.0, 4.0), "[lo, hi] with 0 <= lo <= hi <= 60 (seconds after frame 0 "
                                        "at which the CAVs reach the junction at free-flow speed)",
                                        lambda v: 0 <= v[0] <= v[1] <= 60)
    meet: MeetConfig = field(default_factory=MeetConfig)
    # the movement of CAV i (cav0 first) through the junction in every placement candidate, where given: e.g.
    # [left] makes the ego turn left across oncoming traffic (empty: the placement's own choice)
    movements: tuple[Literal["straight", "left", "right"], ...] = ()
    # a mixed fleet: groups of CAVs with their own sensor and encoder; a CAV in no group runs perception.modality
    # and perception.encoder (empty: every CAV does, as in every single-modality run)
    fleet: tuple[FleetGroup, ...] = ()
    # the share of the placed vehicles besides the egos that are connected, drawn per seed (the others are ordinary
    # SUMO-driven vehicles; v2vsim/traffic/penetration.py); null: all of them
    penetration: float | None = _f(None, "0..1 or null (every placed vehicle connected)", _prob)

    def egos_among(self, present: typing.Sequence[str]) -> list[str]:
        """The CAVs that fuse (and, in a closed loop, drive), from `ego` (first | all | list of ids) and the CAVs
        present, in `present`'s order for first and all."""
        if self.ego == "first":
            return list(present[:1])
        if self.ego == "all":
            return list(present)
        return [c for c in self.ego if c in present]


@dataclass(frozen=True)
class LidarConfig:
    channels: int = _f(32, ">= 1", _pos)
    points_per_channel: int = _f(1024, ">= 1", _pos)
    range_m: float = _f(100.0, "> 0", _pos)
    vertical_fov_deg: tuple[float, float] = _f((-25.0, 5.0), "[lo, hi] with -90 <= lo < hi <= 90",
                                               lambda v: -90 <= v[0] < v[1] <= 90)
    height_m: float = _f(1.9, "> 0", _pos)
    noise_std_m: float = _f(0.02, ">= 0", _nonneg)
    dropout: float = _f(0.0, "0..1", _prob)


@dataclass(frozen=True)
class CamerasConfig:
    count: int = _f(4, "4 (front, right, left, back)", lambda v: v == 4)
    fov_deg: float = _f(110.0, "0 < fov < 180", lambda v: 0 < v < 180)
    width: int = _f(800, ">= 16", lambda v: v >= 16)
    height: int = _f(600, ">= 16", lambda v: v >= 16)
    render_scale: float = _f(0.25, "0 < scale <= 1", lambda v: 0 < v <= 1)
    height_m: float = _f(1.6, "> 0 (mount height)", _pos)


@dataclass(frozen=True)
class SensorsConfig:
    lidar: LidarConfig = field(default_factory=LidarConfig)
    cameras: CamerasConfig = field(default_factory=CamerasConfig)


@dataclass(frozen=True)
class BevConfig:
    size_m: float = _f(100.0, "> 0", _pos)
    cells: int = _f(256, ">= 8", lambda v: v >= 8)


@dataclass(frozen=True)
class LatencyConfig:
    mean: float = _f(0.0, ">= 0 (ms)", _nonneg)
    jitter: float = _f(0.0, ">= 0 (ms, std of the distribution)", _nonneg)
    distribution: Literal["normal", "uniform", "exponential"] = "normal"


@dataclass(frozen=True)
class DropConfig:
    model: Literal["bernoulli", "gilbert_elliott"] = "bernoulli"
    p: float = _f(0.0, "0..1", _prob)
    p_gb: float = _f(0.0, "0..1 (good -> bad transition probability)", _prob)
    p_bg: float = _f(1.0, "0..1 (bad -> good transition probability)", _prob)
    loss_good: float = _f(0.0, "0..1", _prob)
    loss_bad: float = _f(1.0, "0..1", _prob)


@dataclass(frozen=True)
class PoseNoiseConfig:
    xy_std_m: float = _f(0.0, ">= 0", _nonneg)
    yaw_std_deg: float = _f(0.0, ">= 0", _nonneg)


@dataclass(frozen=True)
class AuthConfig:
    """Signed messages. key_file: one secret every process shares (hmac-sha256, bound to the run instance):
    proves membership of the run, not who sent a message. identity per_process: each process signs with its
    own Ed25519 key, issued by the runner for this run (v2vsim/comm/identity.py): a process can sign only as
    itself. One or the other, not both. identity auto (the default) is per_process unless a key_file is given;
    the loader resolves it, so a loaded Scenario holds off or per_process (issue 45: trust by default)."""

    key_file: str | None = _f(None, "path to a secret key file, relative to the YAML", path="file?")
    identity: Literal["auto", "off", "per_process"] = "auto"

    @property
    def mode(self) -> Literal["per_process", "shared_key", "off"]:
        """The trust mode that runs (metrics.json `trust.mode`): off means any local process can alter the run."""
        if self.identity == "per_process":
            return "per_process"
        return "shared_key" if self.key_file is not None else "off"


@dataclass(frozen=True)
class ChannelConfig:
    """The radio channel (v2vsim/comm/tr37885.py). `disk`: delivered within comm.range_m, lost only by comm.drop.
    `tr37885`: within comm.range_m, reception decided by the link budget over 3GPP TR 37.885 path loss with the
    link state (los | nlos | nlosv) from the world's buildings and vehicles; serialisation at the MCS data rate
    (capped by comm.bandwidth_mbps when that is lower). Defaults: TR 37.885 / IEEE 802.11p values (see tr37885.py)."""

    model: Literal["disk", "tr37885"] = "disk"
    scenario: Literal["urban", "highway"] = "urban"  # TR 37.885 Table 6.2.1-1 LOS formula and decorrelation distance
    carrier_ghz: float = _f(5.9, "0.5..100 (GHz)", lambda v: 0.5 <= v <= 100)
    tx_power_dbm: float = _f(23.0, "-50..60 (dBm)", lambda v: -50 <= v <= 60)
    antenna_gain_dbi: float = _f(3.0, "-30..30 (dBi, each of the two antennas)", lambda v: -30 <= v <= 30)
    noise_figure_db: float = _f(9.0, "0..30 (dB)", lambda v: 0 <= v <= 30)
    bandwidth_mhz: float = _f(10.0, "5, 10 or 20 (MHz, an IEEE 802.11 OFDM channel width)", lambda v: v in (5, 10, 20))
    mcs: int = _f(2, "0..7 (IEEE 802.11p MCS: BPSK 1/2 .. 64-QAM 3/4)", lambda v: 0 <= v <= 7)
    antenna_height_m: float = _f(1.5, "> 0 (m above each vehicle's pose.z)", _pos)
    per_slope_db: float = _f(1.0, ">= 0 (dB; logistic packet-error slope, 0 = a hard SNR threshold)", _nonneg)


@dataclass(frozen=True)
class ShareConfig:
    """What each CAV sends of its BEV features (v2vsim/comm/sparse.py). `all`: the whole map. `topk`: the `fraction`
    of its feature cells that its own single-agent vehicle confidence ranks highest (Where2comm's spatial
    confidence, Eq. 2), as a sparse message of indices + values, or the whole map where that is no larger."""

    policy: Literal["all", "topk"] = "all"
    fraction: float = _f(1.0, "0..1 (share of the BEV feature cells sent)", _prob)


@dataclass(frozen=True)
class CommConfig:
    range_m: float = _f(70.0, "> 0", _pos)
    latency_ms: LatencyConfig = field(default_factory=LatencyConfig)
    drop: DropConfig = field(default_factory=DropConfig)
    bandwidth_mbps: float | None = _f(27.0, "> 0 or null (unlimited)", _pos)
    max_age_ms: float = _f(500.0, "> 0", _pos)
    # The ego fuses frame k at t_k + fusion_deadline_ms with every message that has arrived by then; one of frame
    # k that made it is fused aligned, as of t_k (docs/run.md "Time at the receiver"). null: half a frame (50 ms
    # at 10 Hz), the wait a receiver can afford while its own sensing and encoding run, leaving the rest for
    # fusion (Scenario.fusion_deadline_s).
    fusion_deadline_ms: float | None = _f(None, ">= 0 and less than one frame (1000 / rate_hz ms), or null "
                                          "(half a frame)", _nonneg)
    # true: late fusion's neighbour outputs are moved by each object's velocity (model-free), and methods whose zoo
    # ships a trained extrapolation module use it on late features (learned); docs/run.md says which.
    compensation: bool = False
    pose_noise: PoseNoiseConfig = field(default_factory=PoseNoiseConfig)
    compression: Literal["none", "zlib"] = "none"
    # CoBEVT Table 4's learned 1x1 channel compressor, ratio r: C -> C/r channels on the wire. null: the zoo's
    # wire ratio (v2vsim.perception.build.wire_ratio); a ratio needs a trained compressor in the zoo.
    channel_compression: int | None = _f(None, "null (the zoo's wire ratio), 1 (off) or a ratio whose compressor "
                                               "the zoo ships, such as 8, 16, 32, 64", _pos)
    auth: AuthConfig = field(default_factory=AuthConfig)
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    # per_link: every (sender, receiver) link has its own data rate; shared: one broadcast channel for every
    # CAV, one transmission at a time, with its busy ratio measured (v2vsim/comm/medium.py)
    medium: Literal["per_link", "shared"] = "per_link"
    share: ShareConfig = field(default_factory=ShareConfig)


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


LIDAR_ROAD_THRESHOLD, CAMERA_ROAD_THRESHOLD = 0.2, 0.45  # DefenceConfig.road_threshold's defaults


@dataclass(frozen=True)
class DefenceConfig:
    """The ego's check of what trusted senders say (issue 55; v2vsim/perception/consistency.py, docs/scenario.md
    "defence"): each frame, each sender's single-agent maps are compared with the consensus of the ego and the other
    senders where they are near the same cells; a sender that disagrees beyond a threshold is flagged that frame."""

    detect: bool = False  # score and flag senders each frame (one single-agent decoding per sender and frame)
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

    @property
    def on(self) -> bool:
        return self.detect or self.exclude

    def road_limit(self, cameras: bool) -> float:
        """road_threshold as set, or the calibrated default: camera BEV road maps are far less consistent from
        one viewpoint to the next than LiDAR ones."""
        if self.road_threshold is not None:
            return self.road_threshold
        return CAMERA_ROAD_THRESHOLD if cameras else LIDAR_ROAD_THRESHOLD


@dataclass(frozen=True)
class TransportConfig:
    mode: Literal["peer", "client"] = "peer"  # peer: a loopback mesh; client: through transport.connect routers
    connect: tuple[str, ...] = _f((), "zenoh endpoints such as tcp/127.0.0.1:7447")
    listen: tuple[str, ...] = _f((), "zenoh endpoints; empty = a free loopback port")
    clock: Literal["lockstep", "realtime"] = "lockstep"
    # lockstep: frames the driver and CAVs may run ahead of the slowest ego (0 = strict lockstep);
    # results are the same for any value, only the wall time changes.
    pipeline: int = _f(2, "an integer 0..16", lambda v: 0 <= v <= 16)
    # lockstep: how long the ego waits for a CAV that is alive (its token up) but sent nothing for a frame before it
    # fuses without it and counts it lost (metrics.json lost_agents); a dead CAV is noticed at once
    lost_after_s: float = _f(60.0, "seconds > 0", lambda v: 0 < v < float("inf"))


@dataclass(frozen=True)
class PerceptionConfig:
    modality: Literal["lidar", "camera"] = "lidar"
    encoder: Literal["pointpillars", "sinbevt", "lara"] = "pointpillars"
    preset: Literal["tiny", "paper"] = "tiny"
    # default: the built-in methods; a fusion plugin (models.registry) runs when named here or in --methods
    methods: tuple[str, ...] = _f(BUILTIN_METHODS, _Methods(), lambda v: len(v) > 0 and all(m in METHODS for m in v))
    weights: str = _f("auto", "'auto', 'none' or a checkpoint path")
    # the models' forward passes (v2vsim.perception.precision): auto = bf16 autocast where the CPU has native
    # bfloat16 (AMX, AVX-512 BF16), fp32 elsewhere; metrics.json says which ran
    precision: Literal["auto", "fp32", "bf16"] = "fp32"
    # where each process's models run (v2vsim.perception.device): auto = the GPU where torch sees one, else the CPU
    # (so a CPU host runs exactly as before); whether the host has the device is checked before any process starts
    # (the loader imports no torch); metrics.json "device" says what ran
    device: str = _f("auto", "auto, cpu, cuda or cuda:N", lambda v: DEVICE_PATTERN.fullmatch(v) is not None)
    # how many methods the ego fuses at once, each on its own thread (every prediction bit-identical to one at a
    # time; v2vsim.perception.threads): 0 = auto
    fusion_threads: int = _f(0, "0 (auto) or a positive integer", lambda v: v >= 0)


@dataclass(frozen=True)
class EvaluationConfig:
    # How AP ranks detections: 'global' sorts every detection of the run by score (OpenCOOD's
    # --global_sort_detections, the DESIGN.md default); 'per_frame' keeps frame order and sorts
    # only within each frame (OpenCOOD's default, which most published AP tables use).
    ap_sort: Literal["global", "per_frame"] = "global"


@dataclass(frozen=True)
class OutputConfig:
    dir: str = "runs/intersection"
    rerun: bool = True
    # true: the ego also keeps what it received, frame by frame (messages/ beside metrics.json, docs/run.md
    # "Record once, evaluate many"), for `v2vsim evaluate` to replay with other receiver-side keys; lockstep only
    record_messages: bool = False


@dataclass(frozen=True)
class IdmConfig:
    """The planner's car-following law (IDM, Treiber, Hennecke & Helbing 2000) and its limits (v2vsim/control)."""

    desired_speed_mps: float | None = _f(None, "> 0 (m/s) or null (the lane's speed limit)", _pos)
    time_headway_s: float = _f(1.5, "> 0 (s)", _pos)
    min_gap_m: float = _f(2.0, ">= 0 (m, standstill gap)", _nonneg)
    max_accel_mps2: float = _f(2.0, "> 0 (m/s^2)", _pos)
    comfort_decel_mps2: float = _f(3.0, "> 0 (m/s^2)", _pos)
    max_decel_mps2: float = _f(8.0, "> 0 (m/s^2, the hardest braking any command asks)", _pos)
    gap_acceptance_s: float = _f(5.0, "> 0 (s: a crossing vehicle arriving sooner blocks the junction)", _pos)
    # with priority, give way to a crossing vehicle that would need more than violator_decel_mps2 to stop before the
    # junction and meets the ego there (a red-light runner), while the ego can still stop (planner find_violator)
    yield_to_violators: bool = True
    violator_decel_mps2: float = _f(6.0, "> 0 (m/s^2)", _pos)


@dataclass(frozen=True)
class SsmConfig:
    """SUMO's SSM device on each driven vehicle (docs/scenario.md "control"): thresholds below (above, for DRAC)
    which an encounter counts as a conflict, and how far it looks. Defaults are SUMO's."""

    ttc_s: float = _f(3.0, "> 0 (s)", _pos)
    drac_mps2: float = _f(3.0, "> 0 (m/s^2)", _pos)
    pet_s: float = _f(2.0, "> 0 (s)", _pos)
    range_m: float = _f(50.0, "> 0 (m)", _pos)


@dataclass(frozen=True)
class ControlConfig:
    """Closed loop (docs/run.md "The closed loop"): each ego's vehicle is driven by a planner that sees only what
    `method` perceived; absent, the run is open loop exactly as before. The plan of frame k is applied at the
    step after frame k + actuation_delay_frames (lockstep: at least transport.pipeline, the frames the driver may
    run ahead of the ego)."""

    method: str = _f("oracle", "'oracle' (ground truth), or one of perception.methods (e.g. none, late, cobevt)")
    drive: Literal["egos"] = "egos"  # every ego's own vehicle; cavs.ego: all drives every CAV
    planner: Literal["idm"] = "idm"
    actuation_delay_frames: int | None = _f(None, "an integer >= transport.pipeline, or null (the least the "
                                            "pipeline allows)", _nonneg)
    idm: IdmConfig = field(default_factory=IdmConfig)
    ssm: SsmConfig = field(default_factory=SsmConfig)
    hard_brake_mps2: float = _f(4.0, "> 0 (m/s^2: a deceleration at least this hard is a hard-braking event)", _pos)
    near_miss_gap_m: float = _f(1.0, ">= 0 (m: a closest footprint gap at most this, without contact, is a near "
                                "miss)", _nonneg)
    phantom_match_m: float = _f(3.0, "> 0 (m: braking for an obstacle with no vehicle this close to it is "
                                "phantom braking)", _pos)
    # jmIgnoreJunctionFoeProb of the background drivers: 0 = SUMO's attentive drivers, who brake for any vehicle
    # already in the junction (so a driven vehicle that pulls out blindly is rarely hit); 1 = they keep their
    # right of way. A modelling choice: the run's report states it.
    background_ignore_junction_foes: float = _f(0.0, "0..1 (probability)", _prob)
    # The route a driven vehicle must complete (its driving score, v2vsim/control/score.py): this many metres along
    # its SUMO route from where it is at frame 0, or null: to the end of that route. A vehicle that completes it
    # leaves the simulation (it arrived); the run's duration is the time limit.
    route_m: float | None = _f(None, "> 0 (m) or null (to the end of the vehicle's SUMO route)", _pos)
    # What the ego computes: `all` of perception.methods (each scored beside the one it drives on), or only what
    # it `driving` on (perception.methods becomes [method]; oracle: [none], the cheapest map that still scores):
    # a benchmark point pays for one method, not eight (docs/benchmark.md).
    perceive: Literal["all", "driving"] = "all"


@dataclass(frozen=True)
class Scenario:
    name: str = "scenario"
    seed: int = _f(0, f"0..{SEED_MAX}", lambda v: 0 <= v <= SEED_MAX)
    duration_s: float = _f(20.0, "> 0", _pos)
    rate_hz: float = _f(10.0, "> 0", _pos)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    cavs: CavsConfig = field(default_factory=CavsConfig)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    bev: BevConfig = field(default_factory=BevConfig)
    comm: CommConfig = field(default_factory=CommConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    control: ControlConfig | None = None  # closed loop when present (docs/scenario.md "control")
    misbehaviour: tuple[Lie, ...] = ()  # CAVs that lie on purpose (an attacked run; docs/scenario.md "misbehaviour")
    defence: DefenceConfig = field(default_factory=DefenceConfig)  # the ego's misbehaviour check (docs: "defence")
    source: str = field(default="<defaults>", metadata={"internal": True})  # the YAML file
    overrides: tuple[str, ...] = field(default=(), metadata={"internal": True})  # --set, for child processes

    @property
    def frames(self) -> int:
        return max(1, round(self.duration_s * self.rate_hz))

    @property
    def dt(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def actuation_delay_frames(self) -> int:
        """Frames between the capture a plan rests on and the step it is applied after (closed loop)."""
        d = None if self.control is None else self.control.actuation_delay_frames
        return self.transport.pipeline if d is None else d

    @property
    def fusion_deadline_s(self) -> float:
        """How long after a frame's capture the ego fuses it: comm.fusion_deadline_ms, or half a frame."""
        ms = self.comm.fusion_deadline_ms
        return 0.5 * self.dt if ms is None else ms / 1000.0

