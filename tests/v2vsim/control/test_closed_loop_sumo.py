"""The closed loop on the SUMO side (issue 46): without a control section the traffic is exactly what it was
before closed loops existed; with one, the driven vehicle follows its commands, SUMO's safety checks are off for
it, and each world says what the planner may know of its route and what SUMO measured."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from v2vsim.config import ConfigError, load_scenario
from v2vsim.control.measures import ssm_conflicts
from v2vsim.traffic import make_backend
from v2vsim.world.serialize import world_from_bytes, world_to_bytes

ROOT = Path(__file__).resolve().parents[3]
T_JUNCTION = ROOT / "scenarios" / "t_junction.yaml"
# sha256 of the world messages of frames 0..40 of the shipped T-junction (seed 0), computed with the code before
# closed loops existed (commit b1fc6b3): open-loop traffic must stay bit for bit what it was
OPEN_LOOP_WORLDS = "f221d3c8f4bb4623553b72057dc785be3c5e50aa90f61d669536c6fc6cde80f8"


def test_without_control_the_worlds_are_bit_for_bit_those_of_before() -> None:
    h = hashlib.sha256()
    with make_backend(load_scenario(T_JUNCTION)) as b:
        w = b.reset()
        h.update(world_to_bytes(w))
        for _ in range(40):
            w = b.step()
            assert w.driven == ()
            h.update(world_to_bytes(w))
    assert h.hexdigest() == OPEN_LOOP_WORLDS


def test_a_driven_vehicle_follows_its_commands_and_reports_its_route(tmp_path: Path) -> None:
    sc = load_scenario(T_JUNCTION, ["control.method=none", "duration_s=6"])
    ssm = tmp_path / "ssm.xml"
    with make_backend(sc, ssm_file=str(ssm), closed_loop=True) as b:
        w = b.reset()
        (d,) = w.driven
        assert d.id == "cav0" and d.path.shape[1] == 2 and len(d.path) > 10
        ego = w.actor("cav0")
        assert ego is not None and np.hypot(d.path[0, 0] - ego.pose.x, d.path[0, 1] - ego.pose.y) < ego.extent[0]
        assert d.stop_m is not None and d.conflict_zone is not None  # cav0 is on the stem: it must yield
        again = world_from_bytes(world_to_bytes(w), w.static).driven[0]
        assert again.id == d.id and np.allclose(again.path, d.path, atol=0.01) and again.stop_m == d.stop_m
        for _ in range(5):
            b.command({"cav0": -50.0})  # speed mode 0: no SUMO deceleration limit
            w = b.step()
        assert w.actor("cav0").speed == 0.0  # type: ignore[union-attr]
        for _ in range(30):
            b.command({"cav0": 2.0})
            w = b.step()
        assert w.actor("cav0").speed == pytest.approx(6.0)  # 30 steps of 2 m/s^2 at 10 Hz  # type: ignore[union-attr]
        assert w.driven[0].odometer_m > d.odometer_m + 8  # 0.5 a t^2 = 9 m
    assert ssm.is_file() and ssm_conflicts(ssm) is not None


@pytest.mark.parametrize(("override", "key"), [
    ("traffic.backend=highway-env", "control"),
    ("control.method=attfuse", "control.method"),
    ("control.actuation_delay_frames=1", "control.actuation_delay_frames"),
    ("control.idm.max_decel_mps2=0", "control.idm.max_decel_mps2"),
])
def test_bad_control_settings_are_one_line_errors(override: str, key: str) -> None:
    base = ["control.method=cobevt", "perception.methods=[none,cobevt]"]
    with pytest.raises(ConfigError) as e:
        load_scenario(T_JUNCTION, [*base, override])
    assert f": {key}:" in str(e.value) and "\n" not in str(e.value)


def test_only_the_run_s_driver_may_start_a_closed_loop_backend(tmp_path: Path) -> None:
    """`v2vsim frame`, `dataset` and the env step the backend without commanding anyone: the driven vehicle would
    hold its speed for ever, so a control section there is a one-line error, exit 2."""
    with pytest.raises(ConfigError, match="control: a closed loop runs only in"):
        make_backend(load_scenario(T_JUNCTION, ["control.method=none"]))
    done = subprocess.run([sys.executable, "-m", "v2vsim.cli", "frame", str(T_JUNCTION), "--at", "0", "--out",
                           str(tmp_path), "--set", "control.method=none"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr


def test_a_closed_loop_without_an_ssm_file_writes_nothing_where_it_runs(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """issue 52: SUMO's default SSM output is ssm_<vehicle>.xml in the working directory (ssm_cav0.xml was once
    committed at the repository's root); with no ssm_file the backend gives it a scratch folder it removes."""
    here = tmp_path / "cwd"
    here.mkdir()
    monkeypatch.chdir(here)
    sc = load_scenario(T_JUNCTION, ["control.method=none", "duration_s=2"])
    with make_backend(sc, closed_loop=True) as b:
        b.reset()
        for _ in range(5):
            b.command({"cav0": 1.0})
            b.step()
    assert sorted(p.name for p in here.iterdir()) == []
