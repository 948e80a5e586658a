"""The loop closed on the occlusion-critical scenarios (issue 46; the benchmark's families, issue 53), in one
process: the real SUMO backend, the real planner, perception replaced by its two bounds. `oracle` (every other
vehicle, as ground truth) yields to the hidden foe and hits nothing; a planner fed nothing (what an ego whose sensors
see nothing of the main road has) pulls out and is hit. The same loop as the agents run (v2vsim.control.pilot), with
the actuation delay of a lockstep run; the processes' version is tests/agents/test_closed_loop.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from v2vsim.config import load_scenario
from v2vsim.control.measures import vehicle_measures
from v2vsim.control.pilot import Pilot
from v2vsim.traffic import make_backend

SCENARIOS = Path(__file__).resolve().parents[3] / "scenarios"
OCCLUDED = SCENARIOS / "t_junction_occluded.yaml"
SEEDS = (2, 5)  # seeds where the hidden foe reaches the junction as the ego does (scripts/occlusion_share.py)
# (scenario, seed, overrides): per benchmark family a configuration where a blind ego is hit and the oracle is not.
# blind_pullout: the 14 s its seeds were chosen at (cavs.meet.horizon_s caps the look-ahead, so the cast is the
# one a 14 s run has). crossing_paths: the foe 0.5 s ahead of the ego's free-flow arrival, where a planner fed
# nothing is hit on tuning seeds 100-105 (it crosses unhindered at later offsets). red_light_runner: the runner at
# 14 m/s as the ego arrives on its green (the oracle gives way; the blind ego drives on). ramp_merge: the foe as the ego
# reaches the ramp's give-way line at free flow (a planner fed nothing never slows; one on its own LiDAR, which
# briefly yields to what it does see, is hit at later offsets). left_turn_truck: the oncoming foe, behind the
# standing truck, 0.5 s after the ego's free-flow arrival (the LiDAR ego, which waits for what it sees, at 1.5-2.5 s).
CASES = [(OCCLUDED, seed, ("duration_s=14",)) for seed in SEEDS] + [
    (SCENARIOS / "crossroads_occluded.yaml", 100, ("duration_s=20", "traffic.hidden_foe.arrival_offset_s=[-0.5, -0.5]",
                                                   "traffic.hidden_foe.speed_mps=11")),
    (SCENARIOS / "red_light_runner.yaml", 100, ("duration_s=20", "traffic.hidden_foe.arrival_offset_s=[0, 0]",
                                                "traffic.hidden_foe.speed_mps=14")),
    (SCENARIOS / "ramp_merge.yaml", 100, ("duration_s=20", "traffic.hidden_foe.arrival_offset_s=[0, 0]",
                                          "traffic.hidden_foe.speed_mps=11")),
    (SCENARIOS / "left_turn_truck.yaml", 100, ("duration_s=20", "traffic.hidden_foe.arrival_offset_s=[0.5, 0.5]",
                                               "traffic.hidden_foe.speed_mps=11")),
    # blind_corner_stop: the stopped car 5 m past the corner; the oracle follows it to a stop (it has no one to
    # yield to), the blind ego turns into it
    (SCENARIOS / "blind_corner_stop.yaml", 100, ("duration_s=20", "traffic.hidden_stop.distance_m=5",
                                                 "control.idm.desired_speed_mps=11"))]


def _drive(method: str, seed: int, scenario: Path = OCCLUDED, overrides: tuple[str, ...] = ("duration_s=14",)) -> dict:
    """Run the scenario with the ego planning on `method`'s view: `oracle`, or `none` fed no detections."""
    sc = load_scenario(scenario, [f"control.method={method}", f"seed={seed}", "perception.methods=[none]",
                                  *overrides])
    pilot = Pilot(sc, "cav0")
    plans: dict[int, float] = {}
    with make_backend(sc, closed_loop=True) as b:
        w = b.reset()
        for k in range(sc.frames):
            step = pilot.step(w, None)  # no prediction: oracle reads the world, `none` gets nothing
            if step is not None:
                plans[k] = step.plan.accel
            if k - sc.actuation_delay_frames in plans:  # as the driver: the plan of frame k - d, before step k+1
                b.command({"cav0": plans[k - sc.actuation_delay_frames]})
            w = b.step()
    c = sc.control
    assert c is not None
    return vehicle_measures(pilot.frames, sc.dt, c.hard_brake_mps2, c.near_miss_gap_m, None)


@pytest.mark.parametrize(("scenario", "seed", "overrides"), CASES, ids=lambda v: getattr(v, "stem", str(v)))
def test_oracle_yields_to_the_hidden_foe_and_a_blind_planner_is_hit(scenario: Path, seed: int,
                                                                    overrides: tuple[str, ...]) -> None:
    oracle, blind = _drive("oracle", seed, scenario, overrides), _drive("none", seed, scenario, overrides)
    critical = "stopped0" if "hidden_stop" in " ".join(overrides) else "foe0"
    assert oracle["collisions"] == 0 and not oracle["near_miss"], oracle
    assert oracle["yielding_frames"] > 0 or critical == "stopped0"
    assert blind["collisions"] > 0 or blind["near_miss"], blind
    assert critical in blind["collided_with"] or blind["near_miss"]


def test_the_closed_loop_is_deterministic_for_a_seed() -> None:
    assert _drive("oracle", SEEDS[0]) == _drive("oracle", SEEDS[0])
