"""A contact sheet of generated towns (PNG): so a person can look at what the generator made.

Each panel is one town at frame 0 as the simulator has it (its scenario loaded and reset through the SUMO
backend, so the CAVs stand where `cavs.meet` placed them): roads grey, buildings brown, background vehicles and
the standing ones dark, CAVs blue, the ego red; the title says the town's kind, control, density and counts.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Polygon as PolygonPatch  # noqa: E402

from v2vsim.config import load_scenario  # noqa: E402
from v2vsim.towns.plan import draw_plan  # noqa: E402
from v2vsim.traffic import make_backend  # noqa: E402


def _panel(ax: plt.Axes, scenario: Path) -> None:
    sc = load_scenario(str(scenario))
    backend = make_backend(sc)
    try:
        world = backend.reset()
        static = backend.static
    finally:
        backend.close()
    for road in static.roads:
        ax.add_patch(PolygonPatch(road, closed=True, facecolor="0.75", edgecolor="none"))
    for b in static.buildings:
        ax.add_patch(PolygonPatch(b.polygon, closed=True, facecolor="#9c6b4e", edgecolor="#5a3a28", lw=0.3))
    ego = "cav0"
    for a in world.actors:
        colour = "#d62728" if a.id == ego else ("#1f77b4" if a.cav else "0.15")
        ax.add_patch(PolygonPatch(a.footprint(), closed=True, facecolor=colour, edgecolor="none"))
    plan = draw_plan(int(sc.name.split("_")[-1]))
    arms = f"{len(plan.arms)} arms" if plan.kind == "junction" else "merge"
    ax.set_title(f"{sc.name}: {arms}, {plan.control.replace('_', ' ')}\n"
                 f"{sc.traffic.background_per_hour:g} veh/h, {len(static.buildings)} bldgs, "
                 f"{len(sc.traffic.standing)} standing, {sc.cavs.count} CAVs", fontsize=7)
    ax.set_xlim(-130, 130)
    ax.set_ylim(-130, 130)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def contact_sheet(scenarios: list[Path], out: Path, columns: int = 4) -> Path:
    """Draw up to 12 towns' scenarios into `out` (PNG); its path."""
    scenarios = scenarios[:12]
    rows = max(1, -(-len(scenarios) // columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.4 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, sc in zip(axes.flat, scenarios, strict=False):
        ax.axis("on")
        _panel(ax, sc)
    fig.suptitle("Generated towns at frame 0 (260 x 260 m around the main junction; ego red, CAVs blue)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
