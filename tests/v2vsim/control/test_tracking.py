"""Tracking gives perceived obstacles velocities: estimates converge, ids survive crossing paths, a lost obstacle
is dropped, and the same inputs give the same tracks."""

from __future__ import annotations

import numpy as np
import pytest

from v2vsim.control.perceived import Obstacle
from v2vsim.control.tracking import Track, track


def _ob(x: float, y: float) -> Obstacle:
    return Obstacle(x, y, 0.0, 4.5, 1.8)


def test_velocity_of_a_moving_target() -> None:
    rng = np.random.default_rng(0)
    dt, v = 0.1, np.array([5.0, -3.0])
    tracks: tuple[Track, ...] = ()
    nid = 0
    for k in range(5):
        xy = np.array([3.0, 7.0]) + v * k * dt + rng.normal(0.0, 0.003, 2)  # a few mm of detection noise
        tracks, nid = track(tracks, (_ob(*xy),), dt, nid)
    assert len(tracks) == 1 and tracks[0].id == 0 and tracks[0].age == 5
    assert np.hypot(tracks[0].vx - v[0], tracks[0].vy - v[1]) < 0.2


def test_a_new_track_has_no_velocity_and_the_second_frame_takes_the_measured_one() -> None:
    tracks, nid = track((), (_ob(0.0, 0.0),), 0.1, 7)
    assert (tracks[0].id, tracks[0].vx, tracks[0].vy, tracks[0].age, nid) == (7, 0.0, 0.0, 1, 8)
    tracks, nid = track(tracks, (_ob(1.0, 0.0),), 0.1, nid)
    assert np.isclose(tracks[0].vx, 10.0) and tracks[0].age == 2 and nid == 8


def test_crossing_targets_keep_their_ids() -> None:
    """A drives east along y = 0, B north along x = 0.5 a fifth of a second behind; they pass 0.7 m apart. The
    obstacle order flips every frame, so only the association, not the order, can keep the ids."""
    dt = 0.1
    tracks: tuple[Track, ...] = ()
    nid = 0
    ids: dict[str, int] = {}
    for k in range(41):
        t = k * dt
        a, b = _ob(-10.0 + 5.0 * t, 0.0), _ob(0.5, -11.5 + 5.0 * t)
        obs = (a, b) if k % 2 == 0 else (b, a)
        tracks, nid = track(tracks, obs, dt, nid)
        by_pos = {("a" if tr.y == a.y and tr.x == a.x else "b"): tr.id for tr in tracks}
        if k == 0:
            ids = by_pos
        assert by_pos == ids, f"ids swapped at frame {k}"
    assert nid == 2


def test_an_unmatched_track_is_dropped_and_a_far_obstacle_starts_a_new_one() -> None:
    tracks, nid = track((), (_ob(0.0, 0.0), _ob(50.0, 0.0)), 0.1, 0, max_misses=0)
    tracks, nid = track(tracks, (_ob(0.5, 0.0), _ob(80.0, 0.0)), 0.1, nid, max_misses=0)  # 30 m jump: outside gate
    assert [(t.id, t.age) for t in tracks] == [(0, 2), (2, 1)]
    assert nid == 3
    tracks, nid = track(tracks, (), 0.1, nid, max_misses=0)
    assert tracks == () and nid == 3


def test_a_missed_track_coasts_for_max_misses_frames_then_is_dropped() -> None:
    tracks, nid = track((), (_ob(0.0, 0.0),), 0.1, 0)
    tracks, nid = track(tracks, (_ob(1.0, 0.0),), 0.1, nid)  # 10 m/s along +x
    for missed in (1, 2):
        tracks, nid = track(tracks, (), 0.1, nid)
        assert [(t.id, t.missed) for t in tracks] == [(0, missed)]
        assert tracks[0].x == pytest.approx(1.0 + missed * 1.0)  # moved on by its velocity
    tracks, nid = track(tracks, (_ob(4.0, 0.0),), 0.1, nid)  # seen again: the same track, no longer missed
    assert [(t.id, t.missed, t.age) for t in tracks] == [(0, 0, 3)]
    for _ in range(3):
        tracks, nid = track(tracks, (), 0.1, nid)
    assert tracks == ()


def test_deterministic() -> None:
    rng = np.random.default_rng(1)
    frames = [tuple(_ob(*xy) for xy in rng.uniform(-20, 20, (6, 2)) + k * 0.3) for k in range(6)]

    def run() -> tuple[tuple[Track, ...], int]:
        tracks: tuple[Track, ...] = ()
        nid = 0
        for obs in frames:
            tracks, nid = track(tracks, obs, 0.1, nid)
        return tracks, nid

    assert run() == run()


def test_equal_distances_go_to_the_lower_indices() -> None:
    prev = (Track(0, 0.0, 0.0, 0.0, 4.5, 1.8, 0.0, 0.0, 3), Track(1, 0.0, 0.0, 0.0, 4.5, 1.8, 0.0, 0.0, 3))
    tracks, _ = track(prev, (_ob(1.0, 0.0), _ob(-1.0, 0.0)), 0.1, 2)
    assert [t.id for t in tracks] == [0, 1]
