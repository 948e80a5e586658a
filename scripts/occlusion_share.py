"""How often a hidden-foe scenario gives its critical encounter, from the SUMO backend alone (no agents, no models).

    PYTHONPATH=. python scripts/occlusion_share.py [SCENARIO] [--seeds 0-19] [--set KEY=VALUE ...]

Per seed the backend runs open loop (SUMO drives the ego, which yields correctly) over the scenario's duration, and
the encounter counts when all three hold:
  timing    foe0's front enters the main junction's outline (sumolib net.getNode(junction).getShape()) within
            [-1, +3] s of the moment the ego's front reaches its stop line (the end of its approach lane, less
            `_STOP_TOL_M`: SUMO halts a yielding vehicle just short of it);
  hidden    2 s before that moment, the 2D segment from the ego's front to foe0's centre crosses a building, or the
            footprint of a vehicle standing all run (traffic.standing);
  seen      at that time at least one other CAV has an unblocked segment (centre to centre) to foe0 within 60 m.
A scenario with traffic.hidden_stop instead judges stopped0 (the stopped lead vehicle) the same way; it stands in
the junction's exit lane, so its "junction" time is when the ego's path first holds it: its front is inside the
junction outline never, and the timing counts as met while it still stands when the ego reaches its stop line.
Prints a per-seed table and the share of seeds with the encounter.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import shapely

from v2vsim.config import load_scenario
from v2vsim.traffic import make_backend
from v2vsim.traffic.sumo import SumoBackend, _libsumo
from v2vsim.traffic.sumo_hidden_foe import FOE_ID, sight_blocked
from v2vsim.traffic.sumo_standing import HIDDEN_STOP_ID, STANDING_PREFIX
from v2vsim.world.state import Building

_WINDOW_S = (-1.0, 3.0)  # foe at the junction relative to the ego at its stop line
_LOOK_BEFORE_S = 2.0  # when the sight lines are judged, before the ego reaches its stop line
_SEEN_RANGE_M = 60.0  # another CAV sees the foe within this range
_STOP_TOL_M = 1.5  # a front this close to the end of the approach lane is at the stop line


@dataclass(frozen=True)
class Sample:
    """What one frame says about the encounter."""

    ego_front: tuple[float, float] | None
    ego_at_stop: bool
    foe_front: tuple[float, float] | None
    foe_centre: tuple[float, float] | None
    cav_centres: dict[str, tuple[float, float]]


@dataclass(frozen=True)
class Outcome:
    seed: int
    ego_stop_s: float | None
    foe_junction_s: float | None
    hidden: bool | None
    seers: tuple[str, ...]
    side: str
    offset_s: float | None
    lane: int | None
    trial: int | None  # the CAV placement the look-ahead kept

    @property
    def dt(self) -> float | None:
        if self.ego_stop_s is None or self.foe_junction_s is None:
            return None
        return self.foe_junction_s - self.ego_stop_s

    @property
    def timing(self) -> bool:
        return self.dt is not None and _WINDOW_S[0] <= self.dt <= _WINDOW_S[1]

    @property
    def encounter(self) -> bool:
        return self.timing and bool(self.hidden) and bool(self.seers)


def parse_seeds(text: str) -> list[int]:
    """'0-19' or '0,3,5-7' -> seeds."""
    out: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.partition("-")
        out += list(range(int(lo), int(hi) + 1)) if sep else [int(lo)]
    return out


def _sample(tb: SumoBackend, world, ego: str, approach: str) -> Sample:
    ls = _libsumo()
    present = set(ls.vehicle.getIDList())
    ego_front = ego_at_stop = None
    if ego in present:
        x, y = ls.vehicle.getPosition(ego)
        ego_front = (float(x), float(y))
        lane = ls.vehicle.getLaneID(ego)
        on_approach = lane.startswith(f"{approach}_")
        ego_at_stop = not on_approach or ls.vehicle.getLanePosition(ego) >= ls.lane.getLength(lane) - _STOP_TOL_M
    foe_front = foe_centre = None
    target = FOE_ID if FOE_ID in present else HIDDEN_STOP_ID  # the hidden foe, or the stopped lead vehicle
    if target in present:
        x, y = ls.vehicle.getPosition(target)
        foe_front = (float(x), float(y))
        a = world.actor(target)
        foe_centre = (a.pose.x, a.pose.y)
    cavs = {a.id: (a.pose.x, a.pose.y) for a in world.cavs}
    return Sample(ego_front, bool(ego_at_stop), foe_front, foe_centre, cavs)


def measure(scenario_path: str, seed: int, overrides: list[str]) -> Outcome:
    """Run one seed open loop and judge its encounter (module doc)."""
    sc = load_scenario(scenario_path, ["control=null", *overrides, f"seed={seed}"])  # the traffic, open loop
    with make_backend(sc) as tb:
        assert isinstance(tb, SumoBackend), "the hidden foe needs the sumo backend"
        world = tb.reset()
        ego = tb.hidden_foe.ego if tb.hidden_foe is not None else "cav0"
        approach = next(p.route.approach for p in tb.cav_plans if p.id == ego)
        junction = shapely.Polygon([p[:2] for p in tb._net.getNode(tb.topology.junction).getShape()])
        # vehicles standing all run (traffic.standing: a truck waiting to turn) occlude as buildings do
        buildings = tb.static.buildings + tuple(
            Building(id=a.id, polygon=a.footprint(), height=a.extent[2])
            for a in world.actors if a.id.startswith(STANDING_PREFIX))
        samples = [_sample(tb, world, ego, approach)]  # "foe": foe0, or stopped0 with traffic.hidden_stop
        for _ in range(sc.frames - 1):
            world = tb.step()
            samples.append(_sample(tb, world, ego, approach))
        plan, placement = tb.hidden_foe, tb.placement
    dt = sc.dt
    k_ego = next((k for k, s in enumerate(samples) if s.ego_at_stop), None)
    k_foe = next((k for k, s in enumerate(samples)
                  if s.foe_front is not None and junction.covers(shapely.Point(s.foe_front))), None)
    if sc.traffic.hidden_stop is not None and k_ego is not None and samples[k_ego].foe_front is not None:
        k_foe = k_ego  # the stopped car is there when the ego reaches its stop line: the timing holds
    hidden, seers = None, ()
    k_look = None if k_ego is None else k_ego - round(_LOOK_BEFORE_S / dt)
    if k_look is not None and k_look >= 0:
        s = samples[k_look]
        if s.foe_centre is not None and s.ego_front is not None:
            hidden = sight_blocked(s.ego_front, s.foe_centre, buildings)
            fx, fy = s.foe_centre
            seers = tuple(c for c, (x, y) in s.cav_centres.items()
                          if c != ego and (x - fx) ** 2 + (y - fy) ** 2 <= _SEEN_RANGE_M ** 2
                          and not sight_blocked((x, y), s.foe_centre, buildings))
    return Outcome(seed, None if k_ego is None else k_ego * dt, None if k_foe is None else k_foe * dt, hidden, seers,
                   plan.side if plan is not None else "-", plan.offset_s if plan is not None else None,
                   plan.lane if plan is not None else None, placement.trial if placement is not None else None)


def _fmt(v: float | None, spec: str = "6.1f") -> str:
    return f"{v:{spec}}" if v is not None else " " * (int(spec.split(".")[0]) - 1) + "-"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="t_junction_occluded", help="a YAML path or shipped name")
    ap.add_argument("--seeds", default="0-19", help="e.g. 0-19 or 0,3,5-7")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a scenario override, as for v2vsim run (repeatable)")
    args = ap.parse_args(argv)
    seeds = parse_seeds(args.seeds)
    print(f"{'seed':>4} {'trial':>5} {'side':>5} {'lane':>4} {'offset':>6} {'ego@stop':>8} {'foe@jct':>7} {'dt':>6} "
          f"{'hidden':>6} {'seen by':<16} encounter")
    t0 = time.perf_counter()
    hits = 0
    for seed in seeds:
        o = measure(args.scenario, seed, args.overrides)
        hits += o.encounter
        hidden = "-" if o.hidden is None else ("yes" if o.hidden else "no")
        trial = "-" if o.trial is None else str(o.trial)
        lane = "-" if o.lane is None else str(o.lane)
        print(f"{o.seed:>4} {trial:>5} {o.side:>5} {lane:>4} {_fmt(o.offset_s)} {_fmt(o.ego_stop_s, '8.1f')} "
              f"{_fmt(o.foe_junction_s, '7.1f')} {_fmt(o.dt, '+6.1f')} {hidden:>6} "
              f"{','.join(o.seers) or '-':<16} {'YES' if o.encounter else 'no'}", flush=True)
    took = time.perf_counter() - t0
    print(f"critical encounter in {hits}/{len(seeds)} seeds ({100.0 * hits / len(seeds):.0f} %); "
          f"{took:.1f} s ({took / len(seeds):.2f} s per seed)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
