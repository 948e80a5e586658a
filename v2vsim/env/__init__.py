"""A PettingZoo environment over v2vsim: CAVs choose what share of their BEV features to send
(v2vsim.env.parallel). `parallel_env(...)` gives the ParallelEnv, `env(...)` its AEC form."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pettingzoo.utils.conversions import parallel_to_aec

from v2vsim.env.parallel import CooperativePerceptionEnv, EnvOptions, scenario_overrides

__all__ = ["CooperativePerceptionEnv", "EnvOptions", "env", "parallel_env"]


def parallel_env(scenario_path: str | Path, *, render_mode: str | None = None, features: str = "map",
                 methods: tuple[str, ...] | list[str] = ("cobevt",), receivers: str = "all",
                 byte_cost: float = 1e-6, link_window: int = 10, reward: str = "leave_one_out",
                 **overrides: Any) -> CooperativePerceptionEnv:
    """The ParallelEnv of a scenario. `overrides` are scenario keys: `seed=5`, `comm__drop__p=0.3` or
    `**{"comm.drop.p": 0.3}` (values as `--set` takes them); the rest are EnvOptions."""
    options = EnvOptions(features=features, methods=tuple(methods), receivers=receivers,  # type: ignore[arg-type]
                         byte_cost=byte_cost, link_window=link_window, reward=reward)  # type: ignore[arg-type]
    return CooperativePerceptionEnv(scenario_path, render_mode=render_mode, options=options,
                                    overrides=scenario_overrides(overrides))


def env(scenario_path: str | Path, **kwargs: Any):  # noqa: ANN201 - PettingZoo's AEC wrapper type
    """The AEC form (PettingZoo's parallel_to_aec) of `parallel_env(scenario_path, **kwargs)`."""
    return parallel_to_aec(parallel_env(scenario_path, **kwargs))
