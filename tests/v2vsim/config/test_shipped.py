"""A SCENARIO argument is a path or the name of a shipped scenario (v2vsim.config.shipped), for every command."""

from __future__ import annotations

from pathlib import Path

import pytest

from v2vsim.config import ConfigError, describe, find_scenario, load_scenario, scenarios_dir, shipped_scenarios
from v2vsim.study.sweep import SweepArgs, prepare

REPO = Path(__file__).resolve().parents[3]
NAMES = sorted(p.stem for p in (REPO / "scenarios").glob("*.yaml"))


def test_the_checkout_ships_its_scenarios_folder() -> None:
    assert scenarios_dir() == REPO / "scenarios"
    assert list(shipped_scenarios()) == NAMES and "intersection" in NAMES


@pytest.mark.parametrize("name", NAMES)
def test_a_name_loads_the_shipped_yaml_from_any_folder(name: str, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / name).mkdir()  # a folder of that name (a run's output, say) is no scenario file: the name wins
    sc = load_scenario(name)
    assert Path(sc.source) == REPO / "scenarios" / f"{name}.yaml"
    assert sc.name == name
    # its input paths resolve next to the YAML, wherever the working directory is
    for path in (sc.traffic.net, sc.traffic.buildings):
        assert path is None or Path(path).is_relative_to(REPO / "scenarios")
    # its output goes under the working directory (a wheel's YAML sits in site-packages)
    assert not Path(sc.output.dir).is_absolute() and sc.output.dir == f"runs/{name}"
    assert describe(Path(sc.source))  # `v2vsim scenarios` has something to say


def test_a_file_of_that_name_wins_over_the_shipped_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "intersection").write_text("name: mine\ntraffic: {backend: highway-env}\n")
    assert load_scenario("intersection").name == "mine"
    assert find_scenario("intersection") == Path("intersection")


@pytest.mark.parametrize(("arg", "hint"), [
    ("nope", None),
    ("intersection.yaml", "did you mean 'intersection'?"),  # not a file here: names are stems
    ("scenarios/t_junction.yaml", "did you mean 't_junction'?"),
    ("interesction", "did you mean 'intersection'?"),
])
def test_neither_a_file_nor_a_name_is_one_line_listing_the_names(arg: str, hint: str | None, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError) as e:
        load_scenario(arg)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{arg}: scenario file not found")
    assert f"shipped: {', '.join(NAMES)}" in msg
    assert hint is None or hint in msg


def test_description_is_the_first_sentence_of_the_opening_comment(tmp_path: Path) -> None:
    p = tmp_path / "s.yaml"
    p.write_text("# A long first sentence that goes\n#   on to a second line. Then more.\n# Even more.\nname: s\n")
    assert describe(p) == "A long first sentence that goes on to a second line."
    p.write_text("name: s  # no opening comment\n")
    assert describe(p) == ""


def test_sweep_takes_a_name_and_gives_its_runs_the_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    design = prepare(SweepArgs(scenario=Path("intersection"), grid=("comm.drop.p=0,0.1",), seeds="0",
                               out=tmp_path / "sweep", frames=1))
    assert design.scenario == (REPO / "scenarios" / "intersection.yaml").resolve()
    assert all(str(design.scenario) in spec.argv(design.scenario) for spec in design.specs if not spec.replayed)
    assert design.specs[1].replayed  # drop.p=0.1 replays drop.p=0's recording: the file is in its header
