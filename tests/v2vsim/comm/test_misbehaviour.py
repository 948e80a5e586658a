"""The lies of `misbehaviour` (v2vsim/comm/misbehaviour.py) on a hand-made map: each changes exactly what it says
and nothing else. The map: 2 channels, 16 x 16 cells of 2 m over 32 m (cell centres at 15, 13, ..., -15 m; row 0
front, column 0 left), background 1.0; vehicle A at (8, 0) painted 5.0 on rows 3-4, columns 7-8; vehicle B at
(-8, 6) painted 7.0 on rows 11-12, columns 4-5."""

from __future__ import annotations

import math

import numpy as np
import pytest

from v2vsim.comm.misbehaviour import ADDED_SCORE, Sent, active, apply, claimed_pose, tell
from v2vsim.config.schema_misbehaviour import Lie

SIZE = 32.0
A = np.array([8.0, 0.0, 4.5, 2.2, 0.0])
B = np.array([-8.0, 6.0, 4.5, 2.2, 0.0])
POSE = (10.0, 5.0, 0.0, math.pi / 2)


def _sent() -> Sent:
    f = np.ones((2, 16, 16), dtype=np.float32)
    f[:, 3:5, 7:9] = 5.0
    f[:, 11:13, 4:6] = 7.0
    maps = np.zeros((3, 16, 16), dtype=np.float32)
    maps[0, 3:5, 7:9] = maps[0, 11:13, 4:6] = 0.8
    maps[1] = 0.5  # road everywhere
    boxes = np.array([[*A, 0.7], [*B, 0.6]], dtype=np.float32)
    return Sent(f, POSE, maps, boxes)


def _apply(lie: Lie, targets: np.ndarray = A[None], seen: np.ndarray | None = None) -> tuple[Sent, bool]:
    return apply(_sent(), lie, SIZE, targets, np.stack([A, B]) if seen is None else seen)


@pytest.mark.parametrize("factor", [8.0, -8.0])
def test_scale_multiplies_the_features_only(factor: float) -> None:
    s, ok = _apply(Lie(cavs=("cav1",), kind="scale", factor=factor))
    honest = _sent()
    assert ok and np.array_equal(s.features, honest.features * factor)
    assert s.pose == POSE and np.array_equal(s.maps, honest.maps) and np.array_equal(s.boxes, honest.boxes)


def test_flip_mirrors_left_and_right_and_twice_is_the_truth() -> None:
    s, _ = _apply(Lie(cavs=("cav1",), kind="flip"))
    assert np.all(s.features[:, 11:13, 10:12] == 7.0) and np.all(s.features[:, 11:13, 4:6] == 1.0)
    assert s.boxes[1, 1] == -6.0 and s.maps[0, 11, 10] == 0.8
    back, _ = apply(s, Lie(cavs=("cav1",), kind="flip"), SIZE, A[None], np.stack([A, B]))
    honest = _sent()
    assert np.array_equal(back.features, honest.features) and np.array_equal(back.boxes, honest.boxes)


def test_zero_sends_nothing_seen() -> None:
    s, _ = _apply(Lie(cavs=("cav1",), kind="zero"))
    assert not s.features.any() and not s.maps.any() and s.boxes.shape == (0, 6) and s.pose == POSE


def test_pose_moves_the_claim_in_the_senders_frame_and_nothing_else() -> None:
    s, _ = _apply(Lie(cavs=("cav1",), kind="pose", shift_m=(6.0, 2.0), rotate_deg=25.0))
    x, y, z, yaw = s.pose
    # heading +y (yaw 90 degrees): 6 m forward is +y, 2 m to the left is -x
    assert (x, y, z) == pytest.approx((8.0, 11.0, 0.0)) and yaw == pytest.approx(math.pi / 2 + math.radians(25))
    assert np.array_equal(s.features, _sent().features)
    assert claimed_pose((0, 0, 0, math.pi), Lie(cavs=("c",), kind="pose", rotate_deg=90))[3] == pytest.approx(
        -math.pi / 2)  # wrapped to (-pi, pi]


def test_remove_vehicle_sets_its_grown_footprint_to_background_and_drops_its_box() -> None:
    s, ok = _apply(Lie(cavs=("cav1",), kind="remove_vehicle"))
    honest = _sent()
    changed = np.argwhere((s.features != honest.features).any(axis=0))
    # A grown by 1 m: x in [4.75, 11.25] (rows 2-5), y in [-2.1, 2.1] (columns 7-8); only its painted cells change
    assert ok and {tuple(c) for c in changed} == {(r, c) for r in (3, 4) for c in (7, 8)}
    hidden = np.zeros((16, 16), bool)
    hidden[2:6, 7:9] = True
    assert np.all(s.features[:, hidden] == 1.0)  # the background's median
    assert np.all(s.features[:, 11:13, 4:6] == 7.0)  # B untouched
    assert s.boxes.tolist() == honest.boxes[1:].tolist()
    assert not s.maps[0, 3:5, 7:9].any() and s.maps[0, 11, 4] == 0.8 and np.all(s.maps[1] == 0.5)


def test_remove_vehicle_without_its_target_on_the_grid_is_not_told() -> None:
    s, ok = _apply(Lie(cavs=("cav1",), kind="remove_vehicle"), targets=np.zeros((0, 5)))
    assert not ok and np.array_equal(s.features, _sent().features)


def test_add_vehicle_paints_a_car_with_what_vehicles_look_like_and_adds_its_box() -> None:
    s, ok = _apply(Lie(cavs=("cav1",), kind="add_vehicle", at_m=(-4.0, -7.0)))
    honest = _sent()
    changed = {tuple(c) for c in np.argwhere((s.features != honest.features).any(axis=0))}
    # x in [-6.25, -1.75]: rows 9-10; y in [-7.95, -6.05]: column 11; the mean of A's and B's cells: 6
    assert ok and changed == {(9, 11), (10, 11)} and np.all(s.features[:, 9:11, 11] == 6.0)
    assert s.boxes.shape == (3, 6) and s.boxes[-1].tolist() == pytest.approx([-4.0, -7.0, 4.5, 1.9, 0.0, ADDED_SCORE])
    assert np.all(s.maps[0, 9:11, 11] == 1.0) and s.maps[0].sum() == pytest.approx(honest.maps[0].sum() + 2.0)
    _, ok = _apply(Lie(cavs=("cav1",), kind="add_vehicle"), seen=np.zeros((0, 5)))
    assert not ok  # nothing seen to copy: not told


def test_evidence_stays_honest_unless_the_lie_makes_it_agree() -> None:
    from dataclasses import replace

    from v2vsim.perception.evidence import FREE, OCCUPIED, UNKNOWN

    ev = np.full((16, 16), FREE, np.uint8)
    ev[3, 7:9] = OCCUPIED  # A's rear face, as its rays saw it
    sent = replace(_sent(), evidence=ev)
    hide = Lie(cavs=("cav1",), kind="remove_vehicle")
    honest, _ = apply(sent, hide, SIZE, A[None], np.stack([A, B]))
    assert np.array_equal(honest.evidence, ev)  # the lie is in its map only: its rays still say A is there
    sly, _ = apply(sent, replace(hide, evidence="consistent"), SIZE, A[None], np.stack([A, B]))
    assert (sly.evidence[2:6, 7:9] == UNKNOWN).all() and (sly.evidence[2:6, 6] == FREE).all()
    assert (sly.evidence[10:14] == FREE).all()
    added, _ = apply(sent, Lie(cavs=("cav1",), kind="add_vehicle", at_m=(-4.0, -7.0), evidence="consistent"), SIZE,
                     A[None], np.stack([A, B]))
    assert (added.evidence[9:11, 11] == OCCUPIED).all() and added.evidence[9, 12] == FREE
    assert added.evidence[3, 7] == OCCUPIED
    zero, _ = apply(sent, Lie(cavs=("cav1",), kind="zero", evidence="consistent"), SIZE, A[None], A[None])
    assert (zero.evidence == UNKNOWN).all()


def test_lies_are_active_for_their_cavs_from_their_frame_and_told_in_order() -> None:
    lies = [Lie(cavs=("cav1",), kind="zero", from_frame=5), Lie(cavs=("cav1", "cav2"), kind="scale", factor=2.0)]
    assert active(lies, "cav1", 4) == lies[1:] and active(lies, "cav1", 5) == lies and active(lies, "cav3", 9) == []
    s, told = tell(_sent(), [lies[1], Lie(cavs=("cav1",), kind="remove_vehicle", targets=("foe0", "gone"))], SIZE,
                   {"foe0": A}, np.stack([A, B]))
    assert told == ["scale", "remove_vehicle"] and np.all(s.features[:, 3:5, 7:9] == 2.0)  # background 1 x 2
