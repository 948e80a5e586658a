"""v2vsim.perception.consistency: a sender's single-agent maps against the others' consensus, on hand-made maps
(1 m cells over 100 m; row 0 = front, column 0 = left)."""

from __future__ import annotations

import numpy as np
import pytest

from v2vsim.config.schema_misbehaviour import DefenceConfig
from v2vsim.perception.consistency import Disagreement, check_frame, disagreements, judge, without
from v2vsim.perception.fuse import FusionInputs

SIZE, CELLS = 100.0, 100
CFG = DefenceConfig(detect=True, road_threshold=0.2, vehicle_threshold_m2=12.0, min_shared_m2=100.0, near_m=30.0)


def _world_map(vehicle_at: list[tuple[float, float]] = ()) -> np.ndarray:
    """[3, S, S] maps of a T-junction seen from the origin: a road along x (forward) for x >= -10 and a cross
    road along y at x in [10, 18]; a 5 x 2 m vehicle at each (x, y)."""
    m = np.zeros((3, CELLS, CELLS), np.float32)
    c = SIZE / 2 - (np.arange(CELLS) + 0.5)  # cell centres: forward per row, left per column
    fwd, left = c[:, None], c[None, :]
    m[1] = ((np.abs(left) < 4) & (fwd > -10)) | ((fwd > 10) & (fwd < 18))
    for x, y in vehicle_at:
        m[0] = np.maximum(m[0], (np.abs(fwd - x) < 2.5) & (np.abs(left - y) < 1.0))
    return m


ROAD_MAP = _world_map()[1] > 0.5  # the drivable area of the ego's map, on its grid


def _scores(maps: dict[str, np.ndarray], poses: dict[str, tuple[float, float, float]]) -> dict[str, Disagreement]:
    return disagreements(maps, {s: np.array(p, np.float32) for s, p in poses.items()}, "ego", SIZE, CFG.near_m,
                         road_map=ROAD_MAP)


def test_an_honest_sender_at_the_ego_s_place_agrees_exactly() -> None:
    m = _world_map([(14.0, 0.0)])
    d = _scores({"ego": m, "cav1": m.copy()}, {"ego": (0, 0, 0), "cav1": (0, 0, 0)})["cav1"]
    assert d.road == 0 and d.vehicle_m2 == 0 and d.road_vs_map == 0 and d.shared_m2 > 2000
    assert judge({"cav1": d}, CFG) == set()


def _seen_from(x: float, y: float) -> np.ndarray:
    """The world map as an honest agent at (x, y) heading along x sees it, in its own frame."""
    m = np.zeros((3, CELLS, CELLS), np.float32)
    c = SIZE / 2 - (np.arange(CELLS) + 0.5)
    fwd, left = c[:, None] + x, c[None, :] + y  # world coordinates of its cells
    m[1] = ((np.abs(left) < 4) & (fwd > -10)) | ((fwd > 10) & (fwd < 18))
    return m


def test_a_claimed_pose_6_m_and_25_deg_off_misplaces_the_road_against_the_map_and_is_flagged() -> None:
    m = _world_map()
    honest = _scores({"ego": m, "cav1": _seen_from(5.0, 0)}, {"ego": (0, 0, 0), "cav1": (5.0, 0, 0)})["cav1"]
    lying = _scores({"ego": m, "cav1": _seen_from(5.0, 0)}, {"ego": (0, 0, 0), "cav1": (11.0, 0, np.radians(25))})
    assert honest.road_vs_map == pytest.approx(0, abs=0.01) and judge({"cav1": honest}, CFG) == set()
    assert lying["cav1"].road_vs_map > CFG.road_threshold
    assert judge(lying, CFG) == {"cav1"}


def test_a_zeroed_map_has_no_road_where_the_map_has_one_and_is_flagged() -> None:
    d = _scores({"ego": _world_map(), "cav1": np.zeros((3, CELLS, CELLS), np.float32)},
                {"ego": (0, 0, 0), "cav1": (0, 0, 0)})["cav1"]
    assert d.road_vs_map > CFG.road_threshold and d.vehicle_m2 == 0
    assert judge({"cav1": d}, CFG) == {"cav1"}


def test_a_vehicle_removed_where_the_ego_sees_it_is_flagged_by_its_area() -> None:
    truth = _world_map([(14.0, 0.0)])
    hidden = _world_map()
    d = _scores({"ego": truth, "cav1": hidden}, {"ego": (0, 0, 0), "cav1": (0, 0, 0)})["cav1"]
    assert d.road == 0
    assert d.vehicle_m2 == pytest.approx(10.0, abs=2.0)  # a 5 x 2 m car on 1 m cells
    strict = DefenceConfig(detect=True, vehicle_threshold_m2=6.0)
    assert judge({"cav1": d}, strict) == {"cav1"} and judge({"cav1": d}, CFG) == set()


def test_a_lie_about_cells_no_other_agent_is_near_is_not_seen() -> None:
    """The limit by construction: the liar hides a car 40 m ahead of the ego, where only it is near."""
    near_truth = _world_map([(40.0, 0.0)])
    d = _scores({"ego": near_truth, "cav1": _world_map()}, {"ego": (0, 0, 0), "cav1": (45.0, 0, 0)})["cav1"]
    assert d.vehicle_m2 == 0


def test_too_few_shared_cells_is_no_evidence() -> None:
    m = _world_map()
    d = _scores({"ego": m, "cav1": np.zeros_like(m)}, {"ego": (0, 0, 0), "cav1": (58.0, 0, 0)})["cav1"]
    assert d.shared_m2 < CFG.min_shared_m2
    assert judge({"cav1": d}, CFG) == set()
    far = _scores({"ego": m, "cav1": m}, {"ego": (0, 0, 0), "cav1": (0, 90.0, 0)})["cav1"]
    assert far == Disagreement(None, None, 0.0) and not far.flagged(CFG)


def test_the_consensus_flags_the_liar_and_not_the_honest_sender_that_agrees_with_the_ego() -> None:
    m = _world_map([(14.0, 0.0)])
    zero = np.zeros_like(m)  # a zeroed map: no road, no vehicle
    scores = _scores({"ego": m, "cav1": m.copy(), "cav2": zero}, {"ego": (0, 0, 0), "cav1": (2.0, 0, 0),
                                                                 "cav2": (0, 0, 0)})
    assert judge(scores, CFG) == {"cav2"}
    assert scores["cav1"].road < scores["cav2"].road


def test_without_drops_a_sender_from_every_kind_and_every_method() -> None:
    f = np.zeros((2, 4, 4), np.float32)
    inp = FusionInputs(senders=["ego", "cav1", "cav2"], rel_poses=np.zeros((3, 3), np.float32),
                       features={"ego": f, "cav1": f, "cav2": f}, points={"cav1": np.zeros((1, 4))},
                       outputs={"cav1": (np.zeros((3, 2, 2)), np.zeros((0, 6)))},
                       extrapolated={"cobevt": {"cav1": f}}, feature_ages={"cav1": 0.1})
    out = without(inp, {"cav1"})
    assert list(out.features) == ["ego", "cav2"] and not out.points and not out.outputs
    assert out.extrapolated == {"cobevt": {}} and not out.feature_ages
    assert inp.features.keys() == {"ego", "cav1", "cav2"}  # the frame's inputs as received are untouched
    assert without(inp, set()) is inp


def test_a_liar_that_pulls_the_consensus_is_left_out_and_the_honest_sender_is_not_flagged() -> None:
    """cav1 and the liar are 30 m ahead; the liar paints vehicles on every cell. Beyond the ego's 30 m only the two
    of them are near, so in one round each is flagged against the other; the liar disagrees on more cells (near the
    ego too), is left out first, and cav1 judged again has no one to disagree with there."""
    m = _world_map()
    liar = _seen_from(30.0, 0)
    liar[0] = 1.0
    maps = {"ego": m, "cav1": _seen_from(30.0, 0), "cav2": liar}
    poses = {"ego": np.zeros(3, np.float32), "cav1": np.array([30, 0, 0], np.float32),
             "cav2": np.array([30, 0, 0], np.float32)}
    first = disagreements(maps, poses, "ego", SIZE, CFG.near_m, road_map=ROAD_MAP)
    assert judge(first, CFG) == {"cav1", "cav2"} and first["cav2"].vehicle_m2 > first["cav1"].vehicle_m2
    scores, flagged = check_frame(maps, poses, "ego", SIZE, CFG, road_map=ROAD_MAP)
    assert flagged == {"cav2"}
    assert scores["cav1"].vehicle_m2 == 0 and scores["cav2"].vehicle_m2 > CFG.vehicle_threshold_m2
