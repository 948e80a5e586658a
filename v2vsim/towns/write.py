"""One town on disk: its SUMO network, its buildings and a scenario YAML that `v2vsim run` takes as it is.

    OUT/town_0042/town_0042.nod.xml, .edg.xml, .con.xml   the roads as drawn (v2vsim/towns/roads.py)
    OUT/town_0042/town_0042.net.xml                       built by netconvert
    OUT/town_0042/town_0042.poly.xml                      the buildings (v2vsim/towns/buildings.py)
    OUT/town_0042/town_0042.yaml                          the scenario (paths relative to it)

The scenario is the shipped intersection's (sensors, BEV, channel, every method, CAVs placed by `cavs.meet` so
they meet from frame 0) with the town's traffic: its density, class mix and standing vehicles. The standing
vehicles are chosen here, from the built network: on edges with two lanes or more (a one-lane road would be
blocked for good) and straight, parked at the kerb in the third of the lane nearest its end, or waiting at a
junction's stop line in an inner lane.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sumolib
import yaml

from v2vsim.towns.buildings import write_poly
from v2vsim.towns.plan import TownPlan, draw_plan
from v2vsim.towns.roads import build_net

_STANDING_TYPES = ("car", "van", "truck", "bus")


@dataclass(frozen=True)
class TownFiles:
    name: str
    scenario: Path
    net: Path
    buildings: Path
    n_buildings: int


def _standing(plan: TownPlan, net: sumolib.net.Net) -> list[dict]:
    rng = np.random.default_rng([0x70A1, plan.seed, 3])
    curved = {f"A{i}" for i, a in enumerate(plan.arms) if a.curve_m}
    # straight edges only: on a curved one SUMO refused a stop at positions that lie on the lane (libsumo 1.28,
    # "not downstream the current route")
    edges = sorted((e for e in net.getEdges() if e.getFunction() != "internal" and e.getLaneNumber() >= 2
                    and e.getLength() > 40 and e.getID().split("_")[0] not in curved), key=lambda e: e.getID())
    out: list[dict] = []
    for _ in range(plan.standing if edges else 0):
        edge = edges[int(rng.integers(len(edges)))]
        length = edge.getLane(0).getLength()
        kind = _STANDING_TYPES[int(rng.choice(4, p=[0.4, 0.25, 0.2, 0.15]))]
        # parked at the kerb near the lane's end (farther back libsumo 1.28 refused some stops: "not downstream the
        # current route"; v2vsim/traffic/sumo_standing.py holds such a vehicle in place instead)
        if rng.random() < 0.6:
            to_end = round(float(rng.uniform(15, max(15.0, 0.3 * length))), 1)
            entry = {"edge": edge.getID(), "lane": 0, "to_end_m": to_end}
        elif edge.getToNode().getID()[0] in "CS":  # at a junction's stop line in an inner lane (queued to turn)
            entry = {"edge": edge.getID(), "lane": int(rng.integers(1, edge.getLaneNumber())), "to_end_m": 0.5}
        else:
            continue
        if any(o["edge"] == entry["edge"] and o["lane"] == entry["lane"]
               and abs(o["to_end_m"] - entry["to_end_m"]) < 20 for o in out):
            continue
        out.append({**entry, "type": kind})
    return out


def scenario_doc(plan: TownPlan, net_name: str, poly_name: str, standing: list[dict]) -> dict:
    """The scenario YAML of a town (module doc) as plain data."""
    return {
        "name": plan.name,
        "seed": 0,
        "duration_s": 20,
        "rate_hz": 10,
        "traffic": {
            "backend": "sumo",
            "net": net_name,
            "buildings": poly_name,
            "background_per_hour": plan.background_per_hour,
            "building_height_m": [round(plan.buildings.height_m[0], 1), round(plan.buildings.height_m[1], 1)],
            "vehicle_mix": dict(plan.vehicle_mix),
            "standing": standing,
        },
        "cavs": {"count": plan.cavs, "ego": "first", "arrival_s": [0, 4],
                 "meet": {"neighbours": 2, "share": 0.9, "trials": 24}},
        "output": {"dir": f"runs/{plan.name}", "rerun": True},
    }


def write_town(seed: int, out: Path) -> TownFiles:
    """Generate the town of `seed` into `out/<name>/` (module doc); deterministic per seed."""
    plan = draw_plan(seed)
    folder = out / plan.name
    net_path = build_net(plan, folder)
    net = sumolib.net.readNet(str(net_path), withInternal=True)
    poly_path = folder / f"{plan.name}.poly.xml"
    n_buildings = write_poly(plan, net, poly_path)
    doc = scenario_doc(plan, net_path.name, poly_path.name, _standing(plan, net))
    header = (f"# Generated town {plan.name} (v2vsim towns, seed {seed}): {plan.kind}, {len(plan.arms)} arms, "
              f"{plan.control} control, {n_buildings} buildings.\n# Regenerate: v2vsim towns --seeds {seed} "
              f"--out DIR. Sources of the net: {plan.name}.nod.xml / .edg.xml / .con.xml (netconvert).\n")
    scenario = folder / f"{plan.name}.yaml"
    scenario.write_text(header + yaml.safe_dump(doc, sort_keys=False))
    return TownFiles(plan.name, scenario, net_path, poly_path, n_buildings)
