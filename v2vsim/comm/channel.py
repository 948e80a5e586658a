"""The channel model of one (sender, receiver) link: range, latency, jitter, bandwidth and loss.

Everything here works in seconds of the run's clock (lockstep: simulated seconds), so a
latency is a number the receiver compares with its clock, never a sleep.

Reproducibility: each link draws from its own generator, seeded from (seed, sender, receiver)
through numpy's SeedSequence with the ids' utf-8 bytes as entropy (never Python's salted
hash()), so the same scenario seed gives the same losses and delays in every process and
run, and (a, b) and (b, a) are different links. Every `transmit` call draws the same number
of variates whatever happens, so two runs that differ in, say, drop probability still share
their jitter samples (common random numbers).

comm.channel.model: `disk` (the default) delivers whatever is within comm.range_m unless the drop
model loses it. `tr37885` (v2vsim/comm/tr37885.py) decides reception within range_m from the link
budget, on its own random stream (stream 2), so the disk draws, and hence the jitter and drop
samples, are the same under both models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, TypeVar

import numpy as np

from v2vsim.comm import tr37885
from v2vsim.comm.tr37885 import LinkGeometry, LinkState
from v2vsim.config import CommConfig, PoseNoiseConfig
from v2vsim.world.geometry import Pose

Reason = Literal["ok", "out_of_range", "dropped"]
PoseT = TypeVar("PoseT", Pose, tuple[float, float, float, float])

_STALE_EPS_S = 1e-9  # so that an age of exactly max_age, off by float rounding, is not stale


@dataclass(frozen=True)
class Delivery:
    """What the channel did with one message. arrival_time is inf when nothing arrives.

    Under tr37885, `state` is the link state and `snr_db` the SNR of a message within range (a message lost
    to a low SNR is "dropped"); both are None under disk and for messages out of range."""

    delivered: bool
    reason: Reason
    arrival_time: float
    send_time: float = 0.0
    state: LinkState | None = None
    snr_db: float | None = None

    @property
    def latency(self) -> float:
        """Channel latency in seconds (inf when nothing arrives)."""
        return self.arrival_time - self.send_time if self.delivered else math.inf


def id_entropy(text: str) -> list[int]:
    b = text.encode("utf-8")
    return [len(b), int.from_bytes(b, "little")]


def link_seed_sequence(seed: int, sender: str, receiver: str, stream: int = 0) -> np.random.SeedSequence:
    """A stable SeedSequence for one directed link (and one independent stream on it)."""
    return np.random.SeedSequence([int(seed), 0x76327673, stream, *id_entropy(sender), *id_entropy(receiver)])


def serialisation_delay(size_bytes: int, bandwidth_mbps: float | None) -> float:
    """Seconds to put size_bytes on a link of bandwidth_mbps (decimal megabits); 0 if unlimited."""
    if bandwidth_mbps is None:
        return 0.0
    return size_bytes * 8.0 / (bandwidth_mbps * 1e6)


def data_rate_mbps(cfg: CommConfig) -> float | None:
    """The rate messages are serialised at (Mbps; None = unlimited): comm.bandwidth_mbps, and under tr37885 the
    MCS rate, or bandwidth_mbps where that is lower."""
    if cfg.channel.model != "tr37885":
        return cfg.bandwidth_mbps
    mcs_rate = tr37885.mcs_rate_mbps(cfg.channel.mcs, cfg.channel.bandwidth_mhz)
    return mcs_rate if cfg.bandwidth_mbps is None else min(mcs_rate, cfg.bandwidth_mbps)


def is_stale(capture_time: float, now: float, max_age_ms: float) -> bool:
    """True when a message captured at capture_time is older than max_age_ms at `now`."""
    return (now - capture_time) > max_age_ms / 1000.0 + _STALE_EPS_S


class LinkModel:
    """One directed link. Stateful: the Gilbert-Elliott state (and, with queueing, the time the
    link is busy until) persist across messages, so use one instance per link for a whole run.

    Latency (seconds) = max(0, mean + jitter sample) + size * 8 / bandwidth, where the jitter
    sample has standard deviation `jitter` and mean 0 for every distribution:
      normal      N(0, jitter^2)
      uniform     U(-a, a) with a = jitter * sqrt(3)
      exponential Exp(jitter) - jitter (a right-skewed tail; the mean latency stays `mean`)
    With `queueing`, a message cannot start serialising before the previous one on the link
    has finished (a sender that publishes faster than the link drains falls behind); off by
    default, so each message is delayed only by its own size.

    Loss: "bernoulli" drops each message with probability p; "gilbert_elliott" is a two-state
    Markov chain (good/bad) starting in good: a message is lost with loss_good or loss_bad in
    the current state, then the state moves good->bad with p_gb or bad->good with p_bg. The
    chain steps once per transmit call, in range or not (the radio channel evolves anyway).

    Under comm.channel.model tr37885 a message within range_m must also pass the radio
    (tr37885.receive: link state from `geometry`, path loss, correlated shadowing, SNR against
    the MCS threshold); the drop model still applies on top (a loss the radio does not model,
    e.g. congestion; p = 0 by default). Serialisation runs at the MCS data rate, or at
    bandwidth_mbps where that is lower (the default 27 is the fastest MCS rate, so by default
    the MCS rate decides; null leaves the MCS rate alone). The shadowing steps on every call.
    """

    def __init__(self, cfg: CommConfig, seed: int, sender: str, receiver: str, *, queueing: bool = False) -> None:
        self.cfg = cfg
        self.sender = sender
        self.receiver = receiver
        self.queueing = queueing
        self._rng = np.random.Generator(np.random.PCG64(link_seed_sequence(seed, sender, receiver, 0)))
        self.pose_rng = np.random.Generator(np.random.PCG64(link_seed_sequence(seed, sender, receiver, 1)))
        self.bad_state = False
        self.busy_until = -math.inf
        self.radio = cfg.channel.model == "tr37885"
        self._radio_rng = np.random.Generator(np.random.PCG64(link_seed_sequence(seed, sender, receiver, 2)))
        self.shadowing: tr37885.Shadowing | None = None
        self.rate_mbps = data_rate_mbps(cfg)

    def _jitter_s(self, u: float, z: float) -> float:
        lat = self.cfg.latency_ms
        std = lat.jitter
        if std <= 0:
            return 0.0
        if lat.distribution == "normal":
            j = std * z
        elif lat.distribution == "uniform":
            j = std * math.sqrt(3.0) * (2.0 * u - 1.0)
        elif lat.distribution == "exponential":
            j = -std * math.log1p(-u) - std  # inverse CDF of Exp(scale=std), centred
        else:
            raise ValueError(f"unknown latency distribution {lat.distribution!r}")
        return j / 1000.0

    def _lost(self, u_loss: float, u_state: float) -> bool:
        drop = self.cfg.drop
        if drop.model == "bernoulli":
            return u_loss < drop.p
        if drop.model == "gilbert_elliott":
            lost = u_loss < (drop.loss_bad if self.bad_state else drop.loss_good)
            self.bad_state = (u_state >= drop.p_bg) if self.bad_state else (u_state < drop.p_gb)
            return lost
        raise ValueError(f"unknown drop model {drop.model!r}")

    def transmit(self, size_bytes: int, send_time: float, distance_m: float,
                 geometry: LinkGeometry | None = None, start: float | None = None) -> Delivery:
        """Decide the fate of one message of size_bytes sent at send_time over distance_m.

        `geometry` (the two poses and the world at send time) is required under tr37885 and unused under disk.
        `start`: when serialisation starts, if a shared medium decided it (v2vsim/comm/medium.py)."""
        u_state, u_loss, u_jit = self._rng.random(3)
        z_jit = self._rng.standard_normal()
        lost = self._lost(float(u_loss), float(u_state))
        rx: tr37885.Reception | None = None
        if self.radio:
            if geometry is None:
                raise ValueError("comm.channel.model tr37885 needs the link geometry (sender and receiver poses)")
            z_shadow, z_block = self._radio_rng.standard_normal(2)
            u_rx = float(self._radio_rng.random())
            ch = self.cfg.channel
            self.shadowing = tr37885.step_shadowing(self.shadowing, geometry, tr37885.DECORRELATION_M[ch.scenario],
                                                    float(z_shadow))
            if distance_m <= self.cfg.range_m:  # the geometry is only looked at within range
                rx = tr37885.receive(ch, geometry, self.shadowing, float(z_block), u_rx, (self.sender, self.receiver))
        if not distance_m <= self.cfg.range_m:  # NaN distance counts as out of range
            return Delivery(False, "out_of_range", math.inf, send_time)
        ser = serialisation_delay(size_bytes, self.rate_mbps)
        if start is None:
            start = max(send_time, self.busy_until) if self.queueing else send_time
        self.busy_until = start + ser
        state, snr = (rx.state, rx.snr_db) if rx is not None else (None, None)
        if lost or (rx is not None and not rx.received):
            return Delivery(False, "dropped", math.inf, send_time, state, snr)
        base = max(0.0, self.cfg.latency_ms.mean / 1000.0 + self._jitter_s(float(u_jit), float(z_jit)))
        return Delivery(True, "ok", start + ser + base, send_time, state, snr)

    def noisy_pose(self, pose: PoseT) -> PoseT:
        """The sender pose as the receiver will use it, with this link's pose-noise stream."""
        return noisy_pose(pose, self.cfg.pose_noise, self.pose_rng)


def noisy_pose(pose: PoseT, cfg: PoseNoiseConfig, rng: np.random.Generator) -> PoseT:
    """Add N(0, xy_std) to x and y and N(0, yaw_std) to yaw (OpenCOOD's noisy-pose setting).

    z is left alone. With both stds zero the very same object comes back (bit-identical, no
    draw); otherwise three normals are drawn every call whichever stds are zero.
    """
    if cfg.xy_std_m <= 0 and cfg.yaw_std_deg <= 0:
        return pose
    nx, ny, nyaw = rng.standard_normal(3)
    x, y, z, yaw = pose.as_tuple() if isinstance(pose, Pose) else tuple(pose)
    if cfg.xy_std_m > 0:
        x = float(x + cfg.xy_std_m * nx)
        y = float(y + cfg.xy_std_m * ny)
    if cfg.yaw_std_deg > 0:
        yaw = float(yaw + math.radians(cfg.yaw_std_deg) * nyaw)
    if isinstance(pose, Pose):
        return Pose(x, y, z, yaw)
    return (x, y, z, yaw)
