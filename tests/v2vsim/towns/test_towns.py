"""The town generator: deterministic per seed, every town it makes loads and runs, and what it varies."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import sumolib

from v2vsim.config import load_scenario
from v2vsim.towns import check_town, write_town
from v2vsim.towns.plan import draw_plan
from v2vsim.traffic import make_backend
from v2vsim.traffic.sumo_network import analyse_network

pytestmark = pytest.mark.skipif(shutil.which("netconvert") is None, reason="needs netconvert (v2vsim[towns])")


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_a_seed_gives_the_same_files(tmp_path: Path) -> None:
    a, b = write_town(7, tmp_path / "a"), write_town(7, tmp_path / "b")
    assert _files(a.net.parent) == _files(b.net.parent)
    assert _files(write_town(8, tmp_path / "c").net.parent) != _files(a.net.parent)


def test_plans_vary_what_the_families_vary() -> None:
    plans = [draw_plan(s) for s in range(1000, 1080)]
    arms = {len(p.arms) for p in plans if p.kind == "junction"}
    assert arms == {3, 4, 5}
    assert {p.control for p in plans} == {"priority", "traffic_light", "allway_stop"}
    assert any(p.kind == "merge" for p in plans)
    assert any(a.curve_m for p in plans for a in p.arms)
    assert any(a.side_street_at_m for p in plans for a in p.arms)
    assert {a.lanes_in for p in plans for a in p.arms} == {1, 2, 3}
    bearings = [a.bearing_deg % 90 for p in plans for a in p.arms]
    assert sum(1 for b in bearings if 5 < b < 85) > len(bearings) / 2  # mostly not on the axes
    dens = [p.background_per_hour for p in plans]
    assert min(dens) < 400 and max(dens) > 1400
    assert any(dict(p.vehicle_mix)["bus"] > 0 for p in plans)


@pytest.mark.parametrize("seed", [3, 12, 1004])
def test_every_town_loads_and_steps(tmp_path: Path, seed: int) -> None:
    files = write_town(seed, tmp_path)
    sc = load_scenario(str(files.scenario))
    assert analyse_network(sumolib.net.readNet(str(files.net), withInternal=True)).junction == "C"
    backend = make_backend(sc)
    try:
        world = backend.reset()
        assert sum(a.cav for a in world.actors) == sc.cavs.count
        assert len(backend.static.buildings) == files.n_buildings > 0
        for _ in range(3):
            world = backend.step()
        standing = [a for a in world.actors if a.id.startswith("standing")]
        assert len(standing) == len(sc.traffic.standing)
    finally:
        backend.close()


def test_a_town_runs_end_to_end(tmp_path: Path) -> None:
    """`v2vsim run` takes a generated town's scenario as it is: processes, zenoh, the zoo, a report."""
    files = write_town(12, tmp_path / "towns")
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "v2vsim.cli", "run", str(files.scenario), "--frames", "3",
                           "--methods", "none,cobevt", "--out", str(out), "--set", "output.rerun=false"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert m["scenario"] == "town_0012" and m["frames"] == 3
    assert m["methods"]["cobevt"]["iou_vehicle"] is not None


def test_check_town_names_a_town_that_does_not_start(tmp_path: Path) -> None:
    files = write_town(3, tmp_path)
    text = files.scenario.read_text()
    files.scenario.write_text(text.replace("  standing: []", "  standing: [{edge: nowhere, lane: 0}]"))
    assert "nowhere" in files.scenario.read_text()
    with pytest.raises(Exception, match="town_0003.*nowhere"):
        check_town(files)
