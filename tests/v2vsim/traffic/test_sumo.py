"""SUMO backend: determinism, CAV placement, frame conversion, leaving, clean close/restart."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Point, Polygon
from shapely.ops import unary_union

from v2vsim.config import load_scenario
from v2vsim.traffic import TrafficBackend, make_backend
from v2vsim.traffic.sumo import SumoBackend, _libsumo, sumo_to_pose

SCENARIOS = Path(__file__).resolve().parents[3] / "scenarios"
N_FRAMES = 50


def _scenario(name: str = "intersection", *overrides: str):
    return load_scenario(SCENARIOS / f"{name}.yaml", list(overrides))


def _run(sc, frames: int = N_FRAMES):
    with make_backend(sc) as tb:
        return [tb.reset()] + [tb.step() for _ in range(frames - 1)]


def _signature(states) -> list:
    return [(s.frame, s.time, [(a.id, a.kind, a.cav, a.pose.as_tuple(), a.extent) for a in s.actors])
            for s in states]


@pytest.fixture(scope="module")
def run0():
    return _run(_scenario())


def test_conversion_front_bumper_to_centre() -> None:
    east = sumo_to_pose(10.0, 0.0, 90.0, 4.0)
    assert east.yaw == pytest.approx(0.0) and (east.x, east.y) == pytest.approx((8.0, 0.0))
    north = sumo_to_pose(0.0, 10.0, 0.0, 4.0)
    assert north.yaw == pytest.approx(math.pi / 2) and (north.x, north.y) == pytest.approx((0.0, 8.0))
    south = sumo_to_pose(0.0, 0.0, 180.0, 5.0)
    assert south.yaw == pytest.approx(-math.pi / 2) and (south.x, south.y) == pytest.approx((0.0, 2.5))
    west = sumo_to_pose(0.0, 0.0, 270.0, 2.0)
    assert abs(math.cos(west.yaw) + 1) < 1e-9 and (west.x, west.y) == pytest.approx((1.0, 0.0))


def test_same_seed_identical_different_seed_differs(run0) -> None:
    assert _signature(_run(_scenario())) == _signature(run0)
    other = _run(_scenario("intersection", "seed=1"))
    assert _signature(other) != _signature(run0)


def test_cavs_exist_at_frame0_from_different_arms(run0) -> None:
    s0 = run0[0]
    assert s0.frame == 0 and s0.time == 0.0
    assert [a.id for a in s0.cavs] == ["cav0", "cav1", "cav2", "cav3"]
    assert [a.id for a in s0.actors[:4]] == ["cav0", "cav1", "cav2", "cav3"]  # CAVs first
    assert len(s0.actors) > 4  # background traffic is there at frame 0
    assert all(a.cav == a.id.startswith("cav") for a in s0.actors)
    # four different approach directions, all heading towards the junction at the origin
    headings = {round(math.degrees(a.pose.yaw)) % 360 for a in s0.cavs}
    assert headings == {0, 90, 180, 270}
    for a in s0.cavs:
        to_centre = np.array([-a.pose.x, -a.pose.y])
        assert to_centre @ [math.cos(a.pose.yaw), math.sin(a.pose.yaw)] > 0
    ext = s0.actor("cav0").extent
    assert ext == pytest.approx((4.5, 1.9, 1.5))
    assert all(s.time == pytest.approx(s.frame * 0.1) for s in run0)


@pytest.mark.parametrize("name", ["intersection", "t_junction"])
def test_cavs_stay_in_comm_range_of_cav0_most_of_the_run(name: str) -> None:
    sc = _scenario(name)
    states = _run(sc, frames=sc.frames)
    ego = [s.actor("cav0") for s in states]
    assert all(e is not None for e in ego)
    for cid in [f"cav{i}" for i in range(1, sc.cavs.count)]:
        near = [(o := s.actor(cid)) is not None and math.hypot(o.pose.x - e.pose.x, o.pose.y - e.pose.y)
                <= sc.comm.range_m for s, e in zip(states, ego, strict=True)]
        assert sum(near) >= 0.5 * len(states), cid


def _neighbours(states, ego: str, range_m: float) -> list[int | None]:
    """Per frame, other CAVs within range_m of the ego (centre distance); None once the ego is gone."""
    out: list[int | None] = []
    for s in states:
        e = s.actor(ego)
        out.append(None if e is None else sum(
            1 for a in s.cavs if a.id != ego and math.hypot(a.pose.x - e.pose.x, a.pose.y - e.pose.y) <= range_m))
    return out


# Seeds picked where the canonical plan does not qualify on the signalised net (the look-ahead has
# to find another placement) as well as ones where it does; see v2vsim/bench/placement.py for 0-19.
@pytest.mark.parametrize(("name", "seed"), [("intersection", 0), ("intersection", 3), ("intersection", 9),
                                            ("t_junction", 1), ("t_junction", 12), ("t_junction", 18)])
def test_cavs_meet_from_frame0(name: str, seed: int) -> None:
    """>= 2 other CAVs within comm range of cav0 in >= 80 % of the frames counted from frame 0, and
    cav0 is still there at the last frame (measured on the WorldStates, not the backend's own figure)."""
    sc = _scenario(name, f"seed={seed}")
    with SumoBackend(sc) as tb:
        states = [tb.reset()] + [tb.step() for _ in range(sc.frames - 1)]
        placement = tb.placement
    counts = _neighbours(states, "cav0", sc.comm.range_m)
    assert None not in counts, f"cav0 left at frame {counts.index(None)}"
    share = sum(1 for c in counts if c >= 2) / len(counts)
    assert share >= 0.8, share
    # the look-ahead predicted exactly this run (same seed, same steps)
    assert placement is not None and placement.share == pytest.approx(share) and placement.ref_frames == sc.frames
    assert placement.arms >= 2  # not a single platoon


def test_placement_search_is_deterministic() -> None:
    sc = _scenario("intersection", "seed=3")
    runs = []
    for _ in range(2):
        with SumoBackend(sc) as tb:  # a fresh backend searches from scratch
            states = [tb.reset()] + [tb.step() for _ in range(30)]
            runs.append((tb.placement, tb.cav_plans, _signature(states)))
    assert runs[0] == runs[1]
    assert runs[0][0].trial > 0  # seed 3: the canonical plan does not meet the aim, a later candidate does


def test_arrival_window_and_single_trial() -> None:
    """cavs.meet.trials=1 is the canonical plan, unchecked; the arrival window sets the spots."""
    near = _scenario("t_junction", "cavs.meet.trials=1", "cavs.arrival_s=[0, 0]", "traffic.background_per_hour=0")
    far = _scenario("t_junction", "cavs.meet.trials=1", "cavs.arrival_s=[8, 8]", "traffic.background_per_hour=0")
    with SumoBackend(near) as tb:
        tb.reset()
        assert tb.placement is None
        near_plans = tb.cav_plans
    with SumoBackend(far) as tb:
        tb.reset()
        far_plans = tb.cav_plans
    assert all(p.arrival_s == 0.0 for p in near_plans) and all(p.arrival_s == 8.0 for p in far_plans)
    # empty roads: the first CAV of each arm is where the window says (v * t before the stop line)
    firsts = {}
    for p in far_plans:
        firsts.setdefault(p.route.approach, p)
    for p in firsts.values():
        assert p.to_stop_line_m == pytest.approx(8.0 * min(13.89, 50 / 3.6) if p.route.approach != "S2T"
                                                 else 8.0 * 11.11, abs=3.0)
    assert max(p.to_stop_line_m for p in near_plans) < 30.0  # the second CAV of an arm queues behind


def test_yaw_matches_motion_and_centre_is_behind_bumper() -> None:
    sc = _scenario()
    ls = _libsumo()
    with SumoBackend(sc) as tb:
        prev = tb.reset()
        for _ in range(20):
            cur = tb.step()
            for a in cur.actors:
                b = prev.actor(a.id)
                if b is None or a.speed < 3.0 or b.speed < 3.0:
                    continue
                d = np.array([a.pose.x - b.pose.x, a.pose.y - b.pose.y])
                heading = np.array([math.cos(a.pose.yaw), math.sin(a.pose.yaw)])
                assert d @ heading / np.linalg.norm(d) > 0.95, a.id  # moves where it points
            front = ls.vehicle.getPosition("cav0")
            c = cur.actor("cav0")
            assert (c.pose.x + 2.25 * math.cos(c.pose.yaw), c.pose.y + 2.25 * math.sin(c.pose.yaw)) == \
                pytest.approx(front, abs=1e-6)
            prev = cur
    cav0 = prev.actor("cav0")
    # drives east on W2C (it may be mid lane change: SUMO steers up to ~20 degrees over 2 s)
    assert math.cos(cav0.pose.yaw) > 0.9
    assert cav0.pose.x < 0 and -7.0 < cav0.pose.y < 0.0  # right-hand side of the west arm


def test_static_map_via_backend() -> None:
    with make_backend(_scenario()) as tb:
        assert isinstance(tb, TrafficBackend)
        roads = unary_union([Polygon(r) for r in tb.static.roads])
        assert roads.contains(Point(0.0, 0.0))
        assert len(tb.static.buildings) == 12


def test_cav_leaves_cleanly_and_background_turns_over() -> None:
    sc = _scenario("intersection", "cavs.count=2")
    gone: dict[str, int] = {}
    seen: set[str] = set()
    with make_backend(sc) as tb:
        s = tb.reset()
        first_bg = {a.id for a in s.actors if not a.cav}
        for _ in range(700):
            s = tb.step()
            ids = {a.id for a in s.actors}
            seen |= ids
            for cid in ("cav0", "cav1"):
                if cid in ids:
                    assert cid not in gone, f"{cid} came back"
                elif cid not in gone:
                    gone[cid] = s.frame
            if len(gone) == 2:
                break
    assert set(gone) == {"cav0", "cav1"}  # both crossed and drove off the long exit arms
    assert min(gone.values()) > 150  # ... but not before the run is mostly over
    assert first_bg - {a.id for a in s.actors}  # some background vehicles left too
    assert seen - first_bg - {"cav0", "cav1"}  # and new ones entered


def test_close_and_restart_in_one_process() -> None:
    sc = _scenario("intersection", "cavs.count=1")
    a = make_backend(sc)
    first = a.reset()
    b = make_backend(sc)
    with pytest.raises(RuntimeError, match="another SUMO simulation"):
        b.reset()
    a.close()
    a.close()  # idempotent
    with pytest.raises(RuntimeError, match=re.escape("step() before reset() (or after close())")):
        a.step()
    with b:
        again = b.reset()
        assert _signature([again]) == _signature([first])
        assert _signature([b.reset()]) == _signature([first])  # reset() restarts cleanly
    assert not _libsumo().simulation.isLoaded()


def test_t_junction_six_cavs_three_arms() -> None:
    sc = _scenario("t_junction")
    with SumoBackend(sc) as tb:
        s0 = tb.reset()
        assert [a.id for a in s0.cavs] == [f"cav{i}" for i in range(6)]
        assert len({p.route.approach for p in tb.cav_plans}) == 3
        assert tb.cav_plans[0].route.approach == "S2T"  # cav0 on the minor road: it yields and lingers
        for _ in range(30):
            s = tb.step()
        assert {a.id for a in s.cavs} == {f"cav{i}" for i in range(6)}
        assert all(abs(a.pose.x - 400) < 250 and abs(a.pose.y - 250) < 250 for a in s.actors)


def test_stdout_stays_clean() -> None:
    """Agents talk over stdout: neither libsumo's import banner nor SUMO's logs may leak there."""
    code = ("from v2vsim.config import load_scenario\n"
            "from v2vsim.traffic import make_backend\n"
            f"sc = load_scenario({str(SCENARIOS / 'intersection.yaml')!r}, ['traffic.warmup_s=2'])\n"
            "with make_backend(sc) as tb:\n"
            "    tb.reset()\n"
            "    [tb.step() for _ in range(5)]\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout == ""
