"""The receiver side of the channel: latency decides which frame is fused, stale messages are not
fused, the receiver's own message skips the channel, and zero pose noise changes nothing."""

from __future__ import annotations

import dataclasses

import numpy as np

from v2vsim.comm.codec import Message
from v2vsim.comm.inbox import Inbox
from v2vsim.config import CommConfig, LatencyConfig, PoseNoiseConfig

DT = 0.1


def _msg(sender: str, frame: int, pose: tuple[float, float, float, float] = (1.0, 2.0, 0.0, 0.3)) -> Message:
    return Message(kind="features", run_id="r", sender_id=sender, frame=frame, capture_time=frame * DT,
                   sender_pose=pose, payload=np.zeros((2, 4, 4), np.float16))


def _cfg(**kw: object) -> CommConfig:
    return dataclasses.replace(CommConfig(bandwidth_mbps=None), **kw)


def _run(inbox: Inbox, frames: int, senders: list[str]) -> list[dict[str, int]]:
    """Offer each sender's frame-k message at t_k (lockstep) and record which frame is fusable at t_k."""
    fused = []
    for k in range(frames):
        for s in senders:
            inbox.offer(_msg(s, k), 100, k * DT, distance_m=10.0)
        fused.append({s: m.frame for s, m in inbox.ready(k * DT + 1e-9).items()})
    return fused


def test_latency_delays_which_frame_is_fused() -> None:
    inbox = Inbox(_cfg(latency_ms=LatencyConfig(mean=150.0)), seed=0, receiver="cav0", kind="features")
    fused = _run(inbox, 6, ["cav0", "cav1"])
    assert [f["cav0"] for f in fused] == [0, 1, 2, 3, 4, 5]  # the ego's own message has no channel
    assert [f.get("cav1") for f in fused] == [None, None, 0, 1, 2, 3]  # 150 ms late at 10 Hz -> 2 frames old
    assert inbox.stats.latency_percentile_ms(50) == 150.0  # on the channel, once per message
    assert inbox.stats.age_json()["buckets"] == {"200": 4}  # fused two frames old, every time


def _run_deadline(inbox: Inbox, frames: int, deadline_s: float) -> list[dict[str, int]]:
    """As a run's ego: frame k fused at t_k + deadline, as of t_k."""
    fused = []
    for k in range(frames):
        for s in ("cav0", "cav1"):
            inbox.offer(_msg(s, k), 100, k * DT, distance_m=10.0)
        fused.append({s: m.frame for s, m in inbox.ready(k * DT + deadline_s, as_of=k * DT).items()})
    return fused


def test_a_message_just_before_the_deadline_is_fused_aligned() -> None:
    inbox = Inbox(_cfg(latency_ms=LatencyConfig(mean=49.0)), seed=0, receiver="cav0", kind="features")
    fused = _run_deadline(inbox, 5, 0.050)
    assert [f["cav1"] for f in fused] == [0, 1, 2, 3, 4]  # frame k's message fused at frame k
    age = inbox.stats.age_json()
    assert age["buckets"] == {"0": 5} and age["p50"] == 0.0 and age["fused"] == 5
    assert inbox.stats.latency_percentile_ms(50) == 49.0


def test_a_message_just_after_the_deadline_serves_the_next_frame() -> None:
    inbox = Inbox(_cfg(latency_ms=LatencyConfig(mean=51.0)), seed=0, receiver="cav0", kind="features")
    fused = _run_deadline(inbox, 5, 0.050)
    assert [f.get("cav1") for f in fused] == [None, 0, 1, 2, 3]  # one frame old: warped with its capture pose
    age = inbox.stats.age_json()
    assert age["buckets"] == {"100": 4} and age["p50"] == 100.0


def test_zero_deadline_is_the_capture_instant() -> None:
    """Deadline 0 is what the harness did before: any latency makes the message a frame old."""
    inbox = Inbox(_cfg(latency_ms=LatencyConfig(mean=1.0)), seed=0, receiver="cav0", kind="features")
    assert [f.get("cav1") for f in _run_deadline(inbox, 3, 0.0)] == [None, 0, 1]


def test_age_histogram_counts_every_fusion_of_a_reused_message() -> None:
    """A message fused again in later frames (nothing newer came) counts once per fusion, older each time."""
    inbox = Inbox(_cfg(), seed=0, receiver="cav0", kind="features")
    inbox.offer(_msg("cav1", 0), 100, 0.0, distance_m=10.0)
    events = []
    for k in range(4):
        inbox.offer(_msg("cav0", k), 100, k * DT, distance_m=0.0)
        assert inbox.ready(k * DT + 0.05, as_of=k * DT)["cav1"].frame == 0
        events += [(e.outcome, round(e.age_ms)) for e in inbox.take_events()]
    age = inbox.stats.age_json()
    assert age["buckets"] == {"0": 1, "100": 1, "200": 1, "300": 1} and age["fused"] == 4
    assert inbox.stats.latency_s == [0.0]  # its channel time, once
    assert events == [("delivered", 0), ("reused", 100), ("reused", 200), ("reused", 300)]


def test_stale_messages_are_not_fused_and_are_counted() -> None:
    inbox = Inbox(_cfg(latency_ms=LatencyConfig(mean=250.0), max_age_ms=200.0), seed=0, receiver="cav0",
                  kind="features")
    fused = _run(inbox, 8, ["cav0", "cav1"])
    assert all("cav1" not in f for f in fused)
    assert inbox.stats.stale >= 4 and inbox.stats.delivered == 8


def test_zero_pose_noise_is_bit_identical_and_noise_moves_the_pose() -> None:
    quiet = Inbox(_cfg(), seed=0, receiver="cav0", kind="features")
    m = _msg("cav1", 0, (1.234567891, -2.5, 0.0, 0.7))
    assert quiet.sender_pose(m) == m.sender_pose
    noisy = Inbox(_cfg(pose_noise=PoseNoiseConfig(xy_std_m=0.5, yaw_std_deg=2.0)), seed=0, receiver="cav0",
                  kind="features")
    assert noisy.sender_pose(m) != m.sender_pose
    assert noisy.sender_pose(_msg("cav0", 0)) == _msg("cav0", 0).sender_pose  # own pose is known exactly


def test_out_of_range_is_not_delivered_and_bytes_count_only_the_air() -> None:
    inbox = Inbox(_cfg(range_m=50.0), seed=0, receiver="cav0", kind="features")
    inbox.offer(_msg("cav1", 0), 1000, 0.0, distance_m=80.0)
    inbox.offer(_msg("cav0", 0), 1000, 0.0, distance_m=0.0)
    assert inbox.stats.out_of_range == 1 and inbox.stats.sent == 1
    assert set(inbox.ready(0.0)) == {"cav0"}
    assert inbox.take_bytes() == 1000 and inbox.take_bytes() == 0


def test_link_events_say_what_each_link_did() -> None:
    from v2vsim.comm.inbox import LinkEvent
    from v2vsim.config import DropConfig

    inbox = Inbox(_cfg(latency_ms=LatencyConfig(mean=50.0), max_age_ms=250.0, range_m=100.0), seed=0,
                  receiver="cav0", kind="features")
    inbox.offer(_msg("cav0", 0), 100, 0.0, distance_m=0.0)
    inbox.offer(_msg("cav1", 0), 100, 0.0, distance_m=10.0)
    inbox.offer(_msg("cav2", 0), 100, 0.0, distance_m=500.0)
    inbox.ready(0.0)
    assert inbox.take_events() == [LinkEvent("cav1", "in_flight", 50.0), LinkEvent("cav2", "out_of_range")]
    inbox.mark_rejected("cav2")
    inbox.ready(0.1)  # cav1's frame 0 arrived at 50 ms: fused now, for the first time
    assert inbox.take_events() == [LinkEvent("cav1", "delivered", 50.0, 100.0), LinkEvent("cav2", "rejected")]
    inbox.ready(0.2)
    # nothing new: reusing frame 0 is not a new delivery, but the link says how old what is fused is
    assert inbox.take_events() == [LinkEvent("cav1", "reused", None, 200.0)]
    inbox.ready(0.3)
    assert inbox.take_events() == [LinkEvent("cav1", "stale")]  # frame 0 is 300 ms old now
    lossy = Inbox(_cfg(drop=DropConfig(p=1.0)), seed=0, receiver="cav0", kind="features")
    lossy.offer(_msg("cav1", 0), 100, 0.0, distance_m=10.0)
    assert lossy.take_events() == [LinkEvent("cav1", "dropped")]
