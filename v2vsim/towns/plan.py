"""A generated town's plan: everything a seed decides, as plain frozen data, before any file is written.

One seed -> one `TownPlan` (`draw_plan`), deterministic (numpy's PCG64 from the seed, no other state). The plan
varies what the benchmark families vary and more, so that a zoo trained on many towns has seen the kinds of road,
occluder and traffic a user's network brings:

- the main junction: 3, 4 or 5 arms at bearings other than multiples of 90 degrees (evenly spread, then jittered
  by up to +-25 degrees, at least 45 degrees apart), or a merge (a one-way on-ramp joining a two-way road at
  20-35 degrees); priority, signalised or all-way-stop control;
- each arm: 120-230 m, 1-3 lanes each way (minor roads 1-2), 30-60 km/h, straight or curved (the arm's midpoint
  moved 8-35 m sideways), on 4- and 5-arm junctions a side street teeing in 55-110 m out (a second junction);
- buildings along every block (v2vsim/towns/buildings.py): set back 1-10 m from the kerb, 8-40 m frontage, 6-25 m
  deep, gaps 0-14 m and some open lots, 4-30 m tall;
- traffic: 250-1800 background vehicles per hour; a class mix of cars, vans, trucks and buses (SUMO vTypes with
  their real extents, v2vsim/traffic/sumo.py); 0-4 vehicles standing all run, parked at the kerb or waiting in a
  lane (chosen once the network exists, v2vsim/towns/write.py); 4-6 CAVs placed as in the shipped scenarios.

Nothing here looks at the benchmark's networks: the ranges are what a town has, judged on the generator's own
validation towns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

Control = Literal["priority", "traffic_light", "allway_stop"]


@dataclass(frozen=True)
class ArmPlan:
    """One arm of the main junction: a two-way road from the centre out to a fringe node (or a one-way ramp)."""

    bearing_deg: float  # direction from the junction out along the arm, degrees CCW from +x
    length_m: float
    lanes_in: int  # lanes towards the junction
    lanes_out: int  # lanes away from it (0: a one-way on-ramp)
    speed_mps: float
    priority: int  # SUMO edge priority: the main road's arms outrank the minor ones
    curve_m: float  # sideways shift of the arm's midpoint (0: straight; the sign picks the side)
    side_street_at_m: float | None  # a side street tees in this far out (None: none)
    side_street_bearing_deg: float  # its direction from the arm, relative to the arm's bearing


@dataclass(frozen=True)
class BuildingStyle:
    setback_m: tuple[float, float]  # from the kerb, [lo, hi]
    frontage_m: tuple[float, float]
    depth_m: tuple[float, float]
    gap_m: tuple[float, float]
    open_lot_share: float  # share of plots left empty (a car park, a field)
    height_m: tuple[float, float]


@dataclass(frozen=True)
class TownPlan:
    seed: int
    kind: Literal["junction", "merge"]
    control: Control
    arms: tuple[ArmPlan, ...]
    buildings: BuildingStyle
    background_per_hour: float
    vehicle_mix: tuple[tuple[str, float], ...]  # (vType, share), shares summing to 1
    standing: int  # vehicles standing all run
    cavs: int
    tls_cycle_s: float

    @property
    def name(self) -> str:
        return f"town_{self.seed:04d}"


def _bearings(rng: np.random.Generator, n: int) -> list[float]:
    """n arm bearings, evenly spread then jittered, rotated at random, at least 45 degrees apart."""
    for _ in range(100):
        base = float(rng.uniform(0, 360))
        out = [(base + i * 360.0 / n + float(rng.uniform(-25, 25))) % 360 for i in range(n)]
        gaps = np.diff(sorted(out) + [sorted(out)[0] + 360])
        if gaps.min() >= 45:
            return out
    return [(i * 360.0 / n + 17.0) % 360 for i in range(n)]  # not reached in practice


def _angle_between(a: float, b: float) -> float:
    d = abs((a - b + 180) % 360 - 180)
    return d


def _main_road(bearings: list[float]) -> tuple[int, int]:
    """The two arms closest to a straight line through the junction: they form the priority road."""
    best = min(((i, j) for i in range(len(bearings)) for j in range(i + 1, len(bearings))),
               key=lambda ij: abs(180 - _angle_between(bearings[ij[0]], bearings[ij[1]])))
    return best


def _vehicle_mix(rng: np.random.Generator) -> tuple[tuple[str, float], ...]:
    van, truck, bus = float(rng.uniform(0, 0.2)), float(rng.uniform(0, 0.2)), float(rng.uniform(0, 0.1))
    shares = {"car": 1.0 - van - truck - bus, "van": van, "truck": truck, "bus": bus}
    rounded = {k: round(v, 3) for k, v in shares.items()}
    rounded["car"] = round(1.0 - rounded["van"] - rounded["truck"] - rounded["bus"], 3)
    return tuple(rounded.items())


def draw_plan(seed: int) -> TownPlan:
    """The town of this seed (module doc)."""
    rng = np.random.default_rng([0x70A1, seed])  # a stream of its own: town seed s never equals run seed s's
    kind = "merge" if rng.random() < 0.15 else "junction"
    control: Control = ("priority", "traffic_light", "allway_stop")[int(rng.choice(3, p=[0.45, 0.35, 0.2]))]
    arms: list[ArmPlan] = []
    main_lanes = int(rng.choice([1, 2, 3], p=[0.35, 0.45, 0.2]))
    main_speed = float(rng.choice([8.33, 11.11, 13.89, 16.67]))
    if kind == "merge":
        control = "priority"
        road = float(rng.uniform(0, 360))
        ramp_off = float(rng.uniform(20, 35)) * (1 if rng.random() < 0.5 else -1)
        # The ramp comes in from behind the road's direction of travel (bearing road+180 +- the merge angle);
        # right-hand traffic merges from the right, so it lies clockwise of the incoming arm.
        for bearing, lanes_in, lanes_out, prio in ((road + 180, main_lanes, main_lanes, 3),
                                                    (road, main_lanes, main_lanes, 3),
                                                    (road + 180 + abs(ramp_off), 1, 0, 1)):
            arms.append(ArmPlan(bearing % 360, float(rng.uniform(140, 230)), lanes_in, lanes_out,
                                main_speed if prio == 3 else 11.11, prio, 0.0, None, 0.0))
    else:
        n = int(rng.choice([3, 4, 5], p=[0.35, 0.45, 0.2]))
        bearings = _bearings(rng, n)
        main = _main_road(bearings)
        minor_lanes = int(rng.choice([1, 2], p=[0.6, 0.4]))
        sides = 0
        for i, b in enumerate(bearings):
            is_main = i in main
            lanes = main_lanes if is_main else minor_lanes
            curve = float(rng.uniform(8, 35)) * (1 if rng.random() < 0.5 else -1) if rng.random() < 0.35 else 0.0
            side_at = None
            if n >= 4 and curve == 0.0 and sides < 2 and rng.random() < 0.4:
                side_at = float(rng.uniform(55, 110))
                sides += 1
            arms.append(ArmPlan(b, float(rng.uniform(120, 230)), lanes, lanes,
                                main_speed if is_main else float(rng.choice([8.33, 11.11, 13.89])),
                                3 if is_main else 2, curve, side_at,
                                float(rng.uniform(60, 120)) * (1 if rng.random() < 0.5 else -1)))
    setback_lo = float(rng.uniform(1, 7))
    height_lo = float(rng.uniform(4, 12))
    style = BuildingStyle(
        setback_m=(setback_lo, min(10.0, setback_lo + float(rng.uniform(0.5, 3)))),
        frontage_m=(float(rng.uniform(8, 15)), float(rng.uniform(18, 40))),
        depth_m=(float(rng.uniform(6, 12)), float(rng.uniform(14, 25))),
        gap_m=(0.0, float(rng.uniform(2, 14))),
        open_lot_share=float(rng.uniform(0, 0.35)),
        height_m=(height_lo, min(30.0, height_lo + float(rng.uniform(3, 18)))),
    )
    return TownPlan(
        seed=seed, kind=kind, control=control, arms=tuple(arms), buildings=style,
        background_per_hour=float(round(math.exp(rng.uniform(math.log(250), math.log(1800))))),
        vehicle_mix=_vehicle_mix(rng), standing=int(rng.choice(5, p=[0.3, 0.25, 0.2, 0.15, 0.1])),
        cavs=int(rng.choice([4, 5, 6], p=[0.5, 0.3, 0.2])), tls_cycle_s=float(rng.choice([30, 40, 50, 60])),
    )
