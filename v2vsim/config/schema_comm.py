"""The scenario schema's `comm` and `transport` sections (DESIGN.md "Scenario YAML"): the channel model between the
CAVs (latency, drops, radio, bandwidth, what is shared and how it is signed) and the zenoh transport under it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from v2vsim.config.schema_fields import _f, _nonneg, _pos, _prob


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
