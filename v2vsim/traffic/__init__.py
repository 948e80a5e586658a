"""Traffic backends: a simulator seen as a sequence of WorldStates (see `base.TrafficBackend`).

`make_backend(scenario)` picks the backend named by `traffic.backend`. The concrete modules are
imported lazily so that importing `v2vsim.traffic` loads neither libsumo nor highway-env.
"""

from __future__ import annotations

from v2vsim.config import ConfigError, Scenario
from v2vsim.traffic.base import BackendBase, TrafficBackend, cav_id

__all__ = ["BackendBase", "TrafficBackend", "cav_id", "make_backend"]


def make_backend(scenario: Scenario, ssm_file: str | None = None, closed_loop: bool = False) -> TrafficBackend:
    """The scenario's traffic backend, not yet started: call `reset()` (or use it in `with`). closed_loop: the
    caller commands the driven vehicles (the run's driver); any other user of a scenario with a `control` section
    would get vehicles that hold their speed forever, so it is refused. ssm_file: where a closed-loop SUMO run
    logs its SSM device."""
    if scenario.control is not None and not closed_loop:
        raise ConfigError(f"{scenario.source}: control: a closed loop runs only in `v2vsim run` and `sweep` (its "
                          "vehicles follow the ego's plans); remove the section, or --set control=null, for this")
    if scenario.traffic.backend == "sumo":
        from v2vsim.traffic.sumo import SumoBackend

        return SumoBackend(scenario, ssm_file=ssm_file)
    if scenario.traffic.backend == "highway-env":
        from v2vsim.traffic.highway import HighwayEnvBackend

        return HighwayEnvBackend(scenario)
    raise ValueError(f"{scenario.source}: traffic.backend: unknown backend {scenario.traffic.backend!r}")
