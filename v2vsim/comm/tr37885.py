"""A geometry-aware V2V channel after 3GPP TR 37.885: link state from the world, path loss, shadowing, reception.

Per message on one directed link (all pure functions; the caller keeps the shadowing state):
  1. state   the 2D segment between the antennas crosses a building footprint -> "nlos"; else a vehicle (not the
             sender or receiver) whose roof is above the lower antenna -> "nlosv"; else "los".
  2. loss    TR 37.885 Table 6.2.1-1 path loss of that state at the 3D antenna distance, plus for nlosv a
             log-normal vehicle blockage loss, plus spatially correlated log-normal shadowing.
  3. SNR     tx power + 2 antenna gains - loss - (thermal noise + noise figure); no interference.
  4. fate    received with probability 1 / (1 + exp(-(SNR - threshold) / slope)) for the 802.11p MCS in use
             (PER 0.5 at the threshold; slope 0 is a hard threshold).

Units: metres, dB, dBm, GHz, MHz, Mbps. Where a constant comes from is said beside it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import shapely

from v2vsim.config import ChannelConfig
from v2vsim.world.state import StaticMap, WorldState

LinkState = Literal["los", "nlos", "nlosv"]
LINK_STATES: tuple[LinkState, ...] = ("los", "nlos", "nlosv")

# Thermal noise density kT0 (Boltzmann constant, standard noise temperature T0 = 290 K) in dBm/Hz.
THERMAL_NOISE_DBM_PER_HZ = -174.0
# The link-budget defaults live in config.ChannelConfig: 23 dBm, 3 dBi per antenna, 9 dB noise figure, 10 MHz,
# antennas 1.5 m up (the LTE/NR V2X evaluation assumptions of TR 36.885 Annex A, reused by TR 37.885 clause 6),
# carrier 5.9 GHz (the ITS band 5.855-5.925 GHz of ETSI EN 302 663).
# IEEE 802.11p (802.11-2016 clause 17, OFDM PHY) MCS 0..7 = BPSK 1/2, BPSK 3/4, QPSK 1/2, QPSK 3/4, 16-QAM 1/2,
# 16-QAM 3/4, 64-QAM 2/3, 64-QAM 3/4. Data rates for a 10 MHz channel (ETSI ITS-G5, EN 302 663): IEEE
# 802.11-2016 Table 17-4; they scale with the channel width (5 / 20 MHz halve / double them).
MCS_RATE_MBPS_10MHZ = (3.0, 4.5, 6.0, 9.0, 12.0, 18.0, 24.0, 27.0)
# SNR (dB) at which the packet error rate is 0.5 here, per MCS: the 802.11p / ITS-G5 10 MHz reception thresholds
# given in the issue (values as specified there, not re-derived from the standard).
MCS_SNR_THRESHOLD_DB = (4.1, 5.6, 6.5, 9.0, 11.7, 15.5, 19.9, 22.0)
# Shadow-fading standard deviation (dB) per state: TR 37.885 Table 6.2.1-1 (3 dB LOS and NLOSv, 4 dB NLOS).
SHADOW_STD_DB: dict[str, float] = {"los": 3.0, "nlosv": 3.0, "nlos": 4.0}
# Shadowing decorrelation distance (m): 10 m urban, 25 m highway (TR 37.885 Table 6.2.1-1, as in TR 36.885
# Annex A). ns-3's V2V model instead uses 10 m LOS / 13 m NLOS(v) for urban, citing TR 37.885 Table 6.2.3-1.
DECORRELATION_M: dict[str, float] = {"urban": 10.0, "highway": 25.0}
# Vehicle blockage loss (TR 37.885 section 6.2.1, NLOSv): log-normal with mean base + max(0, 15 log10 d - 41) dB.
BLOCKAGE_BOTH_BELOW_DB = (9.0, 4.5)  # (base mean, std): both antennas below the blocker's roof
BLOCKAGE_ONE_BELOW_DB = (5.0, 4.0)  # one antenna below it
# Not from the TR: the path-loss fits are for tens to hundreds of metres; closer than this counts as this.
MIN_DISTANCE_M = 1.0


# ---- path loss (TR 37.885 Table 6.2.1-1; d: 3D distance in m, fc in GHz) --------------------------------------


def los_path_loss_db(d_m: float, fc_ghz: float, scenario: str) -> float:
    """LOS: urban 38.77 + 16.7 log10 d + 18.2 log10 fc; highway 32.4 + 20 log10 d + 20 log10 fc."""
    d = max(d_m, MIN_DISTANCE_M)
    if scenario == "urban":
        return 38.77 + 16.7 * math.log10(d) + 18.2 * math.log10(fc_ghz)
    if scenario == "highway":
        return 32.4 + 20.0 * math.log10(d) + 20.0 * math.log10(fc_ghz)
    raise ValueError(f"unknown scenario {scenario!r}")


def nlos_path_loss_db(d_m: float, fc_ghz: float) -> float:
    """NLOS (buildings; the TR gives it for urban, and it is used for any scenario here): 36.85 + 30 log10 d +
    18.9 log10 fc."""
    d = max(d_m, MIN_DISTANCE_M)
    return 36.85 + 30.0 * math.log10(d) + 18.9 * math.log10(fc_ghz)


def path_loss_db(state: LinkState, d_m: float, fc_ghz: float, scenario: str) -> float:
    """The deterministic path loss of a state; NLOSv is the LOS loss here (its blockage loss is drawn apart)."""
    return nlos_path_loss_db(d_m, fc_ghz) if state == "nlos" else los_path_loss_db(d_m, fc_ghz, scenario)


def blockage_moments_db(d_m: float, below: int) -> tuple[float, float]:
    """(mean, std) in dB of the NLOSv vehicle blockage loss with `below` (0, 1, 2) antennas under the blocker's
    roof: 9 + max(0, 15 log10 d - 41), 4.5 for both; 5 + max(0, 15 log10 d - 41), 4 for one; 0 for neither."""
    if below <= 0:
        return 0.0, 0.0
    base, std = BLOCKAGE_BOTH_BELOW_DB if below >= 2 else BLOCKAGE_ONE_BELOW_DB
    return base + max(0.0, 15.0 * math.log10(max(d_m, MIN_DISTANCE_M)) - 41.0), std


def lognormal_params(mean: float, std: float) -> tuple[float, float]:
    """(mu, sigma) of ln X for a log-normal X with this mean and std (natural log, so E[X] and std[X] come out
    exactly; ns-3 uses log10 here, which does not): mu = ln(m^2 / sqrt(s^2 + m^2)), sigma = sqrt(ln(1 + s^2/m^2))."""
    return math.log(mean * mean / math.sqrt(std * std + mean * mean)), math.sqrt(math.log1p(std * std / (mean * mean)))


def blockage_loss_db(d_m: float, below: int, z: float) -> float:
    """One draw of the blockage loss (dB) from a standard normal z (0 when no antenna is below the blocker)."""
    mean, std = blockage_moments_db(d_m, below)
    if mean <= 0:
        return 0.0
    mu, sigma = lognormal_params(mean, std)
    return math.exp(mu + sigma * z)


# ---- shadowing --------------------------------------------------------------------------------------------------


def shadowing_step(x: float | None, moved_m: float, decorrelation_m: float, z: float) -> float:
    """Next value of the link's unit-variance shadowing process: x' = r x + sqrt(1 - r^2) z with r = exp(-dd/D)
    (Gudmundson's exponential autocorrelation, as TR 37.885 specifies shadowing by a decorrelation distance).
    The first message draws from the stationary N(0, 1). Shadowing in dB is SHADOW_STD_DB[state] * x, so a
    change of state keeps the correlation and only rescales."""
    if x is None or not math.isfinite(moved_m):
        return z
    r = math.exp(-max(moved_m, 0.0) / decorrelation_m)
    return r * x + math.sqrt(max(0.0, 1.0 - r * r)) * z


# ---- link budget and reception ----------------------------------------------------------------------------------


def noise_dbm(bandwidth_mhz: float, noise_figure_db: float) -> float:
    """Receiver noise power: -174 dBm/Hz + 10 log10 B + NF."""
    return THERMAL_NOISE_DBM_PER_HZ + 10.0 * math.log10(bandwidth_mhz * 1e6) + noise_figure_db


def mcs_rate_mbps(mcs: int, bandwidth_mhz: float) -> float:
    """The 802.11p data rate of an MCS at this channel width (Table 17-4 rates scale with the width)."""
    return MCS_RATE_MBPS_10MHZ[mcs] * bandwidth_mhz / 10.0


def success_probability(snr_db: float | np.ndarray, threshold_db: float, slope_db: float) -> float | np.ndarray:
    """P(received) = 1 / (1 + exp(-(snr - threshold) / slope)): 0.5 at the threshold, 0.88 / 0.12 at +-2 slopes.
    The logistic is a smooth stand-in for the measured 802.11p PER-vs-SNR waterfall (a few dB from 10 % to 90 %);
    slope 0 is a hard threshold (received iff snr >= threshold)."""
    snr = np.asarray(snr_db, dtype=float)
    if slope_db <= 0:
        p = (snr >= threshold_db).astype(float)
    else:
        p = 0.5 * (1.0 + np.tanh((snr - threshold_db) / (2.0 * slope_db)))  # the logistic, without exp overflow
    return float(p) if p.ndim == 0 else p


def mean_snr_db(cfg: ChannelConfig, loss_db: float) -> float:
    """SNR (dB) for a total loss (path loss + blockage + shadowing) under cfg's link budget."""
    return cfg.tx_power_dbm + 2.0 * cfg.antenna_gain_dbi - loss_db - noise_dbm(cfg.bandwidth_mhz, cfg.noise_figure_db)


def expected_delivery(cfg: ChannelConfig, state: LinkState, d_m: float) -> float:
    """P(received) at distance d_m in a LOS or NLOS state, averaged over the shadowing N(0, SHADOW_STD_DB)
    (Gauss-Hermite): the curve the delivery ratio of many independent links follows. NLOSv is not given: it
    depends on the blocker's height (how many antennas are below it)."""
    if state == "nlosv":
        raise ValueError("expected_delivery: NLOSv depends on the blocker; only los and nlos")
    x, w = np.polynomial.hermite_e.hermegauss(60)
    loss = path_loss_db(state, max(d_m, MIN_DISTANCE_M), cfg.carrier_ghz, cfg.scenario) + SHADOW_STD_DB[state] * x
    p = success_probability(mean_snr_db(cfg, loss), MCS_SNR_THRESHOLD_DB[cfg.mcs], cfg.per_slope_db)  # type: ignore[arg-type]
    return float((w * p).sum() / w.sum())


# ---- link state from the world's geometry -----------------------------------------------------------------------


@dataclass(frozen=True)
class LinkGeometry:
    """Where the two vehicles were when a message was sent: poses (x, y, z, yaw) on the ground (z = the ground
    under the vehicle, antennas are antenna_height_m above it) and the world whose buildings and vehicles may
    stand between them (None: an empty world)."""

    sender: tuple[float, ...]
    receiver: tuple[float, ...]
    world: WorldState | None = None


@dataclass(frozen=True)
class LinkClass:
    """A link's state; `below`: for nlosv, how many antennas (1 or 2) are under the tallest blocker's roof."""

    state: LinkState
    below: int = 0


@dataclass(frozen=True)
class _Index:
    tree: shapely.STRtree
    ids: tuple[str, ...]
    tops: np.ndarray  # roof height (z) of each geometry


_CACHE_SIZE = 8
_cache: dict[tuple[str, int], tuple[object, _Index]] = {}  # (what, id(obj)) -> (obj, index); obj kept alive


def _memo(what: str, obj: Any, build: Callable[[Any], _Index]) -> _Index:
    """A small identity memo: a map's buildings are indexed once, a world tick's vehicles once for all links."""
    key = (what, id(obj))
    hit = _cache.get(key)
    if hit is not None and hit[0] is obj:
        return hit[1]
    index = build(obj)
    if len(_cache) >= _CACHE_SIZE:
        _cache.pop(next(iter(_cache)))
    _cache[key] = (obj, index)
    return index


def _building_index(static: StaticMap) -> _Index:
    polys = shapely.polygons([np.asarray(b.polygon, dtype=float) for b in static.buildings]) if static.buildings \
        else np.empty(0, dtype=object)
    return _Index(shapely.STRtree(polys), tuple(b.id for b in static.buildings),
                  np.array([b.height for b in static.buildings], dtype=float))


def _vehicle_index(world: WorldState) -> _Index:
    actors = world.actors
    corners = np.stack([a.footprint() for a in actors]) if actors else np.empty((0, 4, 2))
    polys = shapely.polygons(corners) if actors else np.empty(0, dtype=object)
    return _Index(shapely.STRtree(polys), tuple(a.id for a in actors),
                  np.array([a.pose.z + a.extent[2] for a in actors], dtype=float))


def classify_link(a: tuple[float, float, float], b: tuple[float, float, float], world: WorldState | None,
                  exclude: tuple[str, ...] = ()) -> LinkClass:
    """The state of the link between antennas a and b ((x, y, z) each, z = antenna height in the world frame).

    Buildings and vehicles are vertical prisms: the 2D segment a-b crossing (or touching) any building footprint
    is "nlos" whatever the heights (TR 37.885 NLOS: blocked by buildings); else crossing the footprint of a vehicle
    (other than those in `exclude`, the two ends) whose roof is above the lower antenna is "nlosv", with `below`
    the most antennas under any such roof; else "los"."""
    if world is None:
        return LinkClass("los")
    line = shapely.linestrings([[a[0], a[1]], [b[0], b[1]]])
    if world.static.buildings:
        if _memo("buildings", world.static, _building_index).tree.query(line, predicate="intersects").size:
            return LinkClass("nlos")
    if not world.actors:
        return LinkClass("los")
    vehicles = _memo("vehicles", world, _vehicle_index)
    below = 0  # > 0 exactly when some crossing vehicle's roof is above the lower antenna
    for i in vehicles.tree.query(line, predicate="intersects"):
        if vehicles.ids[i] not in exclude:
            top = vehicles.tops[i]
            below = max(below, int(a[2] < top) + int(b[2] < top))
    return LinkClass("nlosv", below) if below else LinkClass("los")


def antenna(pose: tuple[float, ...], height_m: float) -> tuple[float, float, float]:
    """The antenna position of a vehicle at pose (x, y, z, yaw): height_m above pose.z (antenna on the roof
    centre; its horizontal offset is below the model's resolution)."""
    return (float(pose[0]), float(pose[1]), float(pose[2]) + height_m)


# ---- one message ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Shadowing:
    """A link's shadowing state: the unit-variance process value and where its two ends were when it was drawn."""

    x: float
    sender_xy: tuple[float, float]
    receiver_xy: tuple[float, float]


@dataclass(frozen=True)
class Reception:
    """What the radio did to one message: state, 3D distance (m), losses and SNR (dB), P(received), the verdict."""

    state: LinkState
    distance_m: float
    path_loss_db: float
    blockage_db: float
    shadowing_db: float
    snr_db: float
    p_received: float
    received: bool


def step_shadowing(prev: Shadowing | None, geometry: LinkGeometry, decorrelation_m: float, z: float) -> Shadowing:
    """Advance the link's shadowing to this message; dd = the larger of the two ends' displacements since the last."""
    s_xy = (float(geometry.sender[0]), float(geometry.sender[1]))
    r_xy = (float(geometry.receiver[0]), float(geometry.receiver[1]))
    if prev is None:
        return Shadowing(shadowing_step(None, math.inf, decorrelation_m, z), s_xy, r_xy)
    moved = max(math.dist(s_xy, prev.sender_xy), math.dist(r_xy, prev.receiver_xy))
    return Shadowing(shadowing_step(prev.x, moved, decorrelation_m, z), s_xy, r_xy)


def receive(cfg: ChannelConfig, geometry: LinkGeometry, shadow: Shadowing, z_blockage: float, u: float,
            exclude: tuple[str, ...] = ()) -> Reception:
    """Decide one message: classify the link, sum the losses, and receive it iff u < P(received)."""
    a, b = antenna(geometry.sender, cfg.antenna_height_m), antenna(geometry.receiver, cfg.antenna_height_m)
    link = classify_link(a, b, geometry.world, exclude)
    d = math.dist(a, b)
    pl = path_loss_db(link.state, d, cfg.carrier_ghz, cfg.scenario)
    block = blockage_loss_db(d, link.below, z_blockage) if link.state == "nlosv" else 0.0
    shadow_db = SHADOW_STD_DB[link.state] * shadow.x
    snr = mean_snr_db(cfg, pl + block + shadow_db)
    p = float(success_probability(snr, MCS_SNR_THRESHOLD_DB[cfg.mcs], cfg.per_slope_db))
    return Reception(link.state, d, pl, block, shadow_db, snr, p, u < p)
