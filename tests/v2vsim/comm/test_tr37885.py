"""The TR 37.885 channel: path loss per state, link state from the world's geometry, reception against the analytic
curve, shadowing correlation, metrics, config errors; and the disk model left exactly as it was."""

from __future__ import annotations

import hashlib
import math
from dataclasses import replace

import numpy as np
import pytest

from v2vsim.comm.channel import Delivery, LinkModel
from v2vsim.comm.codec import Message
from v2vsim.comm.inbox import Inbox
from v2vsim.comm.stats import CommStats
from v2vsim.comm.tr37885 import (
    LinkClass,
    LinkGeometry,
    Shadowing,
    blockage_loss_db,
    blockage_moments_db,
    classify_link,
    expected_delivery,
    lognormal_params,
    los_path_loss_db,
    mean_snr_db,
    nlos_path_loss_db,
    noise_dbm,
    path_loss_db,
    receive,
    shadowing_step,
    step_shadowing,
    success_probability,
)
from v2vsim.config import ChannelConfig, CommConfig, ConfigError, DropConfig, LatencyConfig, scenario_from_dict
from v2vsim.world.geometry import Pose
from v2vsim.world.state import Actor, Building, StaticMap, WorldState

FC = 5.9
CAR = (4.5, 1.8, 1.5)
TRUCK = (10.0, 2.5, 3.5)


def tr(**kw: object) -> CommConfig:
    """A tr37885 CommConfig: unlimited range and bandwidth unless given."""
    ch = replace(ChannelConfig(model="tr37885"), **{k: v for k, v in kw.items() if hasattr(ChannelConfig, k)})
    base = CommConfig(range_m=10_000.0, bandwidth_mbps=None, channel=ch)
    return replace(base, **{k: v for k, v in kw.items() if not hasattr(ChannelConfig, k)})


def world(actors: tuple[Actor, ...] = (), buildings: tuple[Building, ...] = ()) -> WorldState:
    return WorldState(0.0, 0, actors, StaticMap((), (), (), buildings))


def car(aid: str, x: float, y: float, z: float = 0.0, extent: tuple[float, float, float] = CAR) -> Actor:
    return Actor(aid, "car", aid.startswith("cav"), Pose(x, y, z, 0.0), extent)


def box(bid: str, x0: float, y0: float, x1: float, y1: float, height: float = 10.0) -> Building:
    return Building(bid, np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float), height)


# ---- path loss (TR 37.885 Table 6.2.1-1, written out) ---------------------------------------------------------


@pytest.mark.parametrize("d", [3.0, 25.0, 120.0, 480.0])
def test_path_loss_of_each_state(d: float) -> None:
    lg, lf = math.log10(d), math.log10(FC)
    assert los_path_loss_db(d, FC, "urban") == pytest.approx(38.77 + 16.7 * lg + 18.2 * lf, abs=1e-9)
    assert los_path_loss_db(d, FC, "highway") == pytest.approx(32.4 + 20 * lg + 20 * lf, abs=1e-9)
    assert nlos_path_loss_db(d, FC) == pytest.approx(36.85 + 30 * lg + 18.9 * lf, abs=1e-9)
    assert path_loss_db("nlos", d, FC, "highway") == nlos_path_loss_db(d, FC)
    assert path_loss_db("nlosv", d, FC, "urban") == path_loss_db("los", d, FC, "urban")  # + blockage, drawn apart
    # the numbers themselves, at 100 m urban LOS: 38.77 + 33.4 + 14.0295 (18.2 log10 5.9)
    assert los_path_loss_db(100.0, 5.9, "urban") == pytest.approx(86.1995, abs=1e-3)


def test_blockage_loss_moments_use_the_natural_log() -> None:
    assert blockage_moments_db(10.0, 2) == (9.0, 4.5)  # 15 log10 10 - 41 < 0
    assert blockage_moments_db(1000.0, 2) == pytest.approx((9.0 + 45.0 - 41.0, 4.5))
    assert blockage_moments_db(1000.0, 1) == pytest.approx((5.0 + 4.0, 4.0))
    assert blockage_moments_db(1000.0, 0) == (0.0, 0.0) and blockage_loss_db(50.0, 0, 1.0) == 0.0
    z = np.random.default_rng(0).standard_normal(200_000)
    for d, below in ((30.0, 2), (30.0, 1), (2000.0, 2)):
        mean, std = blockage_moments_db(d, below)
        mu, sigma = lognormal_params(mean, std)
        draws = np.exp(mu + sigma * z)
        assert draws.mean() == pytest.approx(mean, rel=0.01) and draws.std() == pytest.approx(std, rel=0.02)
        assert blockage_loss_db(d, below, float(z[0])) == pytest.approx(draws[0])


# ---- link state from geometry -----------------------------------------------------------------------------------


def test_link_state_from_buildings_and_vehicles() -> None:
    a, b = (0.0, 0.0, 1.5), (60.0, 0.0, 1.5)  # antennas 1.5 m above the ground
    assert classify_link(a, b, None) == LinkClass("los")
    assert classify_link(a, b, world()) == LinkClass("los")
    assert classify_link(a, b, world(buildings=(box("h", 20, -5, 30, 5),))) == LinkClass("nlos")
    assert classify_link(a, b, world(buildings=(box("h", 20, 5, 30, 15),))) == LinkClass("los")  # beside the link
    two_cars = (car("cav1", 0, 0), car("cav0", 60, 0))
    assert classify_link(a, b, world((*two_cars, car("t", 30, 0, extent=TRUCK))), ("cav1", "cav0")) == \
        LinkClass("nlosv", 2)
    assert classify_link(a, b, world((*two_cars, car("c", 30, 0))), ("cav1", "cav0")) == LinkClass("los")  # 1.5 m
    assert classify_link(a, b, world((*two_cars, car("t", 30, 4, extent=TRUCK))), ("cav1", "cav0")) == \
        LinkClass("los")  # a lane over
    # a 2 m van when the receiver stands 1 m higher up (antenna at 2.5 m): only the sender's antenna is below it
    assert classify_link(a, (60.0, 0.0, 2.5), world((car("v", 30, 0, extent=(5.0, 2.0, 2.0)),))) == \
        LinkClass("nlosv", 1)
    # the two ends never block themselves; a building wins over a truck
    assert classify_link(a, b, world((car("cav1", 0, 0, extent=TRUCK),)), ("cav1", "cav0")) == LinkClass("los")
    both = world((car("t", 30, 0, extent=TRUCK),), (box("h", 40, -5, 45, 5),))
    assert classify_link(a, b, both) == LinkClass("nlos")


def test_link_model_reports_the_state_it_saw() -> None:
    w_building = world((car("cav1", 0, 0), car("cav0", 60, 0)), (box("h", 20, -5, 30, 5),))
    w_truck = world((car("cav1", 0, 0), car("cav0", 60, 0), car("t", 30, 0, extent=TRUCK)))
    w_clear = world((car("cav1", 0, 0), car("cav0", 60, 0)))
    link = LinkModel(tr(), 0, "cav1", "cav0")
    states = [link.transmit(1000, 0.1 * i, 60.0, LinkGeometry((0, 0, 0, 0), (60, 0, 0, 0), w)).state
              for i, w in enumerate((w_building, w_truck, w_clear))]
    assert states == ["nlos", "nlosv", "los"]
    out = link.transmit(1000, 1.0, 60.0, LinkGeometry((0, 0, 0, 0), (60, 0, 0, 0), w_clear))
    assert out.snr_db is not None and out.snr_db > 20  # urban LOS at 60 m with the default budget: ~40 dB
    far = LinkModel(tr(range_m=50.0), 0, "cav1", "cav0").transmit(1000, 0.0, 60.0,
                                                                  LinkGeometry((0, 0, 0, 0), (60, 0, 0, 0), w_clear))
    assert far.reason == "out_of_range" and far.state is None  # range_m still bounds what the radio looks at


def test_blocked_links_lose_snr() -> None:
    cfg = tr().channel
    sh = Shadowing(0.0, (0.0, 0.0), (80.0, 0.0))
    geo = {name: LinkGeometry((0, 0, 0, 0), (80, 0, 0, 0), w) for name, w in (
        ("los", world()), ("nlosv", world((car("t", 40, 0, extent=TRUCK),))), ("nlos", world(buildings=(
            box("h", 30, -5, 50, 5),))))}
    rx = {name: receive(cfg, g, sh, 0.0, 0.5) for name, g in geo.items()}
    assert [r.state for r in rx.values()] == ["los", "nlosv", "nlos"]
    mean, std = blockage_moments_db(80.0, 2)
    mu, sigma = lognormal_params(mean, std)
    assert rx["nlosv"].blockage_db == pytest.approx(math.exp(mu))  # the median, z = 0
    assert rx["los"].snr_db - rx["nlosv"].snr_db == pytest.approx(rx["nlosv"].blockage_db)
    assert rx["los"].snr_db - rx["nlos"].snr_db == pytest.approx(nlos_path_loss_db(80.0, FC) -
                                                                 los_path_loss_db(80.0, FC, "urban"))


# ---- reception against the analytic curve -----------------------------------------------------------------------


def analytic_delivery(cfg: ChannelConfig, path_loss: float, shadow_std: float) -> float:
    """E over shadowing S ~ N(0, std) of the logistic P(received | SNR = budget - PL - S) (Gauss-Hermite)."""
    x, w = np.polynomial.hermite_e.hermegauss(60)
    snr = mean_snr_db(cfg, path_loss + shadow_std * x)
    thr = (4.1, 5.6, 6.5, 9.0, 11.7, 15.5, 19.9, 22.0)[cfg.mcs]
    p = 1.0 / (1.0 + np.exp(-(snr - thr) / cfg.per_slope_db))
    return float((w * p).sum() / w.sum())


@pytest.mark.parametrize("state", ["los", "nlos"])
def test_the_reports_expected_curve_is_the_analytic_one(state: str) -> None:
    cfg = ChannelConfig(model="tr37885", mcs=5)
    for d in (20.0, 80.0, 150.0, 300.0):
        pl = path_loss_db(state, d, FC, cfg.scenario)  # type: ignore[arg-type]
        assert expected_delivery(cfg, state, d) == pytest.approx(  # type: ignore[arg-type]
            analytic_delivery(cfg, pl, {"los": 3.0, "nlos": 4.0}[state]), abs=1e-5)


def _sweep(cfg: CommConfig, distances: list[float], n: int, w: WorldState | None
           ) -> tuple[list[float], CommStats, np.ndarray]:
    """Delivery ratio per distance on one link whose ends jump 1 km between messages (independent shadowing);
    also the SNRs, (len(distances), n)."""
    link, stats, ratios, t = LinkModel(cfg, 4, "cav1", "cav0"), CommStats(), [], 0
    snr = np.zeros((len(distances), n))
    for i, d in enumerate(distances):
        ok = 0
        for j in range(n):
            t += 1
            geo = LinkGeometry((-d / 2, 1000.0 * t, 0, 0), (d / 2, 1000.0 * t, 0, 0), w)
            out = link.transmit(1000, 0.1 * t, d, geo)
            stats.record_channel(out, d)
            ok += out.delivered
            snr[i, j] = out.snr_db
        ratios.append(ok / n)
    return ratios, stats, snr


def _check_curve(cfg: CommConfig, distances: list[float], ratios: list[float], snr: np.ndarray, state: str) -> None:
    sigma, n = {"los": 3.0, "nlos": 4.0}[state], snr.shape[1]
    for d, r, s in zip(distances, ratios, snr, strict=True):
        pl = path_loss_db(state, d, FC, cfg.channel.scenario)  # type: ignore[arg-type]
        p = analytic_delivery(cfg.channel, pl, sigma)
        assert abs(r - p) <= 4 * math.sqrt(p * (1 - p) / n) + 0.01, (d, r, p)
        assert abs(s.mean() - mean_snr_db(cfg.channel, pl)) < 4 * sigma / math.sqrt(n)  # shadowing has mean 0
    assert (snr - snr.mean(axis=1, keepdims=True)).std() == pytest.approx(sigma, rel=0.06)  # TR 37.885 sigma
    for near, far in zip(ratios[:-1], ratios[1:], strict=True):  # monotone, up to sampling noise
        assert far <= near + 0.08
    assert ratios[0] > 0.9 and ratios[-1] < 0.1


def test_los_delivery_over_distance_matches_the_analytic_curve() -> None:
    cfg = tr(tx_power_dbm=-8.0)  # low power, so the urban LOS waterfall falls within a few hundred metres
    distances, n = [20.0, 60.0, 90.0, 120.0, 160.0, 250.0, 400.0], 300
    ratios, stats, snr = _sweep(cfg, distances, n, None)
    _check_curve(cfg, distances, ratios, snr, "los")
    by = stats.to_json()["delivery_by_distance"]["los"]
    assert by["0-25"] == {"sent": n, "delivered": round(ratios[0] * n), "ratio": round(ratios[0], 4)}
    assert stats.to_json()["los"] == n * len(distances) and stats.to_json()["nlos"] == 0


def test_nlos_delivery_behind_a_building_matches_the_analytic_curve() -> None:
    wall = world(buildings=(box("wall", -1.0, -1e7, 1.0, 1e7),))  # every link crosses it
    cfg = tr()  # default budget: NLOS reception fades out around 150 m
    distances, n = [40.0, 90.0, 130.0, 160.0, 200.0, 300.0], 300
    ratios, stats, snr = _sweep(cfg, distances, n, wall)
    _check_curve(cfg, distances, ratios, snr, "nlos")
    assert stats.to_json()["nlos"] == n * len(distances)


# ---- shadowing --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("scenario", "d_corr"), [("urban", 10.0), ("highway", 25.0)])
def test_shadowing_autocorrelation_at_the_decorrelation_distance(scenario: str, d_corr: float) -> None:
    link, n = LinkModel(tr(scenario=scenario), 1, "cav1", "cav0"), 6000
    snr = np.array([link.transmit(100, 0.1 * i, 50.0, LinkGeometry((d_corr * i, 0, 0, 0), (d_corr * i + 50, 0, 0, 0)))
                    .snr_db for i in range(n)])
    assert snr.std() == pytest.approx(3.0, rel=0.06)  # LOS shadowing std
    assert np.corrcoef(snr[:-1], snr[1:])[0, 1] == pytest.approx(math.exp(-1), abs=0.04)
    # the pure step: at dd = D the correlation is e^-1, standing still it is 1
    rng = np.random.default_rng(2)
    x0 = rng.standard_normal(100_000)
    x1 = shadowing_step(x0, d_corr, d_corr, rng.standard_normal(100_000))  # type: ignore[arg-type]
    assert np.corrcoef(x0, x1)[0, 1] == pytest.approx(math.exp(-1), abs=0.01) and np.std(x1) == pytest.approx(1, 0.01)
    assert shadowing_step(0.7, 0.0, d_corr, 1.3) == 0.7


def test_link_budget() -> None:
    assert noise_dbm(10.0, 9.0) == pytest.approx(-174 + 70 + 9)  # -95 dBm
    assert noise_dbm(20.0, 0.0) == pytest.approx(-174 + 73.0103, abs=1e-4)
    # 23 dBm + 2 x 3 dBi - 100 dB - (-95 dBm) = 24 dB
    assert mean_snr_db(ChannelConfig(), 100.0) == pytest.approx(24.0)
    assert mean_snr_db(ChannelConfig(tx_power_dbm=10.0, antenna_gain_dbi=0.0, noise_figure_db=5.0), 90.0) == \
        pytest.approx(10.0 - 90.0 + 99.0)


def test_packet_error_curve() -> None:
    assert success_probability(6.5, 6.5, 1.0) == 0.5  # PER 0.5 at the MCS threshold
    assert success_probability(8.5, 6.5, 1.0) == pytest.approx(1 / (1 + math.exp(-2)))
    assert success_probability(3.5, 6.5, 1.5) == pytest.approx(1 / (1 + math.exp(2)))
    assert success_probability(np.array([6.4, 6.5, 9.0]), 6.5, 0.0).tolist() == [0.0, 1.0, 1.0]  # a hard threshold
    assert success_probability(-1e6, 6.5, 0.1) == 0.0 and success_probability(1e6, 6.5, 0.1) == 1.0  # no overflow


def test_shadowing_moves_with_the_end_that_moved_most() -> None:
    z, d_corr = 0.8, 10.0
    first = step_shadowing(None, LinkGeometry((0, 0, 0, 0), (50, 0, 0, 0)), d_corr, 1.2)
    assert first.x == 1.2  # the stationary N(0, 1) draw
    moved = step_shadowing(first, LinkGeometry((0, 10, 0, 0), (50, 4, 0, 0)), d_corr, z)  # dd = max(10, 4)
    assert moved.x == pytest.approx(math.exp(-1) * 1.2 + math.sqrt(1 - math.exp(-2)) * z)
    assert step_shadowing(moved, LinkGeometry((0, 10, 0, 0), (50, 4, 0, 0)), d_corr, z).x == moved.x  # standing


def test_kinds_share_fates_and_the_radio_has_its_own_stream() -> None:
    geo = [LinkGeometry((3.0 * i, 0, 0, 0), (3.0 * i + 180, 0, 0, 0), world(buildings=(box("h", 3 * i + 80, -5,
                                                                                          3 * i + 90, 5),)))
           for i in range(200)]
    a, b = LinkModel(tr(), 9, "cav2", "cav0"), LinkModel(tr(), 9, "cav2", "cav0")
    fa = [a.transmit(65_000, 0.1 * i, 180.0, g).delivered for i, g in enumerate(geo)]
    fb = [b.transmit(300, 0.1 * i, 180.0, g).delivered for i, g in enumerate(geo)]
    assert fa == fb and 0 < sum(fa) < len(fa)  # same losses whatever the message size
    # the disk draws are untouched: the jitter under tr37885 equals the disk one where both deliver
    lat = LatencyConfig(mean=40.0, jitter=10.0)
    disk = LinkModel(CommConfig(range_m=1e4, bandwidth_mbps=None, latency_ms=lat), 9, "cav2", "cav0")
    radio = LinkModel(tr(latency_ms=lat), 9, "cav2", "cav0")
    for i, g in enumerate(geo):
        x, y = disk.transmit(600, 0.1 * i, 180.0), radio.transmit(600, 0.1 * i, 180.0, g)
        if y.delivered:
            assert y.latency == pytest.approx(x.latency + 600 * 8 / 6e6)  # + serialisation at MCS 2 (6 Mbps)


def test_serialisation_at_the_mcs_rate() -> None:
    geo = LinkGeometry((0, 0, 0, 0), (10, 0, 0, 0))
    assert LinkModel(tr(), 0, "a", "b").transmit(6000, 0.0, 10.0, geo).latency == pytest.approx(0.008)  # 6 Mbps
    assert LinkModel(tr(mcs=7), 0, "a", "b").transmit(27_000, 0.0, 10.0, geo).latency == pytest.approx(0.008)
    assert LinkModel(tr(bandwidth_mhz=20.0), 0, "a", "b").transmit(12_000, 0.0, 10.0, geo).latency == \
        pytest.approx(0.008)  # 12 Mbps at 20 MHz
    assert LinkModel(tr(bandwidth_mbps=3.0), 0, "a", "b").transmit(3000, 0.0, 10.0, geo).latency == \
        pytest.approx(0.008)  # a lower bandwidth_mbps caps it
    with pytest.raises(ValueError, match="geometry"):
        LinkModel(tr(), 0, "a", "b").transmit(10, 0.0, 10.0)


# ---- disk is unchanged ------------------------------------------------------------------------------------------


def _disk_cfg() -> CommConfig:
    return CommConfig(range_m=70.0, bandwidth_mbps=27.0, latency_ms=LatencyConfig(mean=40.0, jitter=8.0),
                      drop=DropConfig(model="gilbert_elliott", p_gb=0.1, p_bg=0.3, loss_good=0.05, loss_bad=0.8))


def _disk_run(geometry: bool) -> list[Delivery]:
    link = LinkModel(_disk_cfg(), 11, "cav1", "cav0", queueing=True)
    truck = world((car("t", 30, 0, extent=TRUCK),), (box("h", 10, -5, 20, 5),))
    return [link.transmit(60_000 + 7 * i, 0.1 * i, 55.0 + 10.0 * ((i * 7) % 5),
                          LinkGeometry((0, 0, 0, 0), (60, 0, 0, 0), truck) if geometry else None) for i in range(300)]


def test_disk_model_gives_the_same_deliveries_as_before() -> None:
    out = _disk_run(False)
    text = ";".join(f"{d.delivered},{d.reason},{d.arrival_time!r},{d.send_time!r}" for d in out)
    # recorded from the channel before tr37885 existed (commit 96b401a)
    golden = "9efa10a505c3911d45284626eb156787436fa62960e3f649eb812434d4828baa"
    assert hashlib.sha256(text.encode()).hexdigest() == golden
    assert [(d.reason, d.arrival_time) for d in out[:4]] == [("ok", 0.0683620631099687), ("out_of_range", math.inf),
                                                             ("out_of_range", math.inf), ("ok", 0.3544869653559113)]
    assert out == _disk_run(True)  # disk ignores any geometry
    assert all(d.state is None and d.snr_db is None for d in out)


def _msg(sender: str, frame: int, pose: tuple[float, float, float, float]) -> Message:
    return Message(kind="features", run_id="r", sender_id=sender, frame=frame, capture_time=frame * 0.1,
                   sender_pose=pose, payload=np.zeros((2, 4, 4), np.float16))


def test_inbox_disk_output_unchanged_and_tr37885_metrics() -> None:
    w = world((car("cav1", 0, 0), car("cav0", 40, 0), car("t", 20, 0, extent=TRUCK)), (box("h", 5, 8, 15, 12),))
    plain = Inbox(CommConfig(), 0, "cav0", "features")
    given = Inbox(CommConfig(), 0, "cav0", "features")
    radio = Inbox(replace(CommConfig(), channel=ChannelConfig(model="tr37885")), 0, "cav0", "features")
    assert radio.stats.to_json()["los"] == 0  # the keys are there before any message
    assert radio.stats.to_json()["delivery_by_distance"] == {"los": {}, "nlos": {}, "nlosv": {}}
    for k in range(20):
        sender = (0.0, 10.0 * (k % 3 == 0), 0.0, 0.0)  # every third frame behind the building: NLOS
        plain.offer(_msg("cav1", k, sender), 100, 0.1 * k, 40.0)
        given.offer(_msg("cav1", k, sender), 100, 0.1 * k, 40.0, receiver_pose=(40.0, 10.0, 0.0, 0.0), world=w)
        radio.offer(_msg("cav1", k, sender), 100, 0.1 * k, 40.0, receiver_pose=(40.0, 10.0 * (k % 3 == 0), 0.0, 0.0),
                    world=w)
    assert plain.stats.to_json() == given.stats.to_json() and "los" not in plain.stats.to_json()
    assert plain.take_events() == given.take_events()
    j = radio.stats.to_json()
    assert (j["los"], j["nlos"], j["nlosv"]) == (0, 7, 13)
    assert set(j["delivery_by_distance"]["nlosv"]) == {"25-50"} and j["delivery_by_distance"]["nlosv"]["25-50"][
        "sent"] == 13
    with pytest.raises(ValueError, match="receiver_pose"):
        radio.offer(_msg("cav1", 30, (0.0, 0.0, 0.0, 0.0)), 100, 3.0, 40.0)


# ---- config -----------------------------------------------------------------------------------------------------


def test_channel_config_defaults_and_errors() -> None:
    base = {"traffic": {"backend": "highway-env"}}
    sc = scenario_from_dict(base)
    assert sc.comm.channel == ChannelConfig() and sc.comm.channel.model == "disk"
    sc = scenario_from_dict({**base, "comm": {"channel": {"model": "tr37885", "scenario": "highway", "mcs": 4}}})
    assert (sc.comm.channel.model, sc.comm.channel.scenario, sc.comm.channel.mcs) == ("tr37885", "highway", 4)
    for bad, expect in (({"model": "tr38901"}, ["comm.channel.model", "'disk' | 'tr37885'"]),
                        ({"model": "tr37886"}, ["comm.channel.model", "did you mean 'tr37885'"]),
                        ({"scenario": "rural"}, ["comm.channel.scenario", "'urban' | 'highway'"]),
                        ({"mcs": 8}, ["comm.channel.mcs", "0..7"]),
                        ({"bandwidth_mhz": 15}, ["comm.channel.bandwidth_mhz", "5, 10 or 20"]),
                        ({"per_slope_db": -1}, ["comm.channel.per_slope_db", ">= 0"]),
                        ({"antena_height_m": 2}, ["comm.channel.antena_height_m", "did you mean 'antenna_height_m'"])):
        with pytest.raises(ConfigError) as e:
            scenario_from_dict({**base, "comm": {"channel": bad}}, source="s.yaml")
        for part in ["s.yaml", *expect]:
            assert part in str(e.value), str(e.value)
