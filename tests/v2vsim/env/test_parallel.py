"""The PettingZoo environment: API conformance on both traffic backends, and that its two ends agree
with the run (sending nothing is `none` fusion at zero bytes; sending everything is a full-message run)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test

from v2vsim.config import ConfigError
from v2vsim.env import env, parallel_env

REPO = Path(__file__).resolve().parents[3]
INTERSECTION = str(REPO / "scenarios" / "intersection.yaml")
HIGHWAY = str(REPO / "scenarios" / "highway_intersection.yaml")
FAST = {"features": "pooled", "receivers": "egos"}


@pytest.mark.parametrize("scenario", [INTERSECTION, HIGHWAY], ids=["sumo", "highway-env"])
def test_parallel_api(scenario: str) -> None:
    e = parallel_env(scenario, **FAST)
    try:
        parallel_api_test(e, num_cycles=3)
    finally:
        e.close()


def test_aec_wrapper_passes_api_test() -> None:
    e = env(INTERSECTION, **FAST)
    e.unwrapped.max_cycles = 2
    try:
        api_test(e, num_cycles=4)
    finally:
        e.close()


def test_same_seed_same_episode_and_spaces_hold() -> None:
    e = parallel_env(INTERSECTION, receivers="egos")
    try:
        runs = []
        for _ in range(2):
            obs, _ = e.reset(seed=11)
            steps = [obs]
            for _ in range(2):
                obs, rew, *_ = e.step({a: np.array([0.3], np.float32) for a in e.agents})
                steps.append((obs, rew))
            runs.append(steps)
        a, b = runs
        assert np.array_equal(a[0]["cav1"]["features"], b[0]["cav1"]["features"])
        assert a[2][1] == b[2][1]
        for agent, o in a[2][0].items():
            assert e.observation_space(agent).contains(o)
            assert o["features"].shape == (64, 64, 64)  # the zoo's 64 x 64 grid
        assert e.action_space("cav0") is e.action_space("cav0")
    finally:
        e.close()


def test_sending_nothing_is_none_fusion_at_zero_bytes() -> None:
    e = parallel_env(INTERSECTION, features="pooled", methods=("cobevt", "v2vnet", "none"))
    try:
        e.reset(seed=4)
        for _ in range(3):
            _, rew, _, _, info = e.step(dict.fromkeys(e.agents, np.zeros(1, np.float32)))
            assert all(i["bytes"] == 0 for i in info.values())
            assert all(r == 0.0 for r in rew.values())
        for receiver, scores in e.scores.items():
            assert scores["none"].frames == 3, receiver
            for m in ("cobevt", "v2vnet"):
                assert scores[m].vehicle.counts == scores["none"].vehicle.counts, (receiver, m)
        assert sum(map(sum, e.bytes_sent.values())) == 0
    finally:
        e.close()


def test_sending_everything_matches_a_full_message_run(tmp_path: Path) -> None:
    """Unlimited bandwidth and no latency: every neighbour in range is fused in the frame it was sent, as in the run."""
    sets = ["seed=5", "comm.bandwidth_mbps=null", "output.rerun=false"]
    frames = 4
    argv = [sys.executable, "-m", "v2vsim.cli", "run", INTERSECTION, "--frames", str(frames), "--methods",
            "none,cobevt,fcooper", "--out", str(tmp_path)]
    for s in sets:
        argv += ["--set", s]
    subprocess.run(argv, check=True, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=600)
    run = json.loads((tmp_path / "metrics.json").read_text())["methods"]

    e = parallel_env(INTERSECTION, features="pooled", receivers="egos", methods=("cobevt", "fcooper"),
                     seed=5, **{"comm.bandwidth_mbps": None})
    try:
        e.reset()
        for _ in range(frames):
            _, _, _, _, info = e.step(dict.fromkeys(e.agents, np.ones(1, np.float32)))
            assert info["cav0"]["neighbours"], "a frame without neighbours would fall back to `none`"
            assert info["cav0"]["bytes"] > 0
        for m in ("cobevt", "fcooper"):
            assert round(e.scores["cav0"][m].vehicle.iou, 4) == run[m]["iou_vehicle"], m
        assert round(e.scores["cav0"]["cobevt"].vehicle.iou, 4) != run["none"]["iou_vehicle"]
    finally:
        e.close()


def test_partial_shares_send_fewer_bytes_and_the_picture_shows_them() -> None:
    e = parallel_env(INTERSECTION, features="pooled", receivers="egos", render_mode="rgb_array")
    try:
        e.reset(seed=2)
        sizes = {}
        for frac in (0.05, 0.25, 1.0):
            _, _, _, _, info = e.step(dict.fromkeys(e.agents, np.array([frac], np.float32)))
            sizes[frac] = info["cav1"]["bytes"]
            assert info["cav1"]["cells"] == min(4096, round(frac * 4096)) or frac == 1.0
        assert 0 < sizes[0.05] < sizes[0.25] < sizes[1.0]
        img = e.render()
        assert img.dtype == np.uint8 and img.shape == (256, 3 * 256 + 8, 3)
        assert img[:, -256:].reshape(-1, 3).max(axis=0).min() > 100  # coloured sent cells are drawn
    finally:
        e.close()


def test_bad_options_and_actions_are_clear_errors() -> None:
    with pytest.raises(ConfigError, match="methods"):
        parallel_env(INTERSECTION, methods=("late",))
    with pytest.raises(ConfigError, match="comm.drop.p"):
        parallel_env(INTERSECTION, **{"comm.drop.p": 2})
    e = parallel_env(INTERSECTION, **FAST)
    try:
        e.reset(seed=1)
        with pytest.raises(ValueError, match="action of cav0"):
            e.step({"cav0": np.array([np.nan])})
    finally:
        e.close()


def test_an_agent_whose_vehicle_leaves_is_terminated_and_never_returns() -> None:
    """The traffic is real; only the backend's step is wrapped so that cav3's vehicle leaves at frame 2."""
    import dataclasses

    e = parallel_env(INTERSECTION, **FAST)
    try:
        e.reset(seed=6)
        step = e._backend.step

        def without_cav3():  # noqa: ANN202
            w = step()
            if w.frame < 2:
                return w
            return dataclasses.replace(w, actors=tuple(a for a in w.actors if a.id != "cav3"))

        e._backend.step = without_cav3
        _, _, term, trunc, _ = e.step(dict.fromkeys(e.agents, np.ones(1, np.float32)))
        assert not any(term.values()) and "cav3" in e.agents
        obs, rew, term, trunc, info = e.step(dict.fromkeys(e.agents, np.ones(1, np.float32)))
        assert term == {"cav0": False, "cav1": False, "cav2": False, "cav3": True} and not any(trunc.values())
        assert e.observation_space("cav3").contains(obs["cav3"]) and not obs["cav3"]["features"].any()
        assert e.agents == ["cav0", "cav1", "cav2"] and "cav3" in rew
        obs, rew, term, _, info = e.step(dict.fromkeys(e.agents, np.ones(1, np.float32)))
        assert set(obs) == set(rew) == set(term) == {"cav0", "cav1", "cav2"}
        assert "cav3" not in info  # it sends nothing more; its last message may still be fused while fresh, as in a run
    finally:
        e.close()
