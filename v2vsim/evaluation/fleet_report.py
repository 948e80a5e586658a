"""The fleet's report, when several CAVs drive (`cavs.ego: all` or a list): each ego writes only its own vehicle's
`driving` block (ego_<id>/metrics.json); once every ego has finished, the runner merges them into the run's own
metrics.json and report.md, so that the run's outputs measure the fleet (docs/scenario.md "control").

The merged block keeps the shape of one ego's (v2vsim.control.measures.driving_block): `vehicles` holds every driven
vehicle's entry as its own ego measured it, `total` is recomputed over all of them (counts added, extremes taken,
the mean driving score, success only when every driven vehicle succeeded), and `total.fleet` says what summing per
vehicle cannot: a contact between two driven vehicles is one collision of the fleet though each of the two counts it.

    fleet.driven                  driven vehicles (with frames)
    fleet.collisions_between_driven  distinct pairs of driven vehicles that touched
    fleet.collisions_with_others  distinct (driven, not driven) pairs that touched
    fleet.collisions              the two added: the fleet's distinct contacts
    fleet.vehicles_in_collision   driven vehicles with at least one contact
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from v2vsim.control.critical import critical_total
from v2vsim.control.measures import driving_block
from v2vsim.control.score import total_score
from v2vsim.evaluation.report_md import driving_md
from v2vsim.run_outcome import ego_folder


def fleet_counts(vehicles: Mapping[str, Mapping[str, Any]]) -> dict[str, int]:
    """`total.fleet` (module doc) from the driven vehicles' entries (`collided_with`: the ids each touched)."""
    driven = [v for v, m in vehicles.items() if m.get("frames")]
    between: set[frozenset[str]] = set()
    others: set[tuple[str, str]] = set()
    for v in driven:
        for o in vehicles[v].get("collided_with", ()):
            if o in driven:
                between.add(frozenset((v, o)))
            else:
                others.add((v, o))
    touched = {v for v in driven if vehicles[v].get("collided_with")}
    return {"driven": len(driven), "collisions_between_driven": len(between),
            "collisions_with_others": len(others), "collisions": len(between) + len(others),
            "vehicles_in_collision": len(touched)}


def merge_driving(blocks: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One `driving` block for the fleet from each ego's own (the first one's header; `driven` lists them all)."""
    vehicles: dict[str, Any] = {}
    for b in blocks:
        vehicles.update(b["vehicles"])
    header = {k: v for k, v in blocks[0].items() if k not in ("vehicles", "total")}
    header["driven"] = [v for b in blocks for v in b.get("driven", b["vehicles"])]
    merged = driving_block(vehicles, header)
    scored = [v for v in vehicles.values() if v.get("frames")]
    if any("driving_score" in v for v in scored):
        merged["total"] |= total_score(scored)
    merged["total"] |= critical_total(vehicles, header["driven"][0])
    merged["total"]["fleet"] = fleet_counts(vehicles)
    return merged


def fleet_driving_md(fleet: Mapping[str, int]) -> list[str]:
    """report.md's line on `total.fleet`, below the merged driving section."""
    return ["", f"Fleet: {fleet['driven']} driven vehicles; {fleet['collisions']} distinct contacts "
            f"({fleet['collisions_between_driven']} between driven vehicles, {fleet['collisions_with_others']} with "
            f"others), {fleet['vehicles_in_collision']} driven vehicles in a collision "
            "(v2vsim/evaluation/fleet_report.py)."]


def merge_fleet(out: Path, egos: list[str]) -> bool:
    """Write the fleet's driving into the run's metrics.json and report.md when more than one ego drove and each
    wrote its `driving` block; False (nothing written) otherwise. Each ego's own file stays as it wrote it."""
    if len(egos) < 2:
        return False
    docs = []
    for e in egos:
        try:
            docs.append(json.loads((ego_folder(out, egos, e) / "metrics.json").read_text()))
        except (OSError, ValueError):
            return False
    if not all(isinstance(d.get("driving"), dict) for d in docs):
        return False
    main = docs[0]
    own = main["driving"]
    merged = merge_driving([d["driving"] for d in docs])
    main["driving"] = merged
    (out / "metrics.json").write_text(json.dumps(main, indent=2))
    report = out / "report.md"
    if report.is_file():
        text = report.read_text()
        before = "\n".join(driving_md(own))
        after = "\n".join(driving_md(merged) + fleet_driving_md(merged["total"]["fleet"]))
        report.write_text(text.replace(before, after) if before in text else text + "\n" + after + "\n")
    return True
