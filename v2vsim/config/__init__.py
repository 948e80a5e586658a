"""The scenario YAML (DESIGN.md "Scenario YAML"): typed schema, defaults, overrides, clear errors.

A scenario is loaded once into frozen dataclasses (`Scenario`). Each field carries what is
allowed; unknown keys, wrong types and out-of-range values raise `ConfigError` naming the
file, the key path and what is allowed. Input paths are relative to the YAML file;
`output.dir` is relative to the working directory (so a shipped scenario found by name, whose YAML may sit
in a read-only site-packages, writes its runs under the working directory, e.g. runs/intersection).

Modules (each imports only those above it):
- `errors`: `ConfigError`;
- `schema`: the frozen dataclasses (`Scenario` and every section), the field helpers and the constants
  (`SEED_MAX`, `METHODS`: the live list of models.registry, plugins included; `ENCODERS_BY_MODALITY`);
- `validate`: `_Loader`, which checks a raw mapping against the schema (types, ranges, unknown keys, paths);
- `checks`: the checks across fields of a loaded scenario, `check_output_dir`, and `check_plugins` (the fusion
  plugins a scenario requests, imported and checked: models.registry);
- `shipped`: the shipped scenarios (names, descriptions, where they are) and `find_scenario`, which turns a
  SCENARIO argument (a path or a shipped name) into a YAML file;
- `load`: the strict YAML loader, `parse_override`, `apply_overrides`, `load_scenario`, `scenario_from_dict`.

The public API is re-exported here: import it from `v2vsim.config`.
"""

from v2vsim.config.checks import check_output_dir, check_plugins
from v2vsim.config.errors import ConfigError
from v2vsim.config.load import apply_overrides, load_scenario, neighbours_silent, parse_override, scenario_from_dict
from v2vsim.config.schema import (
    ENCODERS_BY_MODALITY,
    METHODS,
    SEED_MAX,
    AuthConfig,
    BevConfig,
    CamerasConfig,
    CavsConfig,
    ChannelConfig,
    CommConfig,
    ControlConfig,
    DropConfig,
    EvaluationConfig,
    HiddenFoeConfig,
    IdmConfig,
    LatencyConfig,
    LidarConfig,
    MeetConfig,
    OutputConfig,
    PerceptionConfig,
    PoseNoiseConfig,
    Scenario,
    SensorsConfig,
    ShareConfig,
    SsmConfig,
    TrafficConfig,
    TransportConfig,
)
from v2vsim.config.shipped import describe, find_scenario, scenarios_dir, shipped_scenarios

__all__ = [
    "ENCODERS_BY_MODALITY",
    "METHODS",
    "SEED_MAX",
    "AuthConfig",
    "BevConfig",
    "CamerasConfig",
    "CavsConfig",
    "ChannelConfig",
    "CommConfig",
    "ConfigError",
    "ControlConfig",
    "DropConfig",
    "EvaluationConfig",
    "HiddenFoeConfig",
    "IdmConfig",
    "LatencyConfig",
    "LidarConfig",
    "MeetConfig",
    "OutputConfig",
    "PerceptionConfig",
    "PoseNoiseConfig",
    "Scenario",
    "SensorsConfig",
    "ShareConfig",
    "SsmConfig",
    "TrafficConfig",
    "TransportConfig",
    "apply_overrides",
    "check_output_dir",
    "check_plugins",
    "describe",
    "find_scenario",
    "load_scenario",
    "neighbours_silent",
    "parse_override",
    "scenario_from_dict",
    "scenarios_dir",
    "shipped_scenarios",
]
