"""Channel model: loss rates, burst lengths, latency, bandwidth, range, staleness, pose noise, seeds."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from v2vsim.comm.channel import LinkModel, is_stale, noisy_pose, serialisation_delay
from v2vsim.config import CommConfig, DropConfig, LatencyConfig, PoseNoiseConfig
from v2vsim.world.geometry import Pose


def comm(**kw) -> CommConfig:
    base = CommConfig(bandwidth_mbps=None, range_m=70.0)
    return replace(base, **kw)


def run(link: LinkModel, n: int, size: int = 1000, distance: float = 10.0, dt: float = 0.1):
    return [link.transmit(size, i * dt, distance) for i in range(n)]


def test_bernoulli_rate() -> None:
    link = LinkModel(comm(drop=DropConfig(model="bernoulli", p=0.3)), seed=0, sender="cav1", receiver="cav0")
    out = run(link, 10_000)
    rate = sum(d.delivered for d in out) / len(out)
    assert abs(rate - 0.70) <= 0.02
    assert {d.reason for d in out} == {"ok", "dropped"}
    assert all(math.isinf(d.arrival_time) for d in out if not d.delivered)


def test_gilbert_elliott_burst_length() -> None:
    p_gb, p_bg = 0.05, 0.25
    cfg = comm(drop=DropConfig(model="gilbert_elliott", p_gb=p_gb, p_bg=p_bg, loss_good=0.0, loss_bad=1.0))
    lost = [not d.delivered for d in run(LinkModel(cfg, 3, "a", "b"), 50_000)]
    bursts, cur = [], 0
    for x in lost:
        if x:
            cur += 1
        elif cur:
            bursts.append(cur)
            cur = 0
    assert len(bursts) > 1000
    assert abs(np.mean(bursts) - 1 / p_bg) <= 0.1 / p_bg
    # stationary loss rate p_gb / (p_gb + p_bg)
    assert abs(np.mean(lost) - p_gb / (p_gb + p_bg)) < 0.02


def test_gilbert_elliott_bursts_longer_than_bernoulli_at_same_rate() -> None:
    ge = comm(drop=DropConfig(model="gilbert_elliott", p_gb=0.02, p_bg=0.1, loss_good=0.0, loss_bad=1.0))
    lost = np.array([not d.delivered for d in run(LinkModel(ge, 0, "a", "b"), 20_000)])
    both = lost[1:] & lost[:-1]
    assert both.mean() / lost.mean() > 0.8  # P(loss | previous loss) ~ 0.9, Bernoulli would give ~0.17


@pytest.mark.parametrize("dist", ["normal", "uniform", "exponential"])
def test_latency_distribution(dist: str) -> None:
    cfg = comm(latency_ms=LatencyConfig(mean=100.0, jitter=20.0, distribution=dist))
    out = run(LinkModel(cfg, 1, "cav1", "cav0"), 10_000)
    lat_ms = np.array([d.latency for d in out]) * 1000
    assert abs(lat_ms.mean() - 100) < 2
    assert abs(lat_ms.std() - 20) < 2
    assert lat_ms.min() >= 0
    if dist == "normal":
        assert abs(np.percentile(lat_ms, 50) - 100) <= 5


def test_latency_never_negative() -> None:
    cfg = comm(latency_ms=LatencyConfig(mean=5.0, jitter=20.0))
    out = run(LinkModel(cfg, 1, "x", "y"), 2000)
    assert min(d.arrival_time - d.send_time for d in out) >= 0
    fixed = run(LinkModel(comm(latency_ms=LatencyConfig(mean=30.0)), 1, "x", "y"), 10)
    assert all(d.latency == pytest.approx(0.030, abs=1e-12) for d in fixed)


def test_bandwidth_serialisation_delay() -> None:
    assert serialisation_delay(1_000_000, 27.0) == pytest.approx(8 / 27, rel=1e-12)
    assert serialisation_delay(1_000_000, None) == 0.0
    link = LinkModel(comm(bandwidth_mbps=27.0), 0, "a", "b")
    d = link.transmit(1_000_000, 2.0, 5.0)
    assert d.delivered and abs((d.arrival_time - 2.0) - 0.296) <= 0.001
    # bandwidth adds to latency
    both = LinkModel(comm(bandwidth_mbps=27.0, latency_ms=LatencyConfig(mean=100.0)), 0, "a", "b")
    assert both.transmit(1_000_000, 0.0, 5.0).latency == pytest.approx(0.1 + 8 / 27)


def test_queueing_option() -> None:
    link = LinkModel(comm(bandwidth_mbps=8.0), 0, "a", "b", queueing=True)
    a, b = link.transmit(1_000_000, 0.0, 1.0), link.transmit(1_000_000, 0.0, 1.0)
    assert a.arrival_time == pytest.approx(1.0) and b.arrival_time == pytest.approx(2.0)
    plain = LinkModel(comm(bandwidth_mbps=8.0), 0, "a", "b")
    assert plain.transmit(1_000_000, 0.0, 1.0).arrival_time == plain.transmit(1_000_000, 0.0, 1.0).arrival_time


def test_range() -> None:
    link = LinkModel(comm(range_m=70.0), 0, "a", "b")
    assert link.transmit(10, 0.0, 70.0).reason == "ok"
    far = link.transmit(10, 0.0, 70.01)
    assert not far.delivered and far.reason == "out_of_range" and math.isinf(far.arrival_time)
    assert link.transmit(10, 0.0, float("nan")).reason == "out_of_range"


def test_stale() -> None:
    assert not is_stale(0.1, 0.6, 500)  # exactly max age (0.6 - 0.1 rounds below 0.5)
    assert not is_stale(0.0, 0.5, 500)
    assert is_stale(0.1, 0.61, 500)
    assert not is_stale(1.0, 1.0, 500)
    assert is_stale(0.0, 0.101, 100)


def test_pose_noise_zero_is_identity() -> None:
    rng = np.random.default_rng(0)
    pose = Pose(1.1, -2.2, 0.3, 0.123456789)
    assert noisy_pose(pose, PoseNoiseConfig(), rng) is pose
    tup = (1.1, -2.2, 0.3, 0.123456789)
    assert noisy_pose(tup, PoseNoiseConfig(), rng) is tup
    state = rng.bit_generator.state
    link = LinkModel(comm(), 0, "a", "b")
    assert link.noisy_pose(pose) is pose
    assert rng.bit_generator.state == state  # no draw either


def test_pose_noise_statistics() -> None:
    cfg = PoseNoiseConfig(xy_std_m=0.2, yaw_std_deg=0.2)
    rng = np.random.default_rng(5)
    pose = Pose(10.0, 20.0, 0.5, 1.0)
    out = np.array([noisy_pose(pose, cfg, rng).as_tuple() for _ in range(5000)])
    assert np.all(out[:, 2] == 0.5)
    assert abs(out[:, 0].std() - 0.2) < 0.01 and abs(out[:, 1].std() - 0.2) < 0.01
    assert abs(np.degrees(out[:, 3].std()) - 0.2) < 0.01
    assert abs(out[:, 0].mean() - 10.0) < 0.01
    only_yaw = noisy_pose(pose, PoseNoiseConfig(yaw_std_deg=1.0), rng)
    assert (only_yaw.x, only_yaw.y) == (pose.x, pose.y) and only_yaw.yaw != pose.yaw


def _seq(cfg: CommConfig, seed: int, s: str, r: str) -> list[tuple[bool, float]]:
    return [(d.delivered, d.arrival_time) for d in run(LinkModel(cfg, seed, s, r), 500)]


def test_reproducible_and_links_differ() -> None:
    cfg = comm(drop=DropConfig(p=0.3), latency_ms=LatencyConfig(mean=50.0, jitter=10.0))
    assert _seq(cfg, 7, "cav1", "cav0") == _seq(cfg, 7, "cav1", "cav0")
    assert _seq(cfg, 7, "cav1", "cav0") != _seq(cfg, 7, "cav0", "cav1")
    assert _seq(cfg, 7, "cav1", "cav0") != _seq(cfg, 7, "cav2", "cav0")
    assert _seq(cfg, 7, "cav1", "cav0") != _seq(cfg, 8, "cav1", "cav0")
    assert _seq(cfg, 7, "ab", "c") != _seq(cfg, 7, "a", "bc")


def test_common_random_numbers_across_drop_settings() -> None:
    lat = LatencyConfig(mean=50.0, jitter=10.0)
    a = run(LinkModel(comm(latency_ms=lat), 2, "s", "r"), 300)
    b = run(LinkModel(comm(latency_ms=lat, drop=DropConfig(p=0.5)), 2, "s", "r"), 300)
    assert any(not d.delivered for d in b)
    assert all(x.arrival_time == y.arrival_time for x, y in zip(a, b, strict=True) if y.delivered)
