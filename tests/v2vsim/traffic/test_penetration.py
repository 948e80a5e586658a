"""cavs.penetration (v2vsim/traffic/penetration.py): which placed vehicles are connected, drawn reproducibly per seed,
nested across shares, the egos always; and the SUMO world marks the others as ordinary vehicles."""

from __future__ import annotations

from pathlib import Path

import pytest

from v2vsim.config import ConfigError, load_scenario
from v2vsim.traffic.penetration import connected_cavs, connected_share_count

REPO = Path(__file__).resolve().parents[3]
TJ = REPO / "scenarios" / "t_junction_occluded.yaml"
SHARES = (0, 0.25, 0.5, 0.75, 1)


def _connected(share: float | None, seed: int = 0, *extra: str) -> list[str]:
    sets = [f"seed={seed}", "cavs.count=5", *extra] + ([f"cavs.penetration={share}"] if share is not None else [])
    return connected_cavs(load_scenario(TJ, sets))


def test_a_share_connects_its_round_share_of_the_others_and_the_ego_always() -> None:
    assert [connected_share_count(s, 4) for s in SHARES] == [0, 1, 2, 3, 4]
    assert [connected_share_count(s, 3) for s in SHARES] == [0, 1, 2, 2, 3]  # 0.75 x 3 = 2.25, 0.5 x 3 = 1.5
    assert _connected(None) == ["cav0", "cav1", "cav2", "cav3", "cav4"]  # null: as before, every one
    assert _connected(0) == ["cav0"] and _connected(1) == _connected(None)
    for s in SHARES:
        got = _connected(s)
        assert got[0] == "cav0" and len(got) == 1 + connected_share_count(s, 4)
    assert _connected(0, 0, "cavs.ego=[cav2]") == ["cav2"]  # the ego, whichever it is
    assert _connected(0, 0, "cavs.ego=all") == _connected(None)  # every placed vehicle drives: all connected


def test_the_draw_is_reproducible_per_seed_nested_across_shares_and_differs_between_seeds() -> None:
    for seed in range(6):
        draws = [_connected(s, seed) for s in SHARES]
        assert draws == [_connected(s, seed) for s in SHARES]  # the same seed, the same vehicles
        for lo, hi in zip(draws, draws[1:], strict=False):
            assert set(lo) <= set(hi)  # a higher share adds vehicles, it does not reshuffle them
    assert len({tuple(_connected(0.25, seed)) for seed in range(12)}) > 1


@pytest.mark.parametrize(("sets", "expect"), [
    (["cavs.penetration=1.5"], "cavs.penetration"),
    (["cavs.penetration=0.5", "traffic.backend=highway-env", "traffic.hidden_foe=null", "control=null"],
     "cavs.penetration: needs traffic.backend 'sumo'"),
])
def test_a_bad_penetration_is_refused_naming_the_key(sets: list[str], expect: str) -> None:
    with pytest.raises(ConfigError, match=expect):
        load_scenario(TJ, sets)


def test_a_placed_vehicle_left_unconnected_is_an_ordinary_vehicle_in_the_world() -> None:
    from v2vsim.traffic import make_backend

    sc = load_scenario(TJ, ["seed=0", "cavs.count=5", "cavs.penetration=0.5", "control=null"])
    with make_backend(sc) as backend:
        world = backend.reset()
        for _ in range(3):
            world = backend.step()
    placed = {f"cav{i}" for i in range(5)}
    assert [a.id for a in world.cavs] == connected_cavs(sc)
    assert placed - set(connected_cavs(sc)) <= {a.id for a in world.actors if not a.cav}
